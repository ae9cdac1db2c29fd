"""`simgen make --dense-labels`: a z-depth and a class image beside each camera image, checked
against the lidar through the written tables, as a user would read them."""
from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from nuscenes.eval.common.config import config_factory
from nuscenes.eval.detection.evaluate import DetectionEval
from nuscenes.utils.data_classes import LidarPointCloud
from nuscenes.utils.data_io import load_bin_file
from pyquaternion import Quaternion

from conftest import run_simgen
from test_dataset import _gt_as_predictions
from test_determinism import file_hashes

# The resolution the camera encoder is pretrained at: the smaller a pixel's footprint, the fewer
# lidar points sit on an edge within it.
DENSE_ARGS = ["--preset", "tiny", "--resolution", "704x396", "--scenes", "2", "--samples-per-scene", "2",
              "--seed", "7", "--quiet", "--dense-labels"]
TOLERANCE = 0.05          # m
VERSION = "v1.0-sim"


@pytest.fixture(scope="module")
def dense_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dense") / "data"
    run_simgen("make", "--out", out, "--workers", "1", *DENSE_ARGS)
    return out


@pytest.fixture(scope="module")
def dense_nusc(dense_dataset):
    from nuscenes import NuScenes
    return NuScenes(VERSION, str(dense_dataset), verbose=False)


def read_dense(dataroot: Path, image_file: str) -> tuple[np.ndarray, np.ndarray]:
    """The depth (H, W) uint16 and class (H, W) uint8 images of a camera image, as written."""
    stem = Path(image_file).name.rsplit(".", 1)[0]
    folder = Path(dataroot) / "dense" / Path(image_file).parent.name
    depth = cv2.imread(str(folder / f"{stem}_depth.png"), cv2.IMREAD_UNCHANGED)
    seg = cv2.imread(str(folder / f"{stem}_seg.png"), cv2.IMREAD_UNCHANGED)
    return depth, seg


def transform(record: dict) -> np.ndarray:
    """(4, 4) from a nuScenes translation + rotation record."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Quaternion(record["rotation"]).rotation_matrix, record["translation"]
    return T


def T_global_from_sensor(nusc, sd: dict) -> np.ndarray:
    """T_global_from_sensor of a sample_data record at its own timestamp."""
    return (transform(nusc.get("ego_pose", sd["ego_pose_token"]))
            @ transform(nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])))


def depth_at(depth_m: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The dense depth (m) at sub-pixel positions (n,) u, v (pixel i spans [i, i + 1)): that of
    the pixel holding each position; the depth interpolated there from the four pixel centres
    around it (inverse depth is linear in the image across a plane, so on one surface this is
    its depth at the position itself, where the pixel's centre may see the surface half a
    pixel away: metres apart where the road is seen at a grazing angle); and the spread of
    those four depths (large at an edge)."""
    own = depth_m[v.astype(int), u.astype(int)]
    x, y = u - 0.5, v - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    corners = np.stack([depth_m[y0, x0], depth_m[y0, x0 + 1], depth_m[y0 + 1, x0], depth_m[y0 + 1, x0 + 1]])
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    with np.errstate(divide="ignore"):
        inverse = (weights / corners).sum(0)
    interpolated = np.where(corners.min(0) > 0, 1.0 / np.where(inverse > 0, inverse, 1.0), 0.0)
    return own, interpolated, corners.max(0) - corners.min(0)


def static_classes(nusc) -> list[int]:
    """The lidarseg classes of static geometry: flat.* and static.*."""
    return [c["index"] for c in nusc.category if c["name"].startswith(("flat.", "static."))]


def points_in_cameras(nusc, dataroot: Path, classes: list[int]) -> list[np.ndarray]:
    """Every key-frame lidar point of ``classes`` (lidarseg), projected into each camera of its
    sample through the written calibration and ego poses. Returns, over all of them: z (n,)
    camera-frame depth, the dense depth at the point (own pixel, interpolated, spread:
    :func:`depth_at`), the dense class at its pixel and the point's lidarseg class."""
    return [np.concatenate(a) for a in zip(*_points_in_cameras(nusc, dataroot, classes))]


