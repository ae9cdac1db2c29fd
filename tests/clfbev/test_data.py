"""clfbev.data on a tiny simgen dataset: shapes, exact geometry, multi-sweep, projection, errors.

The dataset comes from the session fixture ``tiny_dataset`` (tests/conftest.py), which runs
``python -m simgen.cli make --preset tiny --scenes 2 --samples-per-scene 3 --seed 7 --workers 1``
in a subprocess: clfbev only ever sees the files on disk.
"""
from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
import torch
from pyquaternion import Quaternion

from clfbev.data import (
    ALL_SCENES, CAMERAS, Batch, DataConfig, NuScenesDetection, box_lidar_to_global, box_to_lidar, collate,
)
from clfbev.errors import DataError

VERSION = "v1.0-sim"
SWEEP_S = 0.05                                       # 20 Hz lidar
WIDE = DataConfig(point_range=(-500.0, -500.0, -50.0, 500.0, 500.0, 50.0), min_points=0)


@pytest.fixture(scope="module")
def train(tiny_dataset) -> NuScenesDetection:
    return NuScenesDetection(tiny_dataset, VERSION, "sim-train", DataConfig())


@pytest.fixture(scope="module")
def wide(tiny_dataset) -> NuScenesDetection:
    """Every annotation kept (no range or point filter), so boxes line up with sample['anns']."""
    return NuScenesDetection(tiny_dataset, VERSION, "sim-train", WIDE)


def in_box_local(points: np.ndarray, centre: np.ndarray, R_frame_from_box: np.ndarray) -> np.ndarray:
    """(M, n, 3) coordinates of (n, 3) points in each of M box frames (centre (M, 3), R (M, 3, 3))."""
    return np.einsum("mji,mnj->mni", R_frame_from_box, points[None] - centre[:, None])


