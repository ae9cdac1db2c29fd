"""nuScenes' class mix in the urban preset: all ten detection classes, construction zones with
their machines, trailers that follow their tractors and touch nothing, and the GT as
predictions scoring mAP 1.0 over all ten classes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from simgen import geometry, labels
from simgen.config import PRESET_DIR, load_preset
from simgen.curbside import HITCH_GAP
from simgen.scene import keyframe_times, sample_world
from simgen.traffic import SIZE_MEAN, make_actor
from simgen.world import CLASSES

from conftest import run_simgen

N_SAMPLES = 10
SEEDS = (0, 1)
# nuScenes' attributes per detection class (nuscenes-devkit eval/detection/constants.py and the
# annotator instructions): every vehicle class is moving, stopped or parked.
VEHICLE_ATTRIBUTES = {"vehicle.moving", "vehicle.stopped", "vehicle.parked"}
# The urban preset with denser rare classes, so that 3 samples of one scene (seed 12) hold all ten
# classes with lidar points within their evaluation ranges.
ALL_TEN = {"bicycles_per_km": 8.0, "parked_motorcycle_fraction": 0.15, "construction_zones_per_km": 6.0,
           "parked_trailers_per_km": 6.0, "bus_stops_per_km": 4.0, "cones_per_km": 40.0,
           "vehicle_mix": {"car": 0.64, "truck": 0.18, "bus": 0.08, "motorcycle": 0.1}}
ALL_TEN_SEED, ALL_TEN_SAMPLES = 12, 3


@pytest.fixture(scope="module")
def worlds():
    return [sample_world(load_preset("urban"), np.random.default_rng(s), N_SAMPLES) for s in SEEDS]


def test_urban_worlds_hold_all_ten_classes(worlds):
    for w in worlds:
        assert {a.cls for a in w.actors if a.annotate} == set(CLASSES)
    assert len(CLASSES) == 10


@pytest.mark.parametrize("cls", ["construction_vehicle", "trailer"])
def test_new_class_boxes_enclose_their_meshes(cls):
    rng = np.random.default_rng(3)
    for k in range(20):
        a = make_actor(k, cls, rng, parked=bool(k % 2))
        half = np.array(a.size) / 2
        lo, hi = a.mesh.bounds
        assert (lo >= -half - 1e-9).all() and (hi <= half + 1e-9).all(), (cls, a.size, a.mesh.bounds)
        # The mesh fills its box: the box is the object's, not a loose hull around it.
        assert ((hi - lo) > 0.9 * 2 * half).all(), (cls, a.size, a.mesh.bounds)
        assert len(a.mesh.metadata["reflectivity"]) == len(a.mesh.faces)
        assert np.allclose(np.median(np.array([a.size]), axis=0), SIZE_MEAN[cls], rtol=0.3)


def _overlaps(box: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(m,) whether the (7,) ``box`` and each of ``others`` (m, 7) overlap in BEV (margin 0)."""
    return geometry.bev_overlap_pairwise(np.repeat(box[None], len(others), 0), others, margin=0.0)


def test_trailers_follow_their_tractors_and_touch_nothing(worlds):
    hitched = 0
    for w in worlds:
        index = {a.id: i for i, a in enumerate(w.actors)}
        trailers = [i for i, a in enumerate(w.actors) if a.cls == "trailer"]
        assert trailers
        for t in np.union1d(w.times, keyframe_times(N_SAMPLES)):
            boxes = w.boxes_at(float(t))
            others = np.concatenate([boxes, w.static_boxes])
            for i in trailers:
                hit = _overlaps(boxes[i], others)
                hit[i] = False
                assert not hit.any(), (t, w.actors[i].id, np.nonzero(hit)[0])
                tow = w.actors[i].towed_by
                if tow < 0:
                    continue
                j = index[tow]
                u = np.array([np.cos(boxes[j, 6]), np.sin(boxes[j, 6])])
                # The drawbar between the boxes at the start.
                gap = np.hypot(*(w.xy[i, 0] - w.xy[j, 0])) - (w.sizes[j, 0] + w.sizes[i, 0]) / 2
                assert np.isclose(gap, HITCH_GAP)
                if np.ptp(w.yaw[j]) > 0:
                    # Through a turn (tests/simgen/test_turns.py): its axle, the box centre,
                    # keeps its drawbar's distance to the hitch on the tractor's rear.
                    hitch = boxes[j, :2] - w.sizes[j, 0] / 2 * u
                    assert np.hypot(*(boxes[i, :2] - hitch)) == pytest.approx(gap + w.sizes[i, 0] / 2, abs=1e-6)
                    continue
                behind = w.sizes[j, 0] / 2 + gap + w.sizes[i, 0] / 2
                # On the tractor's path, the hitch distance behind it, with its heading.
                assert np.allclose(boxes[i, :2], boxes[j, :2] - behind * u, atol=1e-6)
                assert boxes[i, 6] == pytest.approx(boxes[j, 6], abs=1e-12)
        hitched += sum(w.actors[i].towed_by >= 0 for i in trailers)
        parked = [i for i in trailers if w.actors[i].parked]
        assert parked and np.ptp(w.xy[parked], axis=1).max() == 0
    assert hitched > 0
    # A hitched trailer moves with its tractor: on a straight path they share a speed at every
    # time; through a turn the trailer cuts the corner, slower, but moves exactly when it does.
    for w in worlds:
        index = {a.id: i for i, a in enumerate(w.actors)}
        for i, a in enumerate(w.actors):
            if a.towed_by >= 0:
                j = index[a.towed_by]
                if np.ptp(w.yaw[j]) > 0:
                    assert np.array_equal(w.speed[i] > 0, w.speed[j] > 0)
                else:
                    assert np.allclose(w.speed[i], w.speed[j])


