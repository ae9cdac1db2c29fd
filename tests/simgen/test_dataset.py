"""The written dataset, read back through nuscenes-devkit: loading, rendering, labels, metric."""
from __future__ import annotations

import json
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from nuscenes.eval.common.config import config_factory
from nuscenes.eval.detection.evaluate import DetectionEval
from nuscenes.eval.detection.utils import category_to_detection_name
from nuscenes.utils.data_classes import Box, LidarPointCloud
from nuscenes.utils.geometry_utils import points_in_box, view_points
from pyquaternion import Quaternion

from conftest import run_simgen

matplotlib.use("Agg")


def test_check_passes(tiny_dataset):
    proc = run_simgen("check", tiny_dataset)
    assert proc.stdout.strip().endswith("OK")
    assert "2 scenes, 6 samples" in proc.stdout


def test_devkit_loads_and_renders(tiny_nusc, tmp_path):
    nusc = tiny_nusc
    assert len(nusc.scene) == 2 and len(nusc.sample) == 6
    sample = nusc.sample[1]
    assert set(sample["data"]) == {"LIDAR_TOP", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK",
                                   "CAM_BACK_LEFT", "CAM_FRONT_LEFT"}
    nusc.render_sample_data(sample["data"]["CAM_FRONT"], out_path=str(tmp_path / "cam.png"))
    nusc.render_sample_data(sample["data"]["LIDAR_TOP"], nsweeps=3, out_path=str(tmp_path / "lidar.png"))
    assert (tmp_path / "cam.png").stat().st_size > 10_000 and (tmp_path / "lidar.png").stat().st_size > 10_000
    # 20 Hz lidar sweeps between 2 Hz key frames, chained by prev/next.
    sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
    prev = nusc.get("sample_data", sd["prev"])
    assert not prev["is_key_frame"] and sd["timestamp"] - prev["timestamp"] == 50_000
    assert prev["filename"].startswith("sweeps/LIDAR_TOP/")


def test_num_lidar_pts_equals_devkit_count(tiny_nusc):
    nusc = tiny_nusc
    n_checked = 0
    for sample in nusc.sample:
        path, boxes, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
        pts = LidarPointCloud.from_file(path).points
        for box in boxes:
            ann = nusc.get("sample_annotation", box.token)
            assert ann["num_lidar_pts"] == int(points_in_box(box, pts[:3]).sum()), ann["token"]
            n_checked += 1
    positive = sum(a["num_lidar_pts"] > 0 for a in nusc.sample_annotation)
    assert n_checked == len(nusc.sample_annotation) and positive > 50


def test_annotations_follow_the_format(tiny_nusc):
    nusc = tiny_nusc
    for ann in nusc.sample_annotation:
        assert min(ann["size"]) > 0
        assert abs(np.linalg.norm(ann["rotation"]) - 1) < 1e-9
        cat = nusc.get("category", nusc.get("instance", ann["instance_token"])["category_token"])["name"]
        attrs = [nusc.get("attribute", t)["name"] for t in ann["attribute_tokens"]]
        if cat.startswith("movable_object"):
            assert attrs == []
        else:
            assert len(attrs) == 1 and attrs[0].split(".")[0] in {"vehicle", "cycle", "pedestrian"}
    cars = [a for a in nusc.sample_annotation if nusc.get("instance", a["instance_token"])["category_token"]
            == next(c["token"] for c in nusc.category if c["name"] == "vehicle.car")]
    lw = np.array([(a["size"][1], a["size"][0]) for a in cars])
    assert np.median(lw[:, 0]) > 4.0 and np.median(lw[:, 1]) < 2.2   # l ~ 4.6, w ~ 1.95


def test_box_velocity_matches_motion(tiny_nusc):
    """Instance chains give the devkit a velocity; moving attributes go with real speed."""
    nusc = tiny_nusc
    speeds = {}
    for ann in nusc.sample_annotation:
        if ann["prev"] and ann["next"]:
            v = nusc.box_velocity(ann["token"])[:2]
            attrs = [nusc.get("attribute", t)["name"] for t in ann["attribute_tokens"]]
            speeds.setdefault(attrs[0] if attrs else None, []).append(np.hypot(*v))
    assert max(speeds["vehicle.parked"]) < 1e-6
    assert np.median(speeds["pedestrian.moving"]) > 0.4
    assert max(speeds.get("pedestrian.standing", [0.0])) < 0.25


