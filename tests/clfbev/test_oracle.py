"""The sensor-visibility oracle (clfbev.oracle, clfbev.run.oracle).

- the camera's KITTI-moderate limits on known geometry: the 25 px height at KITTI's focal
  length, the 30 % truncation, the visible range, a box behind the camera;
- on a generated set: the clean oracle counts exactly the table's num_lidar_pts and scores 1;
  under a condition its GT is the clean GT filtered by the condition's own point counts (the
  devkit's count on the file, with the field of view cut here independently) and what the
  cameras still see, and the GT as predictions scores mAP 1.0 against that GT;
- a set's failed cameras and its cameras' visibility (degradation.json) hide what they hide.
"""
from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from nuscenes import NuScenes
from nuscenes.utils.data_classes import LidarPointCloud
from nuscenes.utils.geometry_utils import points_in_box
from pyquaternion import Quaternion

from clfbev.corruptions import parse
from clfbev.data import CAMERAS
from clfbev.oracle import KITTI_FOCAL_PX, Camera, Oracle, camera_sees
from clfbev.run.evaluate import evaluate
from clfbev.run.oracle import evaluate_oracle
from clfbev.settings import DETECTION_CLASSES

KITTI_SIZE = (1242, 375)


def _corners(centre, size_xyz) -> np.ndarray:
    """(1, 8, 3) corners of an axis-aligned box."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return (np.asarray(centre, float) + signs * np.asarray(size_xyz, float) / 2)[None]


def _kitti_camera() -> Camera:
    """KITTI's camera with the global frame as its own (x right, y down, z ahead)."""
    W, H = KITTI_SIZE
    K = np.array([[KITTI_FOCAL_PX, 0, W / 2], [0, KITTI_FOCAL_PX, H / 2], [0, 0, 1]])
    return Camera(K, np.eye(4), KITTI_SIZE)


def test_camera_sees_by_kitti_moderate_height_truncation_and_range():
    cam = _kitti_camera()
    # A 1.5 m tall, 1 cm deep box ahead: its near face projects f * 1.5 / (d - 0.005) px tall.
    d25 = KITTI_FOCAL_PX * 1.5 / 25.0 + 0.005
    for d, seen in ((d25 - 0.02, True), (d25 + 0.02, False)):
        assert camera_sees(_corners([0, 0, d], [1.0, 1.5, 0.01]), [cam], math.inf).tolist() == [seen], d
    # The same box at 10 m, moved right until a share of its 2D box leaves the image.
    z, w = 10.0, 2.0
    width_px = KITTI_FOCAL_PX * w / (z - 0.005)
    for outside, seen in ((0.27, True), (0.33, False)):
        u_centre = KITTI_SIZE[0] + (outside - 0.5) * width_px
        x = (u_centre - KITTI_SIZE[0] / 2) * (z - 0.005) / KITTI_FOCAL_PX
        assert camera_sees(_corners([x, 0, z], [w, 1.5, 0.01]), [cam], math.inf).tolist() == [seen], outside
    # Within the visible range (the distance to the box centre) or not; behind the camera never.
    box = _corners([0, 0, 20.0], [1.0, 1.5, 0.01])
    assert camera_sees(box, [cam], 20.01).tolist() == [True]
    assert camera_sees(box, [cam], 19.99).tolist() == [False]
    assert camera_sees(_corners([0, 0, -20.0], [1.0, 1.5, 0.01]), [cam], math.inf).tolist() == [False]
    assert camera_sees(box, [], math.inf).tolist() == [False]


def test_clean_oracle_counts_the_tables_points_and_scores_1(tiny_dataset, tmp_path):
    oracle = Oracle(tiny_dataset, "v1.0-sim", "sim-val")
    nusc = oracle.ds.nusc
    for i in range(len(oracle)):
        sight = oracle.sight(i)
        table = [nusc.get("sample_annotation", t)["num_lidar_pts"] for t in sight.tokens]
        assert sight.lidar_points.tolist() == table
    summary = evaluate_oracle(tiny_dataset, "v1.0-sim", "sim-val", (), tmp_path / "oracle", DETECTION_CLASSES)
    assert summary["mean_ap"] == pytest.approx(1.0) and summary["nd_score"] == pytest.approx(1.0)


def _devkit_counts_within_fov(nusc, sample_token: str, fov_deg: float) -> dict[str, int]:
    """{annotation token: points of the key sweep inside its box}, the sweep read by the devkit
    and cut to +-fov/2 around the ego's forward axis here."""
    lidar = nusc.get("sample", sample_token)["data"]["LIDAR_TOP"]
    path, boxes, _ = nusc.get_sample_data(lidar)
    pc = LidarPointCloud.from_file(path)
    calib = nusc.get("calibrated_sensor", nusc.get("sample_data", lidar)["calibrated_sensor_token"])
    forward = Quaternion(calib["rotation"]).rotation_matrix.T @ np.array([1.0, 0.0, 0.0])
    az = np.arctan2(pc.points[1], pc.points[0]) - math.atan2(forward[1], forward[0])
    az = (az + np.pi) % (2 * np.pi) - np.pi
    pts = pc.points[:3, np.abs(az) <= np.deg2rad(fov_deg) / 2]
    return {b.token: int(points_in_box(b, pts).sum()) for b in boxes}