def yaw_matrices(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def test_length_and_batch_shapes(tiny_dataset, train):
    nusc = train.nusc
    for split, ds in (("sim-train", train), ("sim-val", NuScenesDetection(tiny_dataset, VERSION, "sim-val"))):
        scene_names = {"sim-train": "scene-0000", "sim-val": "scene-0001"}[split]
        scene = next(s for s in nusc.scene if s["name"] == scene_names)
        assert len(ds) == scene["nbr_samples"] == 3
    batch = collate([train[0], train[1]])
    assert isinstance(batch, Batch)
    H, W = train.cfg.image_size
    assert batch.images.shape == (2, 6, 3, H, W) and batch.images.dtype == torch.float32
    assert batch.intrinsics.shape == (2, 6, 3, 3)
    assert batch.T_lidar_from_cam.shape == (2, 6, 4, 4)
    assert batch.img_aug.shape == (2, 6, 3, 3)
    assert batch.T_global_from_lidar.shape == (2, 4, 4)
    assert len(batch.points) == len(batch.gt_boxes) == len(batch.gt_labels) == len(batch.sample_tokens) == 2
    lo, hi = np.array(train.cfg.point_range[:3]), np.array(train.cfg.point_range[3:])
    for pts, boxes, labels in zip(batch.points, batch.gt_boxes, batch.gt_labels):
        assert pts.ndim == 2 and pts.shape[1] == 5 and pts.dtype == torch.float32 and len(pts) > 1000
        assert ((pts[:, :3].numpy() >= lo) & (pts[:, :3].numpy() < hi)).all()
        assert 0.0 <= pts[:, 3].min() and pts[:, 3].max() <= 1.0
        assert boxes.shape == (len(labels), 9) and len(labels) > 0 and labels.dtype == torch.int64
        assert ((boxes[:, :3].numpy() >= lo) & (boxes[:, :3].numpy() < hi)).all()
        assert (boxes[:, 3:6] > 0).all() and labels.max() < len(train.cfg.class_names)
    assert batch.sample_tokens == train.sample_tokens[:2]
    # Resize to the network width keeping the aspect ratio, then crop the top rows to H.
    sd = nusc.get("sample_data", nusc.get("sample", batch.sample_tokens[0])["data"]["CAM_FRONT"])
    h1 = round(sd["height"] * W / sd["width"])
    A = torch.tensor([[W / sd["width"], 0, 0], [0, h1 / sd["height"], H - h1], [0, 0, 1.0]])
    assert h1 >= H and torch.allclose(batch.img_aug[0, 1], A)
    moved = batch.to("cpu")
    assert moved.images.device.type == "cpu" and torch.equal(moved.gt_boxes[1], batch.gt_boxes[1])


def test_key_frame_points_in_boxes_match_num_lidar_pts(wide):
    """Exact: key-frame points in each annotation box (full devkit rotation) == num_lidar_pts.

    The 7-dof boxes are yaw-only in the lidar frame while the LIDAR_TOP is tilted (~0.7 deg) from
    the ground, so their count is exact only up to the tilt: it is sandwiched between the counts
    of the box shrunk and grown by (residual angle) x (half diagonal).
    """
    for index in range(len(wide)):
        s = wide[index]
        nusc = wide.nusc
        anns = [nusc.get("sample_annotation", t) for t in nusc.get("sample", s.sample_token)["anns"]]
        assert len(anns) == len(s.gt_boxes)
        want = np.array([a["num_lidar_pts"] for a in anns])
        key = s.points
        key = key[key[:, 4] == 0, :3].astype(np.float64)
        T_lidar_from_global = np.linalg.inv(s.T_global_from_lidar)
        R_full = np.stack([T_lidar_from_global[:3, :3] @ Quaternion(a["rotation"]).rotation_matrix for a in anns])
        lwh = np.array([[a["size"][1], a["size"][0], a["size"][2]] for a in anns])
        boxes = s.gt_boxes.astype(np.float64)
        # Full rotation, the box's own float64 centre: the devkit's points_in_box (inclusive).
        local = in_box_local(key, boxes[:, :3], R_full)
        full = (np.abs(local) <= lwh[:, None] / 2).all(-1).sum(1)
        np.testing.assert_array_equal(full, want)
        # The 7-dof boxes.
        np.testing.assert_allclose(boxes[:, 3:6], lwh, rtol=1e-6)
        R_yaw = yaw_matrices(boxes[:, 6])
        cos_angle = (np.einsum("mji,mji->m", R_yaw, R_full) - 1) / 2
        margin = np.arccos(np.clip(cos_angle, -1, 1)) * np.linalg.norm(lwh, axis=1) / 2 + 1e-3
        assert margin.max() < 0.1
        local = np.abs(in_box_local(key, boxes[:, :3], R_yaw))
        half = lwh[:, None] / 2
        inner = (local <= np.maximum(half - margin[:, None, None], 0)).all(-1).sum(1)
        outer = (local <= half + margin[:, None, None]).all(-1).sum(1)
        assert (inner <= want).all() and (want <= outer).all()
        assert want.max() > 50                      # the check is not vacuous
        # Velocity: the devkit's global velocity rotated into the lidar frame keeps its length
        # (up to the tilt, which moves a little of it into the dropped vz).
        # An unknown one (NaN) stays NaN, not 0.
        v_global = np.stack([nusc.box_velocity(a["token"]) for a in anns])
        known = np.isfinite(v_global).all(axis=1)
        np.testing.assert_array_equal(np.isfinite(boxes[:, 7:9]).all(axis=1), known)
        assert np.isnan(boxes[~known, 7:9]).all()
        speed_xy = np.linalg.norm(boxes[known, 7:9], axis=1)
        tol = 0.02 * np.linalg.norm(v_global[known], axis=1) + 1e-4
        assert (np.abs(speed_xy - np.linalg.norm(v_global[known, :2], axis=1)) <= tol).all()
        assert np.abs(v_global[known]).max() > 1.0


def test_multi_sweep_time_lag_and_alignment(train):
    s = train[1]
    pts = s.points
    lags = np.unique(pts[:, 4])
    n = train.cfg.n_sweeps
    assert (lags > 0).any()
    np.testing.assert_allclose(lags, SWEEP_S * np.round(lags / SWEEP_S), atol=1e-6)
    assert lags.max() <= (n - 1) * SWEEP_S + 1e-6
    np.testing.assert_allclose(lags, SWEEP_S * np.arange(n), atol=1e-6)   # the chain is long enough here
    # Static ground near the sensor lines up across sweeps (ego motion compensated via global).
    near = (np.abs(pts[:, 0]) < 10) & (np.abs(pts[:, 1]) < 10) & (pts[:, 2] < -1.5)
    z0 = np.median(pts[near & (pts[:, 4] == 0), 2])
    z1 = np.median(pts[near & np.isclose(pts[:, 4], SWEEP_S), 2])
    assert abs(z1 - z0) < 0.05
    # Above the ground (walls, poles, parked cars) the older sweeps land on the key sweep's
    # surfaces: most points have a key-frame neighbour within 0.1 m. Without the ego-motion
    # compensation (~0.27 m per sweep here) only about half do.
    from scipy.spatial import cKDTree
    up = pts[:, 2] > -1.0
    tree = cKDTree(pts[up & (pts[:, 4] == 0), :3])
    for k in range(1, n):
        dist, _ = tree.query(pts[up & np.isclose(pts[:, 4], k * SWEEP_S), :3])
        assert np.mean(dist < 0.1) > 0.7, k
    # n_sweeps=1 gives exactly the key sweep, bit for bit.
    one = NuScenesDetection(train.root, VERSION, "sim-train", DataConfig(n_sweeps=1))[1].points
    assert (one[:, 4] == 0).all() and np.array_equal(one, s.points[s.points[:, 4] == 0])


def test_projection_into_cam_front(train):
    H, W = train.cfg.image_size
    cam = CAMERAS.index("CAM_FRONT")
    for index in range(len(train)):
        s = collate([train[index]])                     # as the model sees it: torch, (1, ...)
        s = Batch(**{k: v[0] if k not in ("sample_tokens", "pasted") and v is not None else v
                     for k, v in vars(s).items()})
        T_cam_from_lidar = torch.linalg.inv(s.T_lidar_from_cam[cam].double())
        # The pixel map of the network's image: img_aug @ K (K is the original calibration).
        P = (s.img_aug[cam].double() @ s.intrinsics[cam].double()) @ T_cam_from_lidar[:3]
        centres = torch.cat([s.gt_boxes[:, :3].double(), torch.ones(len(s.gt_boxes), 1, dtype=torch.float64)], 1)
        uvz = centres @ P.T
        z_cam = (centres @ T_cam_from_lidar[2])
        uv = uvz[:, :2] / uvz[:, 2:3]
        in_image = (z_cam > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        # "Ahead of the car" = along CAM_FRONT's optical axis as seen in the lidar frame.
        axis = s.T_lidar_from_cam[cam, :3, 2].double()
        origin = s.T_lidar_from_cam[cam, :3, 3].double()
        ahead = (s.gt_boxes[:, :3].double() - origin) @ axis > 0
        assert (in_image & ahead).any()
        assert not (in_image & ~ahead).any()
        assert (z_cam[~ahead] < 0).all()


def test_box_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = Quaternion(rng.normal(size=4)).normalised
        T_global_from_lidar = np.eye(4)
        T_global_from_lidar[:3, :3], T_global_from_lidar[:3, 3] = q.rotation_matrix, rng.normal(size=3) * 100
        box = np.array([*rng.normal(size=3) * 30, *rng.uniform(0.5, 10, size=3), rng.uniform(-np.pi, np.pi)])
        t, wlh, rot = box_lidar_to_global(box, T_global_from_lidar)
        back = box_to_lidar(t, wlh, rot, np.linalg.inv(T_global_from_lidar))
        np.testing.assert_allclose(back, box, atol=1e-9)
        np.testing.assert_allclose(wlh, box[[4, 3, 5]])
    # Global -> lidar -> global is exact when the lidar is z-up (a yaw-only box stays yaw-only).
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Quaternion(axis=[0, 0, 1], angle=0.7).rotation_matrix, [400.0, -1200.0, 0.5]
    t0, wlh0, rot0 = np.array([410.0, -1190.0, 1.0]), np.array([1.9, 4.6, 1.6]), Quaternion(axis=[0, 0, 1], angle=-2.9)
    t, wlh, rot = box_lidar_to_global(box_to_lidar(t0, wlh0, rot0.elements, np.linalg.inv(T)), T)
    np.testing.assert_allclose(t, t0, atol=1e-9)
    np.testing.assert_allclose(wlh, wlh0, atol=1e-12)
    assert min(np.abs(rot - rot0.elements).max(), np.abs(rot + rot0.elements).max()) < 1e-9


def test_errors_name_the_file_or_split(tiny_dataset, tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(DataError, match="nowhere"):
        NuScenesDetection(missing, VERSION, "sim-train")
    with pytest.raises(DataError, match="sim-bogus"):
        NuScenesDetection(tiny_dataset, VERSION, "sim-bogus")
    # A truncated key-frame lidar file: copy the dataroot (sweeps linked, they stay intact).
    root = tmp_path / "copy"
    root.mkdir()
    for name in ("maps", "samples", VERSION):
        shutil.copytree(tiny_dataset / name, root / name)
    (root / "sweeps").symlink_to((tiny_dataset / "sweeps").resolve())
    # The lidarseg labels' folder left out: lidarseg.json names it, so the devkit cannot load.
    with pytest.raises(DataError, match="lidarseg"):
        NuScenesDetection(root, VERSION, "sim-train")
    (root / "lidarseg").symlink_to((tiny_dataset / "lidarseg").resolve())
    ds = NuScenesDetection(root, VERSION, "sim-train")
    lidar_sd = ds.nusc.get("sample_data", ds.nusc.get("sample", ds.sample_tokens[0])["data"]["LIDAR_TOP"])
    path = root / lidar_sd["filename"]
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size - 7)
    with pytest.raises(DataError, match=re.escape(path.name)):
        ds[0]
    # An unreadable image.
    cam_sd = ds.nusc.get("sample_data", ds.nusc.get("sample", ds.sample_tokens[1])["data"]["CAM_BACK"])
    (root / cam_sd["filename"]).write_bytes(b"not a jpeg")
    with pytest.raises(DataError, match=re.escape(cam_sd["filename"].split("/")[-1])):
        ds[1]


def _copy_dataroot(src, dst, copied=(VERSION,)):
    """A copy of the dataroot ``src`` at ``dst``: the folders ``copied`` copied, the rest linked."""
    dst.mkdir()
    for name in ("maps", "samples", "sweeps", "lidarseg", VERSION):
        if name in copied:
            shutil.copytree(src / name, dst / name)
        else:
            (dst / name).symlink_to((src / name).resolve())
    return dst


@pytest.mark.parametrize("field, value", [("translation", None), ("size", float("nan")), ("rotation", "junk")])
def test_a_bad_annotation_record_names_the_table_and_field(train, tmp_path, field, value):
    root = _copy_dataroot(train.root, tmp_path / "copy")
    table = root / VERSION / "sample_annotation.json"
    anns = json.loads(table.read_text())
    loaded = next(a for a in train.nusc.sample_annotation          # one the loader reads: a car with points
                  if a["num_lidar_pts"] > 5 and a["category_name"].startswith("vehicle.car"))
    ann = next(a for a in anns if a["token"] == loaded["token"])
    if value is None:
        del ann[field]
    elif isinstance(value, float):
        ann[field][0] = value                             # json writes NaN
    else:
        ann[field] = value
    table.write_text(json.dumps(anns))
    ds = NuScenesDetection(root, VERSION, ALL_SCENES)
    with pytest.raises(DataError, match=rf"sample_annotation\.json: record {ann['token']} .*'{field}'") as e:
        ds[ds.sample_tokens.index(ann["sample_token"])]
    assert "\n" not in str(e.value)


def test_a_non_finite_pose_names_the_table(tiny_dataset, tmp_path):
    root = _copy_dataroot(tiny_dataset, tmp_path / "copy")
    table = root / VERSION / "ego_pose.json"
    poses = json.loads(table.read_text())
    for pose in poses:
        pose["translation"][2] = float("inf")
    table.write_text(json.dumps(poses))
    with pytest.raises(DataError, match=r"ego_pose\.json: .*'translation' must be 3 finite numbers"):
        NuScenesDetection(root, VERSION, ALL_SCENES)[0]


def test_a_truncated_jpeg_and_a_missing_lidar_file_are_named(tiny_dataset, tmp_path):
    root = _copy_dataroot(tiny_dataset, tmp_path / "copy", copied=(VERSION, "samples"))
    ds = NuScenesDetection(root, VERSION, "sim-train")
    sample = ds.nusc.get("sample", ds.sample_tokens[0])
    image = root / ds.nusc.get("sample_data", sample["data"]["CAM_FRONT"])["filename"]
    image.write_bytes(image.read_bytes()[:-500])        # cut: the decoder would fill it with grey
    with pytest.raises(DataError, match=rf"truncated image file .*{re.escape(image.name)}"):
        ds[0]
    lidar = root / ds.nusc.get("sample_data", ds.nusc.get("sample", ds.sample_tokens[1])["data"]["LIDAR_TOP"])["filename"]
    lidar.unlink()
    with pytest.raises(DataError, match=rf"cannot read lidar file .*{re.escape(lidar.name)}"):
        ds[1]