def _points_in_cameras(nusc, dataroot: Path, classes: list[int]):
    for sample in nusc.sample:
        lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        points = LidarPointCloud.from_file(str(dataroot / lidar["filename"])).points[:3].T.astype(np.float64)
        label = load_bin_file(str(dataroot / nusc.get("lidarseg", lidar["token"])["filename"]))
        keep = np.isin(label, classes)
        T_global_from_lidar = T_global_from_sensor(nusc, lidar)
        points_global = points[keep] @ T_global_from_lidar[:3, :3].T + T_global_from_lidar[:3, 3]
        label = label[keep]
        for token in sample["data"].values():
            sd = nusc.get("sample_data", token)
            if sd["fileformat"] != "jpg":
                continue
            T_cam_from_global = np.linalg.inv(T_global_from_sensor(nusc, sd))
            p = points_global @ T_cam_from_global[:3, :3].T + T_cam_from_global[:3, 3]
            K = np.array(nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])["camera_intrinsic"])
            z = p[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u, v = K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]
            # Inside the image, with the four pixel centres around the point in it too.
            inside = (z > 0.1) & (u >= 0.5) & (u < sd["width"] - 0.5) & (v >= 0.5) & (v < sd["height"] - 0.5)
            depth, seg = read_dense(dataroot, sd["filename"])
            u, v = u[inside], v[inside]
            yield (z[inside], *depth_at(depth / 256.0, u, v), seg[v.astype(int), u.astype(int)], label[inside])


def test_dense_depth_and_class_agree_with_the_lidar(dense_nusc, dense_dataset):
    """At a static lidar point seen first along its pixel's ray, the dense depth is the point's
    z-depth in that camera to within 5 cm, and the pixel's class is the point's lidarseg class.

    The points that do not agree are accounted for: the lidar's range noise (2 cm sigma: beyond
    5 cm for about 1 % of points, rarely beyond 8 cm); edges, where a pixel's footprint holds two
    surfaces (the four pixel centres around the point differ by more than 0.5 m); and points
    the camera does not see because a nearer surface hides them from its viewpoint (the camera
    sits lower than the lidar and apart from it, and fires a few milliseconds from the lidar's
    beam at the same azimuth, the ego moving meanwhile): the dense depth there is well short of
    the point.
    """
    z, own, interpolated, spread, seg, label = points_in_cameras(dense_nusc, dense_dataset, static_classes(dense_nusc))
    agree = (np.abs(own - z) < TOLERANCE) | (np.abs(interpolated - z) < TOLERANCE)
    noise = np.abs(interpolated - z) < 0.08
    edge = spread > 0.5
    hidden = own < z - 0.5
    unexplained = ~agree & ~noise & ~edge & ~hidden
    assert len(z) > 50_000
    assert agree.mean() >= 0.95, (agree.mean(), noise[~agree].mean(), edge[~agree].mean(), hidden[~agree].mean())
    assert unexplained.mean() < 0.005, unexplained.sum()
    assert (seg[agree] == label[agree]).mean() >= 0.99


def test_class_of_actor_pixels_agrees_with_the_lidar(dense_nusc, dense_dataset):
    """On the actors too, where the lidar point and the pixel see the same surface (the depth
    agrees: a moving actor moves between the lidar's beam and the camera), the pixel's class is
    the point's."""
    actors = [c["index"] for c in dense_nusc.category
              if c["index"] not in static_classes(dense_nusc) and c["name"] != "noise"]
    z, own, interpolated, _, seg, label = points_in_cameras(dense_nusc, dense_dataset, actors)
    agree = (np.abs(own - z) < TOLERANCE) | (np.abs(interpolated - z) < TOLERANCE)
    assert agree.sum() > 2000 and len(np.unique(label[agree])) >= 3
    assert (seg[agree] == label[agree]).mean() >= 0.99


