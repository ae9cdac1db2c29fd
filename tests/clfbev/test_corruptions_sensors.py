"""``misalign`` and ``late``: one sensor seen through an exact calibration error, or its data
stream frames behind its records. Every expectation is rebuilt here from the tables and the
sensor files' bytes."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from clfbev.config import tiny
from clfbev.corruptions import SENSORS, parse
from clfbev.data import CAMERAS, LIDAR, NuScenesDetection, transform_from
from clfbev.sensor_files import IMAGE_MEAN, IMAGE_STD, resize_and_crop

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def clean(tiny_dataset):
    return tiny_dataset, NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", tiny().data_config())


def _corrupted(root, text):
    return NuScenesDetection(root, "v1.0-sim", "sim-val", tiny().data_config(), (parse(text),))


def _record_T(nusc, sd, table):
    rec = nusc.get(table, sd[f"{table}_token"])
    return transform_from(rec["translation"], rec["rotation"])


def _rot(axis: int, deg: float) -> np.ndarray:
    """The right-handed rotation by ``deg`` about coordinate axis ``axis`` (0 x, 1 y, 2 z)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _believed(T_ego_from_sensor, s):
    """The calibration misalign:SENSOR:s makes the loader believe."""
    T = T_ego_from_sensor.copy()
    T[:3, :3] = _rot(2, s) @ _rot(1, s) @ _rot(0, s) @ T[:3, :3]
    T[:3, 3] += 0.02 * s
    return T


def _sds(ds, i):
    sample = ds.nusc.get("sample", ds.sample_tokens[i])
    return {ch: ds.nusc.get("sample_data", sample["data"][ch]) for ch in (LIDAR, *CAMERAS)}


def test_the_sensor_names_are_the_loaders():
    assert SENSORS == (LIDAR, *CAMERAS)


def test_misaligned_camera_is_seen_through_the_exact_error(clean):
    root, ds = clean
    bad_ds, k = _corrupted(root, "misalign:CAM_FRONT:2"), CAMERAS.index("CAM_FRONT")
    for i in range(len(ds)):
        s, b, sds = ds[i], bad_ds[i], _sds(ds, i)
        T_global_from_lidar = _record_T(ds.nusc, sds[LIDAR], "ego_pose") @ _record_T(ds.nusc, sds[LIDAR], "calibrated_sensor")
        cam = sds["CAM_FRONT"]
        expected = (np.linalg.inv(T_global_from_lidar) @ _record_T(ds.nusc, cam, "ego_pose")
                    @ _believed(_record_T(ds.nusc, cam, "calibrated_sensor"), 2.0))
        np.testing.assert_allclose(b.T_lidar_from_cam[k], expected, rtol=0, atol=2e-6)
        # The error is the whole change: clean and believed camera frames differ by the error's rotation.
        dR = s.T_lidar_from_cam[k, :3, :3].astype(np.float64).T @ b.T_lidar_from_cam[k, :3, :3]
        E = _rot(2, 2) @ _rot(1, 2) @ _rot(0, 2)
        assert math.acos((np.trace(dR) - 1) / 2) == pytest.approx(math.acos((np.trace(E) - 1) / 2), abs=1e-5)
        others = [j for j in range(len(CAMERAS)) if j != k]
        np.testing.assert_array_equal(b.T_lidar_from_cam[others], s.T_lidar_from_cam[others])
        for name in ("images", "points", "gt_boxes", "T_global_from_lidar"):
            np.testing.assert_array_equal(getattr(b, name), getattr(s, name))