def _linked_copy(src, dst, *ignore: str):
    """A copy of ``src``'s tables (but the files ``ignore``) with its sensor folders linked."""
    dst.mkdir()
    for entry in src.iterdir():
        if entry.name != "v1.0-sim":
            (dst / entry.name).symlink_to(entry)
    shutil.copytree(src / "v1.0-sim", dst / "v1.0-sim", ignore=shutil.ignore_patterns(*ignore))
    return dst


def _oracle_dataroot(src, dst, unseen: set[str]):
    """A linked copy of ``src`` in which the unseen annotations have no points (so the devkit
    leaves them out of its GT)."""
    table = _linked_copy(src, dst) / "v1.0-sim" / "sample_annotation.json"
    anns = json.loads(table.read_text())
    for ann in anns:
        if ann["token"] in unseen:
            ann["num_lidar_pts"] = ann["num_radar_pts"] = 0
    table.write_text(json.dumps(anns))
    return dst


def test_oracle_gt_is_the_gt_the_condition_still_sees(tiny_dataset, tmp_path):
    """Under a lidar cut to 90 degrees and no camera, the oracle sees exactly the annotations
    with a point of the cut sweep; its predictions score mAP 1.0 against that GT, less against
    the full one."""
    corr = (parse("fov:90"), parse("camera_crash:6"))
    oracle = Oracle(tiny_dataset, "v1.0-sim", "sim-val", corr)
    nusc = oracle.ds.nusc
    unseen, n_seen = set(), 0
    for i, token in enumerate(oracle.ds.sample_tokens):
        sight = oracle.sight(i)
        expected = _devkit_counts_within_fov(nusc, token, 90.0)
        assert dict(zip(sight.tokens, sight.lidar_points.tolist())) == expected
        assert not sight.camera.any()
        assert sight.seen.tolist() == [expected[t] > 0 for t in sight.tokens]
        unseen |= {t for t, s in zip(sight.tokens, sight.seen) if not s}
        n_seen += int(sight.seen.sum())
    assert n_seen > 5 and unseen
    full = evaluate_oracle(tiny_dataset, "v1.0-sim", "sim-val", corr, tmp_path / "oracle", DETECTION_CLASSES)
    assert full["mean_ap"] < 0.95
    root = _oracle_dataroot(tiny_dataset, tmp_path / "seen", unseen)
    evaluated = [c for c in DETECTION_CLASSES if c in full["mean_dist_aps"]]
    against_seen = evaluate(NuScenes("v1.0-sim", str(root), verbose=False), tmp_path / "oracle" / "results.json",
                            "sim-val", tmp_path / "eval_seen", evaluated)
    assert against_seen["mean_ap"] == pytest.approx(1.0)


def _with_record(src, dst, record: dict):
    """A linked copy of ``src`` with the degradation record ``record``."""
    (_linked_copy(src, dst, "degradation.json") / "v1.0-sim" / "degradation.json").write_text(json.dumps(record))
    return dst


def test_a_sets_failed_cameras_and_visibility_hide_what_they_hide(tiny_dataset, tmp_path):
    """Without its lidar, the oracle sees what the cameras see: nothing when the set's six
    cameras failed, only what lies within the cameras' visibility (MOR) through its weather."""
    corr = (parse("lidar_missing"),)

    def seen(root):
        o = Oracle(root, "v1.0-sim", "sim-val", corr)
        sights = [o.sight(i) for i in range(len(o))]
        return o, np.concatenate([s.seen for s in sights]), np.concatenate([s.lidar_points for s in sights])

    clear, seen_clear, points = seen(tiny_dataset)
    assert seen_clear.any() and not points.any()
    _, seen_failed, _ = seen(_with_record(tiny_dataset, tmp_path / "failed", {"failed_sensors": list(CAMERAS)}))
    assert not seen_failed.any()
    mor = 12.0
    _, seen_fog, _ = seen(_with_record(tiny_dataset, tmp_path / "fog", {"camera_visibility_m": mor}))
    nusc = clear.ds.nusc
    centres = []
    for token in clear.ds.sample_tokens:
        sample = nusc.get("sample", token)
        pose = nusc.get("ego_pose", nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["ego_pose_token"])
        centres += [np.linalg.norm(np.subtract(nusc.get("sample_annotation", t)["translation"], pose["translation"])[:2])
                    for t in sample["anns"]]
    dist = np.array(centres)
    assert not (seen_fog & ~seen_clear).any()
    # The cameras sit within 2 m of the ego's origin: nothing farther than MOR + 2 m is seen,
    # and what the clear air shows within MOR - 2 m still is.
    assert not (seen_fog & (dist > mor + 2.0)).any()
    assert (seen_fog[seen_clear & (dist < mor - 2.0)]).all()
    assert (seen_clear & (dist > mor + 2.0)).any()