def test_png_format_and_sky(dense_nusc, dense_dataset):
    """uint16 depth and uint8 class images of each camera image's size. Where the class is 0 the
    camera image shows the sky's colour and the depth is 0; everywhere else there is a depth (the
    tiny map lies within the 256 m that uint16 depth reaches)."""
    from simgen.camera import SKY
    sky_rgb = np.array([int(255 * c) for c in SKY])
    cams = [sd for sd in dense_nusc.sample_data if sd["fileformat"] == "jpg"]
    assert len(cams) == 6 * len(dense_nusc.sample)
    classes, sky_colours = set(), []
    for sd in cams:
        depth, seg = read_dense(dense_dataset, sd["filename"])
        assert depth.dtype == np.uint16 and depth.shape == (sd["height"], sd["width"]) == (396, 704)
        assert seg.dtype == np.uint8 and seg.shape == depth.shape
        assert np.array_equal(depth == 0, seg == 0)
        assert np.all(depth[-1] > 0)                     # the ground, a few metres ahead
        # Away from the horizon by a pixel (JPEG blurs an edge).
        sky = cv2.erode((seg == 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        rgb = cv2.imread(str(dense_dataset / sd["filename"]))[..., ::-1]
        sky_colours.append(rgb[sky].astype(int))
        classes |= set(np.unique(seg).tolist())
    off = np.abs(np.concatenate(sky_colours) - sky_rgb).max(1)
    assert len(off) > 10_000 and np.percentile(off, 99) <= 16
    idx = dense_nusc.lidarseg_name2idx_mapping
    assert {0, idx["flat.driveable_surface"], idx["static.manmade"], idx["vehicle.car"]} <= classes


def test_check_and_devkit_accept_the_set(dense_nusc, dense_dataset, tmp_path):
    """`simgen check` verifies the dense files; the devkit loads and evaluates the set as before."""
    assert run_simgen("check", dense_dataset).stdout.strip().endswith("OK")
    copy = tmp_path / "copy"
    shutil.copytree(dense_dataset, copy)
    seg_file = next((copy / "dense" / "CAM_BACK").glob("*_seg.png"))
    cv2.imwrite(str(seg_file), np.zeros((10, 10), np.uint8))
    proc = run_simgen("check", copy, check=False)
    assert proc.returncode == 1 and f"{seg_file.name}: expected a uint8 image of 396x704" in proc.stdout

    results, classes, all_classes = _gt_as_predictions(dense_nusc, "sim-val")
    cfg = config_factory("detection_cvpr_2019")
    cfg.class_range = {k: v for k, v in cfg.class_range.items() if k in all_classes}
    cfg.class_names = [k for k in cfg.class_range if k in classes]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"meta": {"use_camera": True, "use_lidar": True, "use_radar": False,
                                         "use_map": False, "use_external": False}, "results": results}))
    metrics, _ = DetectionEval(dense_nusc, cfg, str(path), eval_set="sim-val", output_dir=str(tmp_path),
                               verbose=False).evaluate()
    assert metrics.mean_ap == pytest.approx(1.0)


def test_same_bytes_with_two_workers_and_after_a_resume(dense_dataset, tmp_path):
    out = tmp_path / "data"
    run_simgen("make", "--out", out, "--workers", "2", *DENSE_ARGS)
    reference = file_hashes(dense_dataset)
    assert sum(name.startswith("dense/") for name in reference) == 2 * 2 * 6 * 2
    assert file_hashes(out) == reference
    # A scene without its part is made again, dense labels included.
    (out / ".parts" / "scene-0001.json").unlink()
    for f in (out / "dense" / "CAM_FRONT").glob("simgen-7-0001__*"):
        f.unlink()
    run_simgen("make", "--out", out, "--workers", "1", *DENSE_ARGS)
    assert file_hashes(out) == reference


def test_resume_with_another_dense_labels_setting_is_refused(dense_dataset, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(dense_dataset, copy)
    args = [a for a in DENSE_ARGS if a != "--dense-labels"]
    proc = run_simgen("make", "--out", copy, *args, check=False)
    assert proc.returncode == 2 and "other settings (differing: dense_labels)" in proc.stderr


def test_without_the_flag_no_dense_folder(tmp_path):
    out = tmp_path / "data"
    run_simgen("make", "--out", out, "--preset", "tiny", "--scenes", "1", "--samples-per-scene", "1", "--quiet")
    assert (out / "samples" / "CAM_FRONT").is_dir() and not (out / "dense").exists()
    assert "dense_labels" not in json.loads((out / ".parts" / "settings.json").read_text())


def test_degraded_cameras_keep_the_clean_dense_labels(tmp_path):
    """Fog, lens dirt and a failed camera change the images, not the scene they label."""
    args = ["--preset", "tiny", "--scenes", "1", "--samples-per-scene", "1", "--quiet", "--dense-labels"]
    run_simgen("make", "--out", tmp_path / "clean", *args)
    run_simgen("make", "--out", tmp_path / "foggy", *args, "--fog", "3", "--lens-occlusion", "2",
               "--drop-sensor", "CAM_BACK")
    clean, foggy = file_hashes(tmp_path / "clean"), file_hashes(tmp_path / "foggy")
    dense = [name for name in clean if name.startswith("dense/")]
    images = [name for name in clean if name.endswith(".jpg")]
    assert len(dense) == 12 and all(clean[name] == foggy[name] for name in dense)
    assert len(images) == 6 and all(clean[name] != foggy[name] for name in images)


@pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                    reason="the optional extra 'ray' is not installed (pip install -e .[ray])")
def test_ray_gives_the_same_dense_labels(dense_dataset, tmp_path):
    out = tmp_path / "data"
    proc = subprocess.run([sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--ray", "--workers", "2",
                           *DENSE_ARGS], capture_output=True, text=True, start_new_session=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert file_hashes(out) == file_hashes(dense_dataset)
