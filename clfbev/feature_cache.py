"""The frozen image encoder's features, computed once per image and kept on disk.

A camera stage whose ResNet and FPN are frozen
(:meth:`clfbev.camera_encoder.CameraEncoder.freeze_image_features`) computes the same FPN
features of an image in every epoch. ``clfbev cache-features`` computes them once
(:func:`fill_cache`), and ``clfbev train --feature-cache CACHE`` reads them
(:class:`CachedFeatureDataset`) in place of decoding the images and running the encoder; the
depth net and everything after it train on them. The image-space augmentation is off there (it
would change the features); the BEV-space one stays (:mod:`clfbev.augment`).

Content-addressed: an entry holds the FPN features of ONE image, keyed by the sha256 of the
image file's bytes, in a cache folder that belongs to ONE encoder (``encoder.json``, its
:func:`encoder_identity`: the ResNet's and FPN's weights, the input size and stride, the code
that decodes, resizes, normalises and encodes an image, and the numeric setting the features are
computed in). A changed image has another key, hence no entry, and is refused; another encoder
is refused by the folder; an entry whose header names another image or encoder, or whose bytes
are cut short, is refused: each a one-line :class:`clfbev.errors.DataError` (exit 2).

Exact: an entry is ``encoder.fpn_features`` of the image alone (a batch of one), in eval mode,
on one torch thread, stored as float32, bit for bit. Both settings matter: the same image in a
batch of six differs in the last bits (up to 5e-6), and on two threads too (1e-5), so only a
fixed computation makes an entry a function of the image and the encoder alone.

Layout: ``CACHE/encoder.json`` and ``CACHE/<first 2 hex>/<sha256>.feat``. An entry's bytes:
:data:`MAGIC`, a little-endian uint32 header length, the JSON header (``image_sha256``,
``encoder``, ``shape``, ``dtype``, ``img_aug``: the (3, 3) original -> network pixel map of
:func:`clfbev.data.network_image`, so no pixel is decoded to know it), then the (fpn_ch, h, w)
float32 features in C order. Each entry is written atomically (:mod:`clfbev.io`): a killed
run leaves whole entries only, and a rerun computes exactly the missing ones, so its cache is
byte-identical to an uninterrupted run's. Size: ``fpn_ch * h * w * 4`` bytes per image, for
``tiny`` 64 x 24 x 44 x 4 = 270,336 B plus a header of about 300 B, 1.6 MB per sample of six.
"""
from __future__ import annotations

import hashlib
import inspect
import json
import math
import struct
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from clfbev import io
from clfbev.camera_encoder import CameraEncoder
from clfbev.data import CAMERAS, NuScenesDetection, Sample, network_image
from clfbev.errors import DataError
from clfbev.sensor_files import IMAGE_MEAN, IMAGE_STD, load_image, resize_and_crop
from clfbev.settings import DataConfig

FORMAT = "clfbev-feature-cache-v1"
MAGIC = b"CLFBEV-FEAT1\n"
MANIFEST = "encoder.json"
SUFFIX = ".feat"
_LEN = struct.Struct("<I")


# ---------------------------------------------------------------- identities

def image_key(raw: bytes) -> str:
    """The key of an image file: the sha256 hex digest of its bytes."""
    return hashlib.sha256(raw).hexdigest()


def _tensor_bytes(t: torch.Tensor) -> bytes:
    return t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes()