def test_misaligned_lidar_is_seen_through_the_exact_error(clean):
    root, ds = clean
    bad_ds = _corrupted(root, "misalign:LIDAR_TOP:3")
    for i in range(len(ds)):
        s, b, sds = ds[i], bad_ds[i], _sds(ds, i)
        lidar = sds[LIDAR]
        T_global_from_lidar = _record_T(ds.nusc, lidar, "ego_pose") @ _believed(_record_T(ds.nusc, lidar, "calibrated_sensor"), 3.0)
        np.testing.assert_allclose(b.T_global_from_lidar, T_global_from_lidar, rtol=0, atol=1e-9)
        for k, ch in enumerate(CAMERAS):
            expected = (np.linalg.inv(T_global_from_lidar) @ _record_T(ds.nusc, sds[ch], "ego_pose")
                        @ _record_T(ds.nusc, sds[ch], "calibrated_sensor"))
            np.testing.assert_allclose(b.T_lidar_from_cam[k], expected, rtol=0, atol=2e-6)
        # The key sweep is the sensor's own measurement: unchanged, bit for bit.
        np.testing.assert_array_equal(b.points[b.points[:, 4] == 0], s.points[s.points[:, 4] == 0])
        # The labels are put in the believed lidar frame: in global they stay where they are (the
        # range crop, in the lidar frame, may take a box near an edge in or out: 3 deg of pitch
        # lifts a box 40 m away by 2 m).
        to_global = lambda T, boxes: boxes[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        g_bad, g_clean = to_global(b.T_global_from_lidar, b.gt_boxes), to_global(s.T_global_from_lidar, s.gt_boxes)
        gap = np.linalg.norm(g_bad[:, None] - g_clean[None], axis=2)
        assert gap.min(axis=1).max() < 1e-4
        inside = np.linalg.norm(s.gt_boxes[:, :2], axis=1) < 20
        assert inside.sum() >= 3
        assert gap.min(axis=0)[inside].max() < 1e-4
        moved = np.linalg.norm(b.gt_boxes[:, :3] - s.gt_boxes[gap.argmin(axis=1), :3], axis=1)
        assert moved.min() > 0.01                          # in the believed lidar frame every box moved
        np.testing.assert_array_equal(b.images, s.images)


def _chain(nusc, sd, n):
    """``sd`` and up to n - 1 records before it on its channel, newest first."""
    out = [sd]
    while len(out) < n and out[-1]["prev"]:
        out.append(nusc.get("sample_data", out[-1]["prev"]))
    return out


def _raw_points(root, sd):
    """(n, 5) float32 straight from the file's bytes."""
    return np.frombuffer((root / sd["filename"]).read_bytes(), dtype=np.float32).reshape(-1, 5)


def test_late_lidar_reads_the_previous_sweeps_as_current(clean):
    root, ds = clean
    bad_ds, cfg = _corrupted(root, "late:LIDAR_TOP:1"), tiny().data_config()
    lo, hi = np.asarray(cfg.point_range[:3]), np.asarray(cfg.point_range[3:])
    in_range = lambda xyz: ((xyz >= lo) & (xyz < hi)).all(axis=1)
    for i in range(len(ds)):
        s, b, sds = ds[i], bad_ds[i], _sds(ds, i)
        chain = _chain(ds.nusc, sds[LIDAR], 3)
        assert len(chain) == 3, "every tiny sample has sweeps before it"
        # The key sweep's points are the previous sweep's file, labelled as the key frame's (lag 0).
        raw = _raw_points(root, chain[1])
        key = b.points[b.points[:, 4] == 0]
        np.testing.assert_array_equal(key[:, :3], raw[in_range(raw[:, :3]), :3])
        np.testing.assert_array_equal(key[:, 3], raw[in_range(raw[:, :3]), 3] / np.float32(255))
        # The sweep one back carries the file two back, moved with the pose of the sweep one back.
        T_key_from_sweep = (np.linalg.inv(s.T_global_from_lidar) @ _record_T(ds.nusc, chain[1], "ego_pose")
                            @ _record_T(ds.nusc, chain[1], "calibrated_sensor"))
        lag = (chain[0]["timestamp"] - chain[1]["timestamp"]) * 1e-6
        raw2 = _raw_points(root, chain[2])
        xyz = (raw2[:, :3].astype(np.float64) @ T_key_from_sweep[:3, :3].T + T_key_from_sweep[:3, 3]).astype(np.float32)
        np.testing.assert_array_equal(b.points[b.points[:, 4] == np.float32(lag), :3], xyz[in_range(xyz)])
        assert not np.array_equal(key[:, :3], s.points[s.points[:, 4] == 0, :3])
        for name in ("images", "T_lidar_from_cam", "gt_boxes", "T_global_from_lidar"):
            np.testing.assert_array_equal(getattr(b, name), getattr(s, name))


def _network_image(path, size):
    """The network input of an image file, decoded here from its bytes."""
    bgr = cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_COLOR)
    image, _ = resize_and_crop(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), size)
    return ((image.astype(np.float32) / 255.0 - IMAGE_MEAN) / IMAGE_STD).transpose(2, 0, 1)


def test_late_camera_reads_the_previous_frame_as_current(clean):
    root, ds = clean
    bad_ds, k, size = _corrupted(root, "late:CAM_FRONT:1"), CAMERAS.index("CAM_FRONT"), tiny().data_config().image_size
    n_late = 0
    for i in range(len(ds)):
        s, b, sds = ds[i], bad_ds[i], _sds(ds, i)
        cam = sds["CAM_FRONT"]
        # The previous frame of the channel; the scene's first frame has none and stands for itself.
        older = ds.nusc.get("sample_data", cam["prev"]) if cam["prev"] else cam
        n_late += bool(cam["prev"])
        np.testing.assert_array_equal(b.images[k], _network_image(root / older["filename"], size))
        others = [j for j in range(len(CAMERAS)) if j != k]
        np.testing.assert_array_equal(b.images[others], s.images[others])
        for name in ("T_lidar_from_cam", "intrinsics", "img_aug", "points", "gt_boxes"):
            np.testing.assert_array_equal(getattr(b, name), getattr(s, name))
    assert 0 < n_late < len(ds)          # both cases seen: a late frame, and a scene's first one