def _gt_as_predictions(nusc, split):
    scenes = set(json.loads((Path(nusc.dataroot) / nusc.version / "splits.json").read_text())[split])
    results, classes, all_classes = {}, set(), set()
    for sample in nusc.sample:
        if nusc.get("scene", sample["scene_token"])["name"] not in scenes:
            continue
        dets = []
        for tok in sample["anns"]:
            ann = nusc.get("sample_annotation", tok)
            name = category_to_detection_name(nusc.get("category", nusc.get("instance", ann["instance_token"])["category_token"])["name"])
            all_classes.add(name)
            if ann["num_lidar_pts"] == 0 or name is None:
                continue
            vel = nusc.box_velocity(tok)[:2]
            attrs = [nusc.get("attribute", t)["name"] for t in ann["attribute_tokens"]]
            dets.append({"sample_token": sample["token"], "translation": ann["translation"], "size": ann["size"],
                         "rotation": ann["rotation"], "velocity": [float(v) if np.isfinite(v) else 0.0 for v in vel],
                         "detection_name": name, "detection_score": 1.0, "attribute_name": attrs[0] if attrs else ""})
            classes.add(name)
        results[sample["token"]] = dets
    return results, classes, all_classes


def test_detection_eval_of_ground_truth_is_perfect(tiny_nusc, tmp_path):
    nusc = tiny_nusc
    results, classes, all_classes = _gt_as_predictions(nusc, "sim-val")
    cfg = config_factory("detection_cvpr_2019")
    # Ranges for every class with GT (the loader indexes them); AP over those with lidar points.
    cfg.class_range = {k: v for k, v in cfg.class_range.items() if k in all_classes}
    cfg.class_names = [k for k in cfg.class_range if k in classes]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"meta": {"use_camera": True, "use_lidar": True, "use_radar": False,
                                         "use_map": False, "use_external": False}, "results": results}))
    ev = DetectionEval(nusc, cfg, str(path), eval_set="sim-val", output_dir=str(tmp_path), verbose=False)
    metrics, _ = ev.evaluate()
    assert {"car", "pedestrian"} <= set(cfg.class_names)
    assert metrics.mean_ap == pytest.approx(1.0)
    # Every evaluated class has matches (AP 1), so its translation and scale errors are numbers,
    # and zero: the predictions are the boxes themselves.
    for name in cfg.class_names:
        assert metrics.get_label_tp(name, "trans_err") == pytest.approx(0.0, abs=1e-9), name
        assert metrics.get_label_tp(name, "scale_err") == pytest.approx(0.0, abs=1e-9), name


def test_projected_box_lands_on_rendered_object(tiny_dataset, tiny_nusc):
    """GT boxes, projected with the written calibration, cover the object's rendered id mask."""
    from simgen import geometry
    from simgen import rig
    from simgen.camera import Renderer
    from simgen.config import load_preset
    from simgen.pipeline import BASE_TIMESTAMP_US, MakeSettings, build_world
    from simgen.writer import token

    nusc = tiny_nusc
    cfg = load_preset("tiny")
    settings = MakeSettings(cfg, 2, 7, 3, "v1.0-sim")
    renderer = Renderer(cfg.camera)
    results = []   # (category, IoU, share of the mask's box inside the projected box)
    for idx, scene in enumerate(nusc.scene):
        world = build_world(settings, idx)
        renderer.set_world(world, key=("test", idx))
        by_instance = {token(7, idx, "instance", a.id): a.id for a in world.actors}
        annotated = [a for a in world.actors if a.annotate]
        sample = nusc.get("sample", scene["first_sample_token"])
        for channel in ("CAM_FRONT", "CAM_BACK", "CAM_FRONT_LEFT"):
            sd = nusc.get("sample_data", sample["data"][channel])
            pose, cal = nusc.get("ego_pose", sd["ego_pose_token"]), nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            T_ge = np.eye(4)
            T_ge[:3, :3], T_ge[:3, 3] = Quaternion(pose["rotation"]).rotation_matrix, pose["translation"]
            T_ec = np.eye(4)
            T_ec[:3, :3], T_ec[:3, 3] = Quaternion(cal["rotation"]).rotation_matrix, cal["translation"]
            t_cam = (sd["timestamp"] - BASE_TIMESTAMP_US - idx * 1_000_000_000) / 1e6
            b = world.boxes_at(t_cam)
            poses = geometry.poses_2d(b[:, 0], b[:, 1], b[:, 6], b[:, 2])
            cam = next(c for c in rig.cameras(cfg.camera.resolution) if c.channel == channel)
            _, _, ids = renderer.render(cam, T_ge @ T_ec, {a.id: poses[world.actors.index(a)] for a in annotated})
            K = np.array(cal["camera_intrinsic"])
            W, H = sd["width"], sd["height"]
            dt = (sd["timestamp"] - sample["timestamp"]) / 1e6
            for tok in sample["anns"]:
                ann = nusc.get("sample_annotation", tok)
                if ann["visibility_token"] != "4":
                    continue
                vel = np.nan_to_num(nusc.box_velocity(tok))
                box = Box(np.array(ann["translation"]) + vel * dt, ann["size"], Quaternion(ann["rotation"]))
                box.translate(-np.array(pose["translation"]))
                box.rotate(Quaternion(pose["rotation"]).inverse)
                box.translate(-np.array(cal["translation"]))
                box.rotate(Quaternion(cal["rotation"]).inverse)
                corners = box.corners()
                if corners[2].min() < 1.0:
                    continue
                uv = view_points(corners, K, normalize=True)[:2]
                x0, y0, x1, y1 = uv[0].min(), uv[1].min(), uv[0].max(), uv[1].max()
                if x0 < 0 or y0 < 0 or x1 > W or y1 > H or min(x1 - x0, y1 - y0) < 12:
                    continue       # whole objects in this camera, large enough for pixel-level IoU
                # Visibility "4" (>= 80 % seen) and wholly inside this camera: seen here.
                rows, cols = np.nonzero(ids == by_instance[ann["instance_token"]])
                assert len(rows) > 0, ann["token"]
                m = (cols.min(), rows.min(), cols.max() + 1, rows.max() + 1)
                inter = max(0, min(x1, m[2]) - max(x0, m[0])) * max(0, min(y1, m[3]) - max(y0, m[1]))
                mask_area = (m[2] - m[0]) * (m[3] - m[1])
                union = (x1 - x0) * (y1 - y0) + mask_area - inter
                cls = nusc.get("category", nusc.get("instance", ann["instance_token"])["category_token"])["name"]
                results.append((cls, inter / union, inter / mask_area))
    renderer.close()
    # Every object's silhouette lies inside its projected box (to a pixel or so).
    assert len(results) >= 10, results
    assert min(r[2] for r in results) >= 0.9, results
    # Vehicle bodies fill their boxes, so there the boxes match the silhouettes tightly. (A person
    # or a two-wheeler is much thinner than its box, whose footprint has room for arms and legs.)
    vehicles = [r[1] for r in results if r[0] in ("vehicle.car", "vehicle.truck", "vehicle.bus.rigid")]
    assert len(vehicles) >= 5 and min(vehicles) >= 0.7, results