def test_construction_zones_hold_a_machine_behind_barriers_and_cones(worlds):
    for w in worlds:
        b = w.boxes_at(0.0)
        cls = np.array([a.cls for a in w.actors])
        moves = np.ptp(w.xy, axis=1).max(-1) > 0
        machines = np.nonzero((cls == "construction_vehicle") & ~moves)[0]
        assert len(machines) >= 3
        for i in machines:
            d = np.hypot(*(b[:, :2] - b[i, :2]).T)
            assert ((cls == "barrier") & (d < 20)).sum() >= 4, w.actors[i].id
            assert ((cls == "traffic_cone") & (d < 35)).sum() >= 3, w.actors[i].id


def test_attributes_are_nuscenes_ones(worlds):
    seen = {"construction_vehicle": set(), "trailer": set()}
    for w in worlds:
        for t in keyframe_times(N_SAMPLES):
            speed = w.speed_at(float(t))
            for i, a in enumerate(w.actors):
                if not a.annotate:
                    continue
                attr = labels.attribute(a, float(speed[i]))
                if a.cls in ("car", "truck", "bus", "construction_vehicle", "trailer"):
                    assert attr in VEHICLE_ATTRIBUTES, (a.cls, attr)
                if a.cls in seen:
                    seen[a.cls].add(attr)
    assert seen["trailer"] >= {"vehicle.moving", "vehicle.parked"}, seen
    assert seen["construction_vehicle"] >= {"vehicle.stopped", "vehicle.parked"}, seen


@pytest.fixture(scope="module")
def all_ten_nusc(tmp_path_factory):
    """One scene of three samples from the urban preset with denser rare classes, at 160x90."""
    tmp = tmp_path_factory.mktemp("all_ten")
    preset = yaml.safe_load((PRESET_DIR / "urban.yaml").read_text())
    preset["actors"].update(ALL_TEN)
    (tmp / "all_ten.yaml").write_text(yaml.safe_dump(preset))
    out = tmp / "data"
    run_simgen("make", "--out", out, "--preset", tmp / "all_ten.yaml", "--scenes", 1, "--samples-per-scene",
               ALL_TEN_SAMPLES, "--seed", ALL_TEN_SEED, "--workers", 1, "--resolution", "160x90", "--quiet")
    from nuscenes import NuScenes
    return NuScenes("v1.0-sim", str(out), verbose=False)


def test_ground_truth_as_predictions_is_perfect_over_all_ten_classes(all_ten_nusc, tmp_path):
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.detection.evaluate import DetectionEval
    from nuscenes.eval.detection.utils import category_to_detection_name

    from test_dataset import _gt_as_predictions
    nusc = all_ten_nusc
    splits = json.loads((Path(nusc.dataroot) / nusc.version / "splits.json").read_text())
    split = next(name for name, scenes in splits.items() if scenes)
    results, classes, all_classes = _gt_as_predictions(nusc, split)
    cfg = config_factory("detection_cvpr_2019")
    # Every class has boxes with points within its range (the devkit drops the others).
    in_range = set()
    for ann in nusc.sample_annotation:
        name = category_to_detection_name(ann["category_name"])
        sample = nusc.get("sample", ann["sample_token"])
        ego = nusc.get("ego_pose", nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["ego_pose_token"])
        if ann["num_lidar_pts"] > 0 and np.hypot(*(np.subtract(ann["translation"][:2], ego["translation"][:2]))) \
                <= cfg.class_range[name]:
            in_range.add(name)
    assert in_range == set(cfg.class_names), set(cfg.class_names) - in_range
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"meta": {"use_camera": True, "use_lidar": True, "use_radar": False,
                                         "use_map": False, "use_external": False}, "results": results}))
    ev = DetectionEval(nusc, cfg, str(path), eval_set=split, output_dir=str(tmp_path), verbose=False)
    metrics, _ = ev.evaluate()
    assert metrics.mean_ap == pytest.approx(1.0)
    for name in cfg.class_names:
        assert metrics.get_label_ap(name, 2.0) == pytest.approx(1.0), name
        assert metrics.get_label_tp(name, "trans_err") == pytest.approx(0.0, abs=1e-9), name


def test_num_lidar_pts_is_the_devkit_count_for_every_class(all_ten_nusc):
    from nuscenes.utils.data_classes import LidarPointCloud
    from nuscenes.utils.geometry_utils import points_in_box
    nusc, counted = all_ten_nusc, set()
    for sample in nusc.sample:
        path, boxes, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
        pts = LidarPointCloud.from_file(path).points
        for box in boxes:
            ann = nusc.get("sample_annotation", box.token)
            assert ann["num_lidar_pts"] == int(points_in_box(box, pts[:3]).sum()), ann["token"]
            if ann["num_lidar_pts"] > 0:
                counted.add(ann["category_name"])
    assert {"vehicle.construction", "vehicle.trailer"} <= counted


def test_same_seed_same_world():
    cfg = load_preset("urban")
    a, b = (sample_world(cfg, np.random.default_rng(5), 4) for _ in range(2))
    assert [(x.id, x.cls, x.size, x.towed_by) for x in a.actors] == [(x.id, x.cls, x.size, x.towed_by) for x in b.actors]
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.speed, b.speed) and np.array_equal(a.yaw, b.yaw)