def encoder_identity(encoder: CameraEncoder) -> dict:
    """What the cached features of ``encoder`` depend on, and ``id``, the sha256 of all of it.

    ``weights_sha256``: every tensor (name, dtype, shape, bytes) of the ResNet and the FPN, the
    BatchNorm statistics included; ``code_sha256``: the source of the modules that define them
    (the ResNet or EfficientNet and the FPN) and of the image's decoding, resize, crop and
    normalisation (a change of any of it may move the features); the input size, stride and
    feature shape; the ImageNet mean and std; torch's
    version and CPU kernel capability, one thread, float32 (the features' bits depend on them).
    """
    weights = hashlib.sha256()
    tensors = {**{f"backbone.{k}": v for k, v in encoder.backbone.state_dict().items()},
               **{f"neck.{k}": v for k, v in encoder.neck.state_dict().items()}}
    for name in sorted(tensors):
        t = tensors[name]
        weights.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        weights.update(_tensor_bytes(t))
    code = hashlib.sha256()
    for source in (sys.modules[type(encoder.backbone).__module__], sys.modules[type(encoder.neck).__module__],
                   network_image, resize_and_crop, load_image):
        code.update(inspect.getsource(source).encode())
    H, W = encoder.image_size
    s = encoder.feature_stride
    identity = {
        "format": FORMAT, "image_size": [H, W], "feature_stride": s,
        "feature_shape": [encoder.depth_net.in_channels, H // s, W // s],
        "backbone": type(encoder.backbone).__name__, "weights_sha256": weights.hexdigest(),
        "code_sha256": code.hexdigest(), "image_mean": IMAGE_MEAN.tolist(), "image_std": IMAGE_STD.tolist(),
        "torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(), "threads": 1,
        "dtype": "float32",
    }
    return {**identity, "id": hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()}


@torch.no_grad()
def encode_image(encoder: CameraEncoder, image: np.ndarray) -> np.ndarray:
    """(fpn_ch, h, w) float32 C-order: ``encoder.fpn_features`` of the (3, H, W) network image
    alone, in eval mode on one torch thread (the computation an entry holds, bit for bit)."""
    threads, was_training = torch.get_num_threads(), encoder.training
    torch.set_num_threads(1)
    encoder.eval()
    try:
        device = next(encoder.parameters()).device
        fpn = encoder.fpn_features(torch.from_numpy(np.ascontiguousarray(image))[None, None].to(device))
        return fpn[0].float().cpu().contiguous().numpy()
    finally:
        encoder.train(was_training)
        torch.set_num_threads(threads)


# ---------------------------------------------------------------- the cache

class FeatureCache:
    """The cache folder ``root`` of the encoder ``identity`` (:func:`encoder_identity`)."""

    def __init__(self, root: str | Path, identity: dict) -> None:
        self.root, self.identity = Path(root), identity
        self.shape = tuple(identity["feature_shape"])

    @classmethod
    def create(cls, root: str | Path, identity: dict) -> FeatureCache:
        """The cache at ``root`` for writing ``identity``'s features: a new folder gets its
        manifest; an existing one must be of the same encoder. Temporary files that a killed
        writer left are removed (one writer per cache)."""
        root = Path(root)
        if (root / MANIFEST).exists():
            cache = cls.open(root)
            cache.check_encoder(identity)
        else:
            io.write_json(root / MANIFEST, identity, indent=1)
            cache = cls(root, identity)
        for stale in root.glob(f"*/.*.tmp{SUFFIX}"):
            stale.unlink(missing_ok=True)
        return cache

    @classmethod
    def open(cls, root: str | Path) -> FeatureCache:
        """The existing cache at ``root``, its encoder read from its manifest."""
        path = Path(root) / MANIFEST
        try:
            identity = json.loads(path.read_text())
        except FileNotFoundError:
            raise DataError(f"{root} is not a feature cache (no {MANIFEST}; `clfbev cache-features` makes one)") from None
        except (OSError, ValueError) as e:
            raise DataError(f"feature cache manifest {path} is unreadable ({e})") from None
        if not isinstance(identity, dict) or identity.get("format") != FORMAT or "id" not in identity:
            raise DataError(f"{path} is not a {FORMAT} manifest")
        return cls(root, identity)

    def check_encoder(self, identity: dict) -> None:
        """Refuse the cache unless it holds the features of the encoder ``identity``; the
        message names the differing fields."""
        if identity["id"] != self.identity["id"]:
            diff = sorted(k for k in set(identity) | set(self.identity) if k != "id" and identity.get(k) != self.identity.get(k))
            raise DataError(f"feature cache {self.root} holds the features of another encoder (differs in: "
                            f"{', '.join(diff) or 'id'}); rerun `clfbev cache-features` into another --out")

    def entry_path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}{SUFFIX}"

    def entry_bytes(self, key: str, features: np.ndarray, img_aug: np.ndarray) -> bytes:
        """The bytes of the entry of image ``key``: header and (fpn_ch, h, w) float32 features."""
        if features.shape != self.shape or features.dtype != np.float32:
            raise ValueError(f"features {features.shape} {features.dtype}, the cache holds {self.shape} float32")
        header = json.dumps({"image_sha256": key, "encoder": self.identity["id"], "shape": list(self.shape),
                             "dtype": "float32", "img_aug": np.asarray(img_aug, np.float64).ravel().tolist()},
                            sort_keys=True).encode()
        return MAGIC + _LEN.pack(len(header)) + header + np.ascontiguousarray(features).tobytes()

    def write(self, key: str, features: np.ndarray, img_aug: np.ndarray) -> Path:
        """Write the entry of image ``key`` atomically."""
        return io.write_bytes(self.entry_path(key), self.entry_bytes(key, features, img_aug))

    def read(self, key: str, image: Path | str = "") -> tuple[np.ndarray, np.ndarray]:
        """(features (fpn_ch, h, w) float32, img_aug (3, 3) float64) of image ``key`` (the file
        ``image``, for the messages); DataError when there is no entry or it is not this
        image's and this encoder's."""
        path = self.entry_path(key)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raise DataError(f"feature cache {self.root} has no features of image {image or key} (sha256 {key[:16]}: "
                            f"changed since, or never cached); run `clfbev cache-features` for it") from None
        except OSError as e:
            raise DataError(f"cannot read feature cache entry {path}: {e.strerror}") from None
        return self._parse(raw, key, path)

    def valid(self, key: str) -> bool:
        """Whether image ``key`` has an entry that :meth:`read` accepts."""
        try:
            self.read(key)
        except DataError:
            return False
        return True

    def _parse(self, raw: bytes, key: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
        head = len(MAGIC) + _LEN.size
        why = None
        if raw[:len(MAGIC)] != MAGIC or len(raw) < head:
            why = "not a feature cache entry"
        else:
            n = _LEN.unpack(raw[len(MAGIC):head])[0]
            try:
                header = json.loads(raw[head:head + n])
            except ValueError:
                header = None
            payload = raw[head + n:]
            if not isinstance(header, dict):
                why = "its header is unreadable"
            elif header.get("image_sha256") != key:
                why = "it holds the features of another image"
            elif header.get("encoder") != self.identity["id"]:
                why = "it was computed by another encoder"
            elif header.get("shape") != list(self.shape) or len(payload) != math.prod(self.shape) * 4:
                why = f"it holds {len(payload)} bytes of features, not {self.shape} float32"
        if why is not None:
            raise DataError(f"feature cache entry {path} is refused: {why}; rerun `clfbev cache-features`")
        features = np.frombuffer(payload, dtype=np.float32).reshape(self.shape)
        return features, np.asarray(header["img_aug"], dtype=np.float64).reshape(3, 3)


# ---------------------------------------------------------------- filling and reading

def camera_files(dataset: NuScenesDetection, index: int) -> list[Path]:
    """The camera image files of sample ``index`` of ``dataset``, in ``CAMERAS`` order."""
    sample = dataset.nusc.get("sample", dataset.sample_tokens[index])
    return [dataset.root / dataset.nusc.get("sample_data", sample["data"][cam])["filename"] for cam in CAMERAS]


def read_image_file(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise DataError(f"cannot read image file {path}: {e.strerror}") from None


def fill_cache(dataset: NuScenesDetection, encoder: CameraEncoder, cache: FeatureCache,
               progress: bool = False) -> dict:
    """Write the entry of every camera image of ``dataset`` that ``cache`` lacks (or holds
    unreadable), in the dataset's order; the others are kept. Returns the counts ``images``,
    ``computed``, ``kept``. ``encoder`` must be the cache's (checked)."""
    from tqdm import tqdm
    cache.check_encoder(encoder_identity(encoder))
    computed = kept = 0
    for index in tqdm(range(len(dataset)), disable=not progress, unit="sample", dynamic_ncols=True):
        for path in camera_files(dataset, index):
            key = image_key(read_image_file(path))
            if cache.valid(key):
                kept += 1
                continue
            image, img_aug = network_image(path, encoder.image_size)
            cache.write(key, encode_image(encoder, image), img_aug)
            computed += 1
    return {"images": computed + kept, "computed": computed, "kept": kept}


class CachedFeatureDataset(NuScenesDetection):
    """:class:`clfbev.data.NuScenesDetection` whose samples carry each camera's cached FPN
    features (``Sample.image_features``, (N, fpn_ch, h, w) float32) in place of its pixels
    (``images`` (N, 3, 0, 0)): an image file is read and hashed, never decoded. The rest of a
    sample (points, boxes, the cameras' geometry) is the base class's."""

    def __init__(self, dataroot: str | Path, version: str, split: str, cfg: DataConfig, cache: FeatureCache):
        super().__init__(dataroot, version, split, cfg)
        self.cache = cache

    def _camera_input(self, path: Path) -> tuple[np.ndarray, np.ndarray]:
        # The base class stacks what this returns as the sample's images; __getitem__ moves it.
        return self.cache.read(image_key(read_image_file(path)), path)

    def __getitem__(self, index: int) -> Sample:
        sample = super().__getitem__(index)
        features = sample.images                              # (N, fpn_ch, h, w), see _camera_input
        return replace(sample, images=np.zeros((len(features), 3, 0, 0), np.float32), image_features=features)
