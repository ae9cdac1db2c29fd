"""nuScenes-format dataset -> typed ``Sample`` / ``Batch`` for CL-FusionBEV.

Reads any nuScenes-format dataroot (real nuScenes or one written by ``simgen``) through
nuscenes-devkit; it knows nothing about how the data were made.

Frames and conventions
----------------------
- Everything a model sees is in the KEY-FRAME lidar frame (the LIDAR_TOP sensor frame at the
  sample's lidar timestamp): points, boxes, and the camera extrinsics ``T_lidar_from_cam``.
- Every sensor record has its own ego pose (camera and lidar fire at different timestamps), so a
  sensor-to-sensor transform always goes through the global frame:
  ``T_global_from_X = T_global_from_ego(X's ego pose) @ T_ego_from_X(calibrated_sensor)``.
- Pixel coordinates use the pixel-edge convention (pixel c covers [c, c + 1)), as in
  :mod:`clfbev.camera_encoder`. ``intrinsics`` is the calibrated K of the ORIGINAL image and
  ``img_aug`` maps original pixels to the pixels of the image the network sees. Here that is a
  resize keeping the aspect ratio to the network width, then a crop of the top rows (sky) to
  the network height: ``A = [[s, 0, 0], [0, s', -top], [0, 0, 1]]`` with ``s = W'/W`` and
  ``s' = round(s H) / H`` (within 0.3% of s), exact in this convention; objects keep their
  aspect ratio. So a lidar point projects to ``[u', v', 1] ~ img_aug @ intrinsics @
  T_cam_from_lidar @ p`` (``A K`` is the K of the resized image). The camera encoder composes ``img_aug @ intrinsics`` itself, so K is not pre-scaled.
- Boxes are ``(x, y, z, l, w, h, yaw)`` (+ ``vx, vy``) as in :mod:`clfbev.ops.boxes`;
  :func:`box_to_lidar` and :func:`box_lidar_to_global` are the only crossings to the nuScenes
  global ``translation, size (w, l, h), rotation (w, x, y, z)`` form.
- A record that lacks a field the loader reads, or holds a non-finite number there, and a sensor
  file that is missing, truncated or undecodable raise a one-line :class:`DataError` naming the
  file (and the record and field).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from pyquaternion import Quaternion
from torch import Tensor

from clfbev import corruptions
from clfbev.attributes import still_state
from clfbev.errors import DataError
from clfbev.geometry import batch_depth_bins
from clfbev.sensor_files import IMAGE_MEAN, IMAGE_STD, load_image, load_points, resize_and_crop
from clfbev.settings import DataConfig

CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT")
LIDAR = "LIDAR_TOP"
ALL_SCENES = "all"       # the pseudo split of every scene in a version


@dataclass
class Sample:
    """One key frame, N = 6 cameras in ``CAMERAS`` order, all geometry in its lidar frame; numpy
    arrays until :func:`collate` makes the torch :class:`Batch`.

    images : (N, 3, H, W) float32, RGB normalised with ``IMAGE_MEAN`` / ``IMAGE_STD``.
    intrinsics : (N, 3, 3) float32 K of the original images.
    T_lidar_from_cam : (N, 4, 4) float32 camera -> key-frame lidar.
    img_aug : (N, 3, 3) float32 original -> network-image pixels.
    points : (n, 5) float32 x, y, z (m), intensity / 255, time lag (s, 0 = key frame).
    gt_boxes : (M, 9) float32 x, y, z, l, w, h, yaw, vx, vy (m/s, lidar axes); vx, vy NaN where
        the velocity is unknown (see :func:`velocity_or_still`).
    gt_labels : (M,) int64 index into ``DataConfig.class_names``.
    T_global_from_lidar : (4, 4) float64, to send predictions back to nuScenes global form.
    sample_token : the nuScenes sample token.
    pasted : (n,) bool, True for points GT-paste added (no pixel shows them), or None.
    image_features : (N, fpn_ch, h, w) float32 the frozen image encoder's FPN features of the
        network images, read from a feature cache (:mod:`clfbev.feature_cache`; ``images`` is then
        (N, 3, 0, 0): no pixel is decoded), or None.
    gt_still : (M,) int64 the still state of each box (:mod:`clfbev.attributes`: 0 or 1, which of
        its class's two attributes at rest), -1 where it has none to learn (a moving vehicle or
        walker, a cone, a pasted object), or None (no box's is known).
    camera_missing : (N,) bool the cameras that delivered nothing (modality dropout in training,
        ``camera_crash`` and ``frame_lost`` at evaluation), or None (all delivered): the model
        lifts nothing from them, and a sample without any camera gets an all-zero camera BEV
        (:class:`clfbev.model.CLFusionBEV`).
    """

    images: np.ndarray
    intrinsics: np.ndarray
    T_lidar_from_cam: np.ndarray
    img_aug: np.ndarray
    points: np.ndarray
    gt_boxes: np.ndarray
    gt_labels: np.ndarray
    T_global_from_lidar: np.ndarray
    sample_token: str
    pasted: np.ndarray | None = None
    image_features: np.ndarray | None = None
    camera_missing: np.ndarray | None = None
    gt_still: np.ndarray | None = None


@dataclass
class Batch:
    """B samples as torch tensors. Shapes as in :class:`Sample` with a leading B; ragged data
    stay lists.

    images : (B, N, 3, H, W) float32.  intrinsics : (B, N, 3, 3).  T_lidar_from_cam : (B, N, 4, 4).
    img_aug : (B, N, 3, 3).  T_global_from_lidar : (B, 4, 4) float64.
    points : list of B (n_i, 5).  gt_boxes : list of B (M_i, 9).  gt_labels : list of B (M_i,).
    sample_tokens : list of B str.  pasted : list of B (n_i,) bool or None (see :class:`Sample`).
    gt_still : list of B (M_i,) int64 (-1 where :class:`Sample` has None).
    image_features : (B, N, fpn_ch, h, w) float32 or None.  camera_missing : (B, N) bool or None
    (every camera delivered).
    depth_bins : (B, N, H / s, W / s) int64 per camera feature cell (stride s =
        ``ModelConfig.feature_stride``), the depth bin (camera z, ``ModelConfig.depth_bins``) of
        its nearest key-frame lidar point, pasted points left out, -1 where none
        (:func:`clfbev.geometry.batch_depth_bins`): the depth the oracle lift
        (``ModelConfig.cam_oracle_depth``) lifts with, projected once in the loader by
        :func:`collate` with that config (or by the training collate, from its depth targets);
        None without the oracle.
    """

    images: Tensor
    intrinsics: Tensor
    T_lidar_from_cam: Tensor
    img_aug: Tensor
    points: list[Tensor]
    gt_boxes: list[Tensor]
    gt_labels: list[Tensor]
    T_global_from_lidar: Tensor
    sample_tokens: list[str] = field(default_factory=list)
    pasted: list[Tensor | None] = field(default_factory=list)
    image_features: Tensor | None = None
    camera_missing: Tensor | None = None
    depth_bins: Tensor | None = None
    gt_still: list[Tensor] = field(default_factory=list)

    def to(self, device: torch.device | str) -> "Batch":
        """A copy with every tensor on ``device`` (tokens are shared)."""
        return Batch(
            images=self.images.to(device),
            intrinsics=self.intrinsics.to(device),
            T_lidar_from_cam=self.T_lidar_from_cam.to(device),
            img_aug=self.img_aug.to(device),
            points=[p.to(device) for p in self.points],
            gt_boxes=[b.to(device) for b in self.gt_boxes],
            gt_labels=[labels.to(device) for labels in self.gt_labels],
            T_global_from_lidar=self.T_global_from_lidar.to(device),
            sample_tokens=list(self.sample_tokens),
            pasted=[None if m is None else m.to(device) for m in self.pasted],
            image_features=None if self.image_features is None else self.image_features.to(device),
            camera_missing=None if self.camera_missing is None else self.camera_missing.to(device),
            depth_bins=None if self.depth_bins is None else self.depth_bins.to(device),
            gt_still=[s.to(device) for s in self.gt_still],
        )

    def select(self, index: list[int]) -> "Batch":
        """The batch of the samples ``index`` (in that order): every stacked tensor indexed along
        its batch dimension, every per-sample list picked; the tensors are views or copies, never
        changed in place."""
        picked = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Tensor):
                picked[f.name] = value[index]
            elif isinstance(value, list) and value:
                picked[f.name] = [value[i] for i in index]
            else:
                picked[f.name] = value      # None, or a list the batch does not fill (no pasted masks)
        return Batch(**picked)


def _tensor(a: np.ndarray) -> Tensor:
    """``a`` as a tensor sharing its memory (a copy when numpy marks it read-only)."""
    return torch.from_numpy(a if a.flags.writeable else a.copy())


def collate(samples: list[Sample], model_cfg=None) -> Batch:
    """numpy Samples -> the torch Batch: fixed-size fields stacked, points and boxes per-sample
    lists; with ``model_cfg`` (the :class:`clfbev.config.ModelConfig` of the model the batch is
    for) and its ``cam_oracle_depth`` on, the oracle's ``depth_bins`` too (else nothing more)."""
    batch = Batch(
        images=_tensor(np.stack([s.images for s in samples])),
        intrinsics=_tensor(np.stack([s.intrinsics for s in samples])),
        T_lidar_from_cam=_tensor(np.stack([s.T_lidar_from_cam for s in samples])),
        img_aug=_tensor(np.stack([s.img_aug for s in samples])),
        points=[_tensor(s.points) for s in samples],
        gt_boxes=[_tensor(s.gt_boxes) for s in samples],
        gt_labels=[_tensor(s.gt_labels) for s in samples],
        T_global_from_lidar=_tensor(np.stack([s.T_global_from_lidar for s in samples])),
        sample_tokens=[s.sample_token for s in samples],
        pasted=[None if s.pasted is None else _tensor(s.pasted) for s in samples],
        image_features=(None if any(s.image_features is None for s in samples)
                        else _tensor(np.stack([s.image_features for s in samples]))),
        camera_missing=(None if all(s.camera_missing is None for s in samples) else
                        torch.from_numpy(np.stack([np.zeros(len(s.intrinsics), bool) if s.camera_missing is None
                                                   else s.camera_missing for s in samples]))),
        gt_still=[torch.full((len(s.gt_boxes),), -1, dtype=torch.int64) if s.gt_still is None
                  else _tensor(s.gt_still) for s in samples],
    )
    if model_cfg is not None and model_cfg.cam_oracle_depth:
        batch.depth_bins = batch_depth_bins(batch, model_cfg)
    return batch


# ---------------------------------------------------------------- transforms and boxes

def velocity_or_still(boxes: np.ndarray) -> np.ndarray:
    """(M, 2) float64 the velocities (vx, vy) of ``boxes`` (M, 9), an unknown one as standing still.

    The unknown-velocity contract: an annotation whose velocity the devkit cannot tell (NaN from
    ``box_velocity``: no neighbour in time) keeps NaN in ``Sample.gt_boxes`` through every
    augmentation and paste, and the velocity loss masks it
    (:func:`clfbev.supervision.assign.assign_targets`), so no box is trained toward a speed it
    was never measured at. Only geometry that must move a box with its object (which points
    belong to it, where it was at an older sweep) reads it as 0, through this function; a
    target never does.
    """
    return np.nan_to_num(np.asarray(boxes, dtype=np.float64)[..., 7:9], nan=0.0)


def transform_from(translation, rotation_wxyz) -> np.ndarray:
    """(4, 4) float64 T_parent_from_child of a nuScenes record (translation, wxyz quaternion)."""
    T = np.eye(4)
    T[:3, :3] = Quaternion(rotation_wxyz).rotation_matrix
    T[:3, 3] = translation
    return T


def box_to_lidar(translation, size_wlh, rotation_wxyz, T_lidar_from_global: np.ndarray) -> np.ndarray:
    """A nuScenes global box -> (7,) float64 ``x, y, z, l, w, h, yaw`` in the lidar frame.

    The yaw is the heading of the box's rotated x axis, as devkit's ``quaternion_yaw``; the
    lidar's small roll/pitch relative to the ground is dropped (boxes are yaw-only).
    """
    R_lidar_from_box = T_lidar_from_global[:3, :3] @ Quaternion(rotation_wxyz).rotation_matrix
    centre = T_lidar_from_global[:3, :3] @ np.asarray(translation, float) + T_lidar_from_global[:3, 3]
    w, l, h = size_wlh
    yaw = np.arctan2(R_lidar_from_box[1, 0], R_lidar_from_box[0, 0])
    return np.array([*centre, l, w, h, yaw], dtype=np.float64)


def box_lidar_to_global(box7, T_global_from_lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`box_to_lidar`: (7,) lidar box -> (translation (3,), size wlh (3,), rotation wxyz (4,))."""
    x, y, z, l, w, h, yaw = (float(v) for v in box7[:7])
    c, s = np.cos(yaw), np.sin(yaw)
    R_lidar_from_box = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R_global_from_box = T_global_from_lidar[:3, :3] @ R_lidar_from_box
    translation = T_global_from_lidar[:3, :3] @ np.array([x, y, z]) + T_global_from_lidar[:3, 3]
    # Re-orthonormalise: pyquaternion rejects matrices a few ulp away from a rotation.
    u, _, vt = np.linalg.svd(R_global_from_box)
    rotation = Quaternion(matrix=u @ vt).elements
    return translation, np.array([w, l, h]), rotation


# ---------------------------------------------------------------- splits and tables

def split_scene_names(dataroot: Path, version: str, split: str) -> list[str]:
    """Scene names of an official split, else of a key of ``<dataroot>/<version>/splits.json``.

    As DetectionEval does, splits.json is only read for names that are not official.
    """
    from nuscenes.utils.splits import create_splits_scenes
    official = create_splits_scenes()
    if split in official:
        return list(official[split])
    path = dataroot / version / "splits.json"
    try:
        splits = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"split '{split}' is not official and {path} does not exist") from None
    except (OSError, ValueError) as e:
        raise DataError(f"cannot read splits file {path}: {e}") from None
    if split not in splits:
        raise DataError(f"split '{split}' is neither official nor in {path} (has: {', '.join(sorted(splits))})")
    return list(splits[split])


# ---------------------------------------------------------------- dataset

def require_tables(dataroot: str | Path, version: str) -> None:
    """A :class:`DataError` unless ``<dataroot>/<version>/`` exists."""
    if not (Path(dataroot) / version).is_dir():
        raise DataError(f"no nuScenes tables at {Path(dataroot) / version} (dataroot {dataroot}, version {version})")


def load_nuscenes(dataroot: str | Path, version: str):
    """``NuScenes(version, dataroot)``, with a :class:`DataError` naming the problem instead of the
    devkit's exception (a missing table, corrupt JSON, lidarseg.json without its
    ``lidarseg/<version>/`` folder)."""
    from nuscenes import NuScenes
    require_tables(dataroot, version)
    try:
        return NuScenes(version=version, dataroot=str(dataroot), verbose=False)
    except (OSError, AssertionError, ValueError, KeyError) as e:
        raise DataError(f"nuscenes-devkit cannot load {Path(dataroot) / version}: {e}") from None


class NuScenesDetection(torch.utils.data.Dataset):
    """Key-frame samples of one split of a nuScenes-format dataroot, as :class:`Sample`.

    Parameters
    ----------
    dataroot : folder holding ``<version>/``, ``samples/``, ``sweeps/``, ``maps/``.
    version : e.g. ``v1.0-mini`` or ``v1.0-sim``.
    split : an official split name, a key of ``<dataroot>/<version>/splits.json``, or
        :data:`ALL_SCENES` for every scene of the version (e.g. a dataroot without splits).
    cfg : :class:`DataConfig`.
    corruptions : :class:`clfbev.corruptions.Corruption` s applied to every sample (robustness
        evaluation), deterministic per sample token.
    """

    def __init__(self, dataroot: str | Path, version: str, split: str, cfg: DataConfig = DataConfig(),
                 corruptions: tuple = ()):
        self.root = Path(dataroot)
        self.cfg, self.version, self.split = cfg, version, split
        self.corruptions = tuple(corruptions)     # clfbev.corruptions.Corruption, applied at load time
        require_tables(self.root, version)          # before the split names: a bad split fails fast
        if split != ALL_SCENES:
            names = split_scene_names(self.root, version, split)
        self.nusc = load_nuscenes(self.root, version)
        if split == ALL_SCENES:
            names = [s["name"] for s in self.nusc.scene]
        scene_by_name = {s["name"]: s for s in self.nusc.scene}
        missing = [n for n in names if n not in scene_by_name]
        # Official splits list all of trainval; a version (e.g. mini) holds only some of them.
        if missing and (len(missing) == len(names) or split not in _official_splits()):
            raise DataError(f"split '{split}' names scenes not in {self.root / version}/scene.json: {missing[:5]}")
        self.sample_tokens: list[str] = []
        for name in names:
            if name not in scene_by_name:
                continue
            token = scene_by_name[name]["first_sample_token"]
            while token:                                  # the scene's samples in time order
                self.sample_tokens.append(token)
                token = self.nusc.get("sample", token)["next"]

    def __len__(self) -> int:
        return len(self.sample_tokens)

    def __getitem__(self, index: int) -> Sample:
        sample = self.nusc.get("sample", self.sample_tokens[index])
        lidar_sd = self.nusc.get("sample_data", sample["data"][LIDAR])
        T_global_from_lidar = self._T_global_from_sensor(lidar_sd)
        T_lidar_from_global = np.linalg.inv(T_global_from_lidar)
        images, K, T_lidar_from_cam, A = self._cameras(sample, T_lidar_from_global)
        points = self._corrupted_points(sample, lidar_sd, T_lidar_from_global)
        missing = None
        if self.corruptions:
            T_ego_from_lidar = self._T_parent_from(lidar_sd, "calibrated_sensor")
            up_lidar = T_ego_from_lidar[:3, :3].T @ np.array([0, 0, 1.0])
            images, T_lidar_from_cam, missing = corruptions.corrupt_cameras(
                images, T_lidar_from_cam, K, A, up_lidar, corruptions.camera_corruptions(self.corruptions),
                sample["token"])
            missing = missing if missing.any() else None
        boxes, labels, still = self._boxes(sample, T_lidar_from_global)
        return Sample(
            images=images,
            intrinsics=K.astype(np.float32),
            T_lidar_from_cam=T_lidar_from_cam.astype(np.float32),
            img_aug=A.astype(np.float32),
            points=points,
            gt_boxes=boxes,
            gt_labels=labels,
            T_global_from_lidar=T_global_from_lidar,
            sample_token=sample["token"],
            camera_missing=missing,
            gt_still=still,
        )

    def lidar_points(self, index: int) -> np.ndarray:
        """(n, 5) float32 points of sample ``index``, corrupted, exactly as :meth:`__getitem__`
        gives them, without reading its cameras."""
        sample = self.nusc.get("sample", self.sample_tokens[index])
        lidar_sd = self.nusc.get("sample_data", sample["data"][LIDAR])
        T_lidar_from_global = np.linalg.inv(self._T_global_from_sensor(lidar_sd))
        return self._corrupted_points(sample, lidar_sd, T_lidar_from_global)

    def _corrupted_points(self, sample: dict, lidar_sd: dict, T_lidar_from_global: np.ndarray) -> np.ndarray:
        """:meth:`_points` with the lidar corruptions applied."""
        points, rings = self._points(lidar_sd, T_lidar_from_global)
        lidar = corruptions.lidar_corruptions(self.corruptions)
        if not lidar:
            return points
        T_ego_from_lidar = self._T_parent_from(lidar_sd, "calibrated_sensor")
        forward_lidar = T_ego_from_lidar[:3, :3].T @ np.array([1.0, 0, 0])
        return corruptions.corrupt_points(points, rings, forward_lidar, lidar, sample["token"])

    def lidar_and_boxes(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What sample ``index`` holds without its cameras (and without the corruptions applied after
        loading; ``misalign`` and ``late`` change what is read, so they stay): points (n, 5),
        gt_boxes (M, 9) and gt_labels (M,), as :meth:`__getitem__` gives them. For work that
        needs no image (the GT-paste database): decoding the six JPEGs is most of a sample's
        load time."""
        sample = self.nusc.get("sample", self.sample_tokens[index])
        lidar_sd = self.nusc.get("sample_data", sample["data"][LIDAR])
        T_lidar_from_global = np.linalg.inv(self._T_global_from_sensor(lidar_sd))
        points, _ = self._points(lidar_sd, T_lidar_from_global)
        boxes, labels, _ = self._boxes(sample, T_lidar_from_global)
        return points, boxes, labels

    # ------------------------------------------------------------ the tables' records, checked

    def _field(self, table: str, record: dict, name: str):
        """``record[name]`` of a record of ``<table>.json``; a :class:`DataError` naming the file,
        the record and the field when it is missing."""
        try:
            return record[name]
        except KeyError:
            raise DataError(f"{self.root / self.version / table}.json: record {record.get('token', '?')} "
                            f"has no field '{name}'") from None

    def _numbers(self, table: str, record: dict, name: str, shape: tuple[int, ...]):
        """``record[name]`` as it is, once checked to be finite numbers of ``shape``."""
        value = self._field(table, record, name)
        try:
            ok = np.asarray(value, dtype=np.float64).shape == shape and np.isfinite(value).all()
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise DataError(f"{self.root / self.version / table}.json: record {record.get('token', '?')} field "
                            f"'{name}' must be {math.prod(shape)} finite numbers, got {value!r}")
        return value

    def _T_parent_from(self, sd: dict, table: str) -> np.ndarray:
        """(4, 4) float64 transform of the ``ego_pose`` (T_global_from_ego) or
        ``calibrated_sensor`` (T_ego_from_sensor) record of sample_data ``sd``."""
        record = self.nusc.get(table, self._field("sample_data", sd, f"{table}_token"))
        T = transform_from(self._numbers(table, record, "translation", (3,)),
                           self._numbers(table, record, "rotation", (4,)))
        # A ``misalign`` corruption: the loader believes a wrong calibration of that sensor.
        if table == "calibrated_sensor" and self.corruptions:
            T = corruptions.miscalibrated(T, sd["channel"], self.corruptions)
        return T

    def _file(self, sd: dict) -> Path:
        """The sensor file read for sample_data ``sd``: its own, or an older one of its channel
        under a ``late`` corruption (:func:`clfbev.corruptions.late_record`)."""
        return self.root / self._field("sample_data", corruptions.late_record(sd, self.corruptions, self.nusc.get),
                                       "filename")

    def _T_global_from_sensor(self, sd: dict) -> np.ndarray:
        """(4, 4) float64 T_global_from_X for a sample_data record X (its own ego pose)."""
        return self._T_parent_from(sd, "ego_pose") @ self._T_parent_from(sd, "calibrated_sensor")

    def _cameras(self, sample: dict, T_lidar_from_global: np.ndarray):
        """images (N, 3, H, W) float32, K (N, 3, 3), T_lidar_from_cam (N, 4, 4), img_aug (N, 3, 3)."""
        images, Ks, Ts, As = [], [], [], []
        for cam in CAMERAS:
            sd = self.nusc.get("sample_data", sample["data"][cam])
            calib = self.nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            image, A = self._camera_input(self._file(sd))
            images.append(image)
            Ks.append(np.asarray(self._numbers("calibrated_sensor", calib, "camera_intrinsic", (3, 3)), np.float64))
            Ts.append(T_lidar_from_global @ self._T_global_from_sensor(sd))
            As.append(A)
        return np.stack(images), np.stack(Ks), np.stack(Ts), np.stack(As)

    def _camera_input(self, path: Path) -> tuple[np.ndarray, np.ndarray]:
        """What the network reads of the camera image file ``path`` and its img_aug (3, 3):
        :func:`network_image` (a feature-cache dataset reads the cached features instead)."""
        return network_image(path, self.cfg.image_size)

    def _points(self, key_sd: dict, T_lidar_from_global: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 5) float32 points of the key sweep and its previous sweeps, key-frame lidar frame
        (x, y, z, intensity / 255, time lag), and their (n,) ring indices."""
        chunks, rings, sd = [], [], key_sd
        key_time = self._numbers("sample_data", key_sd, "timestamp", ())
        for k in range(self.cfg.n_sweeps):
            raw = load_points(self._file(sd))
            xyz = raw[:, :3]
            if k > 0:   # the key sweep stays bit-exact: it is already in the key-frame lidar frame
                T_key_from_sweep = T_lidar_from_global @ self._T_global_from_sensor(sd)
                xyz = (xyz.astype(np.float64) @ T_key_from_sweep[:3, :3].T + T_key_from_sweep[:3, 3]).astype(np.float32)
            lag = (key_time - self._numbers("sample_data", sd, "timestamp", ())) * 1e-6     # integer us -> s
            chunks.append(np.column_stack([xyz, raw[:, 3] / np.float32(255.0), np.full(len(raw), lag, np.float32)]))
            rings.append(raw[:, 4])
            if not sd["prev"]:
                break
            sd = self.nusc.get("sample_data", sd["prev"])
        pts = np.concatenate(chunks).astype(np.float32)
        lo, hi = np.asarray(self.cfg.point_range[:3]), np.asarray(self.cfg.point_range[3:])
        keep = ((pts[:, :3] >= lo) & (pts[:, :3] < hi)).all(axis=1)
        return np.ascontiguousarray(pts[keep]), np.concatenate(rings)[keep]

    def _boxes(self, sample: dict, T_lidar_from_global: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """gt_boxes (M, 9) float32 and gt_labels (M,) int64 in the key-frame lidar frame, and
        gt_still (M,) int64 (:class:`Sample`)."""
        from nuscenes.eval.detection.utils import category_to_detection_name
        label_of = {name: i for i, name in enumerate(self.cfg.class_names)}
        R_lidar_from_global = T_lidar_from_global[:3, :3]
        boxes, labels, still = [], [], []
        for token in sample["anns"]:
            ann = self.nusc.get("sample_annotation", token)
            name = category_to_detection_name(self._field("sample_annotation", ann, "category_name"))
            if name not in label_of or self._numbers("sample_annotation", ann, "num_lidar_pts", ()) < self.cfg.min_points:
                continue
            box = box_to_lidar(self._numbers("sample_annotation", ann, "translation", (3,)),
                               self._numbers("sample_annotation", ann, "size", (3,)),
                               self._numbers("sample_annotation", ann, "rotation", (4,)), T_lidar_from_global)
            velocity = self._velocity(token)       # global, m/s; NaN (unknown) stays NaN
            v_lidar = R_lidar_from_global @ velocity
            boxes.append(np.concatenate([box, v_lidar[:2]]))
            labels.append(label_of[name])
            attributes = [self.nusc.get("attribute", t)["name"]
                          for t in self._field("sample_annotation", ann, "attribute_tokens")]
            still.append(max((still_state(name, a) for a in attributes), default=-1))
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 9)
        labels = np.asarray(labels, dtype=np.int64)
        lo, hi = np.asarray(self.cfg.point_range[:3]), np.asarray(self.cfg.point_range[3:])
        keep = ((boxes[:, :3] >= lo) & (boxes[:, :3] < hi)).all(axis=1)
        return boxes[keep].astype(np.float32), labels[keep], np.asarray(still, dtype=np.int64)[keep]

    def _velocity(self, token: str) -> np.ndarray:
        """(3,) the devkit's velocity of annotation ``token`` (global, m/s; NaN where unknown),
        from its neighbours in time, whose records it reads."""
        try:
            return self.nusc.box_velocity(token)
        except KeyError as e:
            raise DataError(f"{self.root / self.version}/sample_annotation.json: a neighbour of record {token} "
                            f"has no field {e}") from None


def network_image(path: Path, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The image file ``path`` as the network sees it: (3, H, W) float32 RGB normalised with
    ``IMAGE_MEAN`` / ``IMAGE_STD`` after :func:`clfbev.sensor_files.resize_and_crop` to ``size``,
    and that (3, 3) float64 map from original to network pixels."""
    image, A = resize_and_crop(load_image(path), size)
    return ((image.astype(np.float32) / 255.0 - IMAGE_MEAN) / IMAGE_STD).transpose(2, 0, 1), A


def _official_splits() -> set[str]:
    from nuscenes.utils.splits import create_splits_scenes
    return set(create_splits_scenes())