def test_lidarseg_labels_the_written_points(tiny_nusc, tiny_dataset):
    """nuScenes-lidarseg through the devkit: one label per key-frame point; the points inside an
    annotation's box carry its class, except the ground the box stands on; and the ground classes
    lie at the ground's height in the global frame."""
    from nuscenes.utils.data_io import load_bin_file
    from nuscenes.utils.color_map import get_colormap
    nusc = tiny_nusc
    assert [c["name"] for c in sorted(nusc.category, key=lambda c: c["index"])] == list(get_colormap())
    assert len(nusc.lidarseg) == len(nusc.sample)
    idx = nusc.lidarseg_name2idx_mapping
    ground = {idx[n] for n in ("flat.driveable_surface", "flat.sidewalk", "flat.terrain", "flat.other")}
    same = total = 0
    heights = {}
    for sample in nusc.sample:
        sd_token = sample["data"]["LIDAR_TOP"]
        path, boxes, _ = nusc.get_sample_data(sd_token)
        pts = LidarPointCloud.from_file(path).points
        labels = load_bin_file(str(tiny_dataset / nusc.get("lidarseg", sd_token)["filename"]))
        assert labels.shape == (pts.shape[1],)
        for box in boxes:
            inside = points_in_box(box, pts[:3])
            mine = labels[inside] == idx[box.name]
            assert set(labels[inside][~mine].tolist()) <= ground, (box.name, np.unique(labels[inside]))
            same += int(mine.sum())
            total += int(inside.sum())
        # The points into the global frame (sensor -> ego -> global, at this sweep).
        sd = nusc.get("sample_data", sd_token)
        cs, pose = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"]), nusc.get("ego_pose", sd["ego_pose_token"])
        z = (Quaternion(pose["rotation"]).rotation_matrix @ (Quaternion(cs["rotation"]).rotation_matrix @ pts[:3]
             + np.array(cs["translation"])[:, None]))[2] + pose["translation"][2]
        for name in ("flat.driveable_surface", "flat.sidewalk", "flat.terrain", "flat.other", "static.manmade"):
            heights.setdefault(name, []).append(z[labels == idx[name]])
    assert total > 1000 and same / total > 0.85, (same, total)
    z_of = {name: np.concatenate(zs) for name, zs in heights.items()}
    # Asphalt, markings and crosswalks: z = 0 to +1.5 cm, and 2 cm of range noise along the beam.
    road = z_of["flat.driveable_surface"]
    assert len(road) > 1000 and np.abs(road).max() < 0.08 and np.median(np.abs(road)) < 0.02
    # Sidewalks: their top at 0.15 m and the curb's face below it.
    sidewalk = z_of["flat.sidewalk"]
    assert len(sidewalk) > 100 and sidewalk.min() > -0.06 and sidewalk.max() < 0.22 and np.median(sidewalk) > 0.12
    # Lawns or paved lots: a 1 cm slab on the blocks, 0.15-0.16 m.
    lots = np.concatenate([z_of["flat.terrain"], z_of["flat.other"]])
    assert len(lots) > 0 and lots.min() > 0.1 and lots.max() < 0.22
    assert len(z_of["static.manmade"]) > 1000 and np.median(z_of["static.manmade"]) > 1.0   # buildings, poles
