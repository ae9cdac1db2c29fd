"""The image-view pretraining set: the camera images of a nuScenes-format dataroot with their
dense labels (``simgen make --dense-labels``) and annotated boxes, and the loader's collate that
builds the targets of :mod:`clfbev.supervision.dense`.

Dense labels lie beside each camera image ``samples/CAM_X/NAME.jpg``: ``dense/CAM_X/NAME_depth.png``
(uint16, z-depth along the optical axis in metres x 256, 0 where nothing is hit) and
``dense/CAM_X/NAME_seg.png`` (uint8 nuScenes-lidarseg class, 0 = void). They are warped into the
network image by the image's own ``img_aug`` (resize and crop), nearest-neighbour: a depth or a
class is never averaged with its neighbour's.

The pretraining split must be a set of its own (its own ``simgen make`` seed), never one the
detector is evaluated on: :func:`data_identity` names the set, and the encoder checkpoint keeps it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import cv2
import numpy as np
import torch

from clfbev.config import ModelConfig
from clfbev.data import CAMERAS, Batch, NuScenesDetection, Sample, collate
from clfbev.errors import DataError
from clfbev.geometry import CameraGeometry
from clfbev.supervision.dense import DenseTargets, cell_depth_and_class, centre_targets

DENSE_DIR = "dense"
DEPTH_SCALE = 256.0      # KITTI's convention: the uint16 value is metres x 256


def dense_label_files(image_file: str) -> tuple[str, str]:
    """(depth, seg) files, relative to the dataroot, of the camera image ``samples/CAM_X/NAME.jpg``."""
    parts = PurePosixPath(image_file).parts
    stem = parts[-1].rsplit(".", 1)[0]
    return f"{DENSE_DIR}/{parts[-2]}/{stem}_depth.png", f"{DENSE_DIR}/{parts[-2]}/{stem}_seg.png"


@dataclass
class DenseSample:
    """One key frame for pretraining: ``sample`` (images, cameras, boxes as the detector loads
    them), ``depth`` (N, H, W) float32 metres of the network image (0 = none) and ``seg``
    (N, H, W) uint8 lidarseg class."""

    sample: Sample
    depth: np.ndarray
    seg: np.ndarray


class DenseLabelled(torch.utils.data.Dataset):
    """The key frames of ``split`` with their dense labels. Refuses (DataError naming the first
    missing file) a dataroot whose split lacks them."""

    def __init__(self, dataroot: str | Path, version: str, split: str, cfg: ModelConfig) -> None:
        self.base = NuScenesDetection(dataroot, version, split, cfg.data_config())
        self.root = Path(dataroot)
        if len(self.base) == 0:
            raise DataError(f"split '{split}' of {dataroot} has no samples")
        self.files = [self._label_files(token) for token in self.base.sample_tokens]
        missing = next((f for cams in self.files for pair in cams for f in pair if not (self.root / f).is_file()), None)
        if missing is not None:
            raise DataError(f"no dense labels: {self.root / missing} is missing (make the set with "
                            f"`simgen make --dense-labels`)")

    def _label_files(self, token: str) -> list[tuple[str, str]]:
        sample = self.base.nusc.get("sample", token)
        return [dense_label_files(self.base.nusc.get("sample_data", sample["data"][cam])["filename"])
                for cam in CAMERAS]

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, index: int) -> DenseSample:
        sample = self.base[index]
        H, W = sample.images.shape[-2:]
        depth, seg = [], []
        for (depth_file, seg_file), A in zip(self.files[index], sample.img_aug):
            depth.append(warp_nearest(_read_png(self.root / depth_file, np.uint16), A, (H, W)))
            seg.append(warp_nearest(_read_png(self.root / seg_file, np.uint8), A, (H, W)))
        return DenseSample(sample, np.stack(depth).astype(np.float32) / DEPTH_SCALE, np.stack(seg))


def _read_png(path: Path, dtype) -> np.ndarray:
    """(H, W) label image of ``dtype``; DataError naming the file when unreadable or of another kind."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"unreadable dense label file {path}")
    if img.ndim != 2 or img.dtype != dtype:
        raise DataError(f"dense label file {path}: expected a one-channel {np.dtype(dtype).name} PNG, "
                        f"got {img.dtype.name} of shape {img.shape}")
    return img


def warp_nearest(label: np.ndarray, A: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The (H, W) network view of a label image of the original camera image: ``A`` (3, 3) maps
    original to network pixels in the pixel-edge convention; OpenCV's maps act on pixel centres,
    hence the half-pixel shifts. Pixels from outside the original are 0 (no label)."""
    to_centres = np.array([[1.0, 0, -0.5], [0, 1.0, -0.5], [0, 0, 1.0]])
    M = (to_centres @ A @ np.linalg.inv(to_centres))[:2]
    H, W = size
    return cv2.warpAffine(label, M, (W, H), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


class DenseCollate:
    """The pretraining loader's ``collate_fn``: DenseSamples -> (Batch, :class:`DenseTargets`)."""

    def __init__(self, cfg: ModelConfig) -> None:
        self.cfg = cfg

    def __call__(self, samples: list[DenseSample]) -> tuple[Batch, DenseTargets]:
        batch = collate([s.sample for s in samples])
        return batch, build_dense_targets(batch, np.stack([s.depth for s in samples]),
                                          np.stack([s.seg for s in samples]), self.cfg)


@torch.no_grad()
def build_dense_targets(batch: Batch, depth: np.ndarray, seg: np.ndarray, cfg: ModelConfig) -> DenseTargets:
    """The targets of ``batch`` with dense labels depth (B, N, H, W) metres and seg (B, N, H, W)."""
    bins, classes = cell_depth_and_class(torch.from_numpy(depth), torch.from_numpy(seg), cfg.feature_stride,
                                         cfg.depth_bins)
    cams = CameraGeometry.of_batch(batch, cfg)
    heatmap, centres, codes = centre_targets(batch.gt_boxes, batch.gt_labels, cams, len(cfg.class_names))
    return DenseTargets(bins, classes, heatmap, centres, codes)


def data_identity(ds: DenseLabelled) -> dict:
    """What names the pretraining set: the dataroot, version, split, its scenes' log names (they
    carry simgen's seed) and a sha1 of its sorted sample tokens, so that a benchmark can check
    that the encoder never saw its evaluation samples."""
    nusc = ds.base.nusc
    scenes = sorted({nusc.get("sample", t)["scene_token"] for t in ds.base.sample_tokens})
    logs = sorted(nusc.get("log", nusc.get("scene", s)["log_token"])["logfile"] for s in scenes)
    digest = hashlib.sha1(json.dumps(sorted(ds.base.sample_tokens)).encode()).hexdigest()
    return {"dataroot": str(ds.root), "version": ds.base.version, "split": ds.base.split, "logs": logs,
            "samples": len(ds), "sample_tokens_sha1": digest}

