"""The nuScenes schema and the one writer: tokens, the tables' rows, a scene's records written
atomically, and the merge of the scenes' parts.

A scene is made in memory as a :class:`SceneRecords`: its rows of the per-scene tables and the
bytes of each of its files. :func:`write_scene` writes the files first, each to a temporary name
and renamed, then the rows as one part file ``<dataroot>/.parts/scene-NNNN.json``. Only when
every part exists are the 13 tables (and ``splits.json``, and nuScenes-lidarseg's
``lidarseg.json``) merged into ``<dataroot>/<version>/``, the same way. So a half-written scene
is never referenced, and a rerun finishes what is missing.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from . import geometry
from . import lidarseg
from .errors import DataError
from .rig import CAMERAS, LIDAR
from .world import CATEGORY

TABLES = ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
          "sample_annotation", "sample_data", "scene", "sensor", "visibility")
PER_SCENE_TABLES = ("calibrated_sensor", "ego_pose", "instance", "log", "map", "sample",
                    "sample_annotation", "sample_data", "scene", "lidarseg")
ATTRIBUTES = ("vehicle.moving", "vehicle.parked", "vehicle.stopped", "cycle.with_rider",
              "cycle.without_rider", "pedestrian.moving", "pedestrian.standing", "pedestrian.sitting_lying_down")
VISIBILITY_LEVELS = {"1": "v0-40", "2": "v40-60", "3": "v60-80", "4": "v80-100"}
PARTS_DIR = ".parts"
DENSE_DIR = "dense"
# A depth image compressed at OpenCV's default level outweighs its JPEG several times; zlib's
# level 3 more than halves it for a few milliseconds per image.
DENSE_PNG_LEVEL = 3


def token(*parts) -> str:
    """A 32-hex-digit token, a pure function of its parts (so of the seed, never of time)."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


@dataclass
class SceneRecords:
    """One scene as it is written: its rows of :data:`PER_SCENE_TABLES` (in that order) and
    ``files``, the bytes of each of its files by path relative to the dataroot."""
    index: int
    tables: dict[str, list[dict]] = field(default_factory=lambda: {name: [] for name in PER_SCENE_TABLES})
    files: dict[str, bytes] = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return len(self.tables["sample"])

    @property
    def nbytes(self) -> int:
        """The bytes the scene writes: its files and its part."""
        return sum(map(len, self.files.values())) + len(dump_json(self.tables))


# ---- files -------------------------------------------------------------------------------------

def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary name and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def dump_json(obj) -> bytes:
    return json.dumps(obj, indent=0, separators=(",", ":")).encode()


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    """(H, W, 3) uint8 RGB -> JPEG bytes."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {rgb.shape} image as JPEG")
    return buf.tobytes()


def encode_png(img: np.ndarray, level: int | None = None) -> bytes:
    """(H, W) uint8 or uint16, or (H, W, 3) uint8 -> PNG bytes; ``level``: zlib's compression
    level 0-9, None for OpenCV's default."""
    params = [] if level is None else [cv2.IMWRITE_PNG_COMPRESSION, level]
    ok, buf = cv2.imencode(".png", img, params)
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {img.shape} image as PNG")
    return buf.tobytes()


def write_png(path: Path, img: np.ndarray) -> None:
    write_atomic(path, encode_png(img))


def dense_label_files(image_file: str) -> tuple[str, str]:
    """The dense labels of the camera image ``samples/CAM_X/NAME.jpg``: ``dense/CAM_X/NAME_depth.png``
    (uint16 z-depth x 256) and ``dense/CAM_X/NAME_seg.png`` (uint8 lidarseg class), relative to
    the dataroot. They lie outside the devkit's tables, beside the images they label."""
    _, channel, name = PurePosixPath(image_file).parts
    stem = name.rsplit(".", 1)[0]
    return f"{DENSE_DIR}/{channel}/{stem}_depth.png", f"{DENSE_DIR}/{channel}/{stem}_seg.png"


def encode_pointcloud(points: np.ndarray) -> bytes:
    """(n, 5) x, y, z, intensity, ring -> the nuScenes .pcd.bin layout (float32, row-major)."""
    return np.ascontiguousarray(points, dtype=np.float32).tobytes()


# ---- rows --------------------------------------------------------------------------------------

def log_row(log_token: str, logfile: str, location: str) -> dict:
    return {"token": log_token, "logfile": logfile, "vehicle": "simgen-ego", "date_captured": "2020-09-13",
            "location": location}


def map_row(map_token: str, log_token: str, filename: str) -> dict:
    return {"token": map_token, "log_tokens": [log_token], "category": "semantic_prior", "filename": filename}


def calibrated_sensor_row(calib_token: str, channel: str, translation, rotation_wxyz, K_cam=None) -> dict:
    """A sensor's extrinsics in the ego frame; ``K_cam`` (3, 3) for a camera, None for the lidar."""
    return {"token": calib_token, "sensor_token": token("sensor", channel), "translation": list(translation),
            "rotation": list(rotation_wxyz), "camera_intrinsic": [] if K_cam is None else K_cam.tolist()}


def sample_rows(sample_tokens: list[str], timestamps_us: list[int], scene_token: str) -> list[dict]:
    """The key frames of a scene, linked in time order."""
    n = len(sample_tokens)
    return [{"token": tok, "timestamp": timestamps_us[k], "scene_token": scene_token,
             "prev": sample_tokens[k - 1] if k else "", "next": sample_tokens[k + 1] if k + 1 < n else ""}
            for k, tok in enumerate(sample_tokens)]


def scene_row(scene_token: str, log_token: str, sample_tokens: list[str], name: str, description: str) -> dict:
    return {"token": scene_token, "log_token": log_token, "nbr_samples": len(sample_tokens),
            "first_sample_token": sample_tokens[0], "last_sample_token": sample_tokens[-1],
            "name": name, "description": description}


def ego_pose_row(pose_token: str, timestamp_us: int, T_global_from_ego: np.ndarray) -> dict:
    """The ego's pose on the ground plane (z = 0 by nuScenes convention)."""
    T = T_global_from_ego
    return {"token": pose_token, "timestamp": timestamp_us, "translation": [float(T[0, 3]), float(T[1, 3]), 0.0],
            "rotation": [float(v) for v in geometry.matrix_to_quat_wxyz(T[:3, :3])]}


def sample_data_row(sd_token: str, sample_token: str, calib_token: str, timestamp_us: int, fileformat: str,
                    is_key_frame: bool, width: int, height: int, filename: str) -> dict:
    """One sensor file; its ego pose shares its token. ``prev`` and ``next`` are set by :func:`link`."""
    return {"token": sd_token, "sample_token": sample_token, "ego_pose_token": sd_token,
            "calibrated_sensor_token": calib_token, "timestamp": timestamp_us, "fileformat": fileformat,
            "is_key_frame": is_key_frame, "height": height, "width": width, "filename": filename,
            "prev": "", "next": ""}


def lidarseg_row(sd_token: str, filename: str) -> dict:
    return {"token": sd_token, "sample_data_token": sd_token, "filename": filename}


def annotation_row(ann_token: str, sample_token: str, instance_token: str, visibility_token: str,
                   attribute: str | None, box) -> dict:
    """A (7,) global box (x, y, z, l, w, h, yaw) as a sample_annotation; ``num_lidar_pts`` is
    counted later, on the written sweep."""
    translation, size, rotation = geometry.box_to_nuscenes(box)
    return {"token": ann_token, "sample_token": sample_token, "instance_token": instance_token,
            "visibility_token": visibility_token,
            "attribute_tokens": [token("attribute", attribute)] if attribute else [],
            "translation": translation, "size": size, "rotation": rotation,
            "prev": "", "next": "", "num_lidar_pts": 0, "num_radar_pts": 0}


def instance_row(annotations: list[dict], category: str) -> dict:
    """The instance of an object's annotations (in time order)."""
    return {"token": annotations[0]["instance_token"], "category_token": token("category", category),
            "nbr_annotations": len(annotations), "first_annotation_token": annotations[0]["token"],
            "last_annotation_token": annotations[-1]["token"]}


def link(rows: list[dict]) -> None:
    """Set ``prev`` and ``next`` of rows in time order."""
    for a, b in zip(rows[:-1], rows[1:]):
        a["next"], b["prev"] = b["token"], a["token"]


def static_tables() -> dict[str, list[dict]]:
    """The tables shared by all scenes: sensors, categories, attributes, visibility levels."""
    sensors = [{"token": token("sensor", ch), "channel": ch, "modality": "camera"} for ch in CAMERAS]
    sensors.append({"token": token("sensor", LIDAR), "channel": LIDAR, "modality": "lidar"})
    describe = {name: f"simgen {cls}" for cls, name in CATEGORY.items()}
    describe.update({lidarseg.NAMES[i]: f"simgen static world: {what}" for i, what in (
        (lidarseg.ROAD, "asphalt, lane markings, crosswalks"), (lidarseg.SIDEWALK, "sidewalks and curbs"),
        (lidarseg.TERRAIN, "lawns"), (lidarseg.PLAZA, "paved lots"), (lidarseg.MANMADE, "buildings, poles, bins"),
        (lidarseg.VEGETATION, "trees, hedges"))})
    describe[lidarseg.NAMES[lidarseg.NOISE]] = "simgen: fog returns"
    return {
        "sensor": sensors,
        # All of nuScenes-lidarseg's classes with their indices (the devkit needs 0..31 without gaps).
        "category": [{"token": token("category", name), "name": name, "index": i,
                      "description": describe.get(name, "not generated")} for i, name in enumerate(lidarseg.NAMES)],
        "attribute": [{"token": token("attribute", name), "name": name, "description": name} for name in ATTRIBUTES],
        "visibility": [{"token": k, "level": v, "description": f"visibility of whole object is {v[1:]} %"}
                       for k, v in VISIBILITY_LEVELS.items()],
    }


# ---- a scene, the parts and the merge ----------------------------------------------------------

def part_path(dataroot: Path, scene_idx: int) -> Path:
    return dataroot / PARTS_DIR / f"scene-{scene_idx:04d}.json"


def write_scene(dataroot: Path, records: SceneRecords) -> None:
    """Write a scene's files into ``dataroot``, each through a temporary name and a rename, its
    table part last: until that exists, a rerun makes the scene again. The paths may come from
    another machine (a Ray worker): one that would leave ``dataroot`` is refused."""
    for rel in records.files:
        p = PurePosixPath(rel)
        if p.is_absolute() or ".." in p.parts or rel.startswith(PARTS_DIR):
            raise DataError(f"scene {records.index}: file {rel!r} is not a path inside the dataroot "
                            f"(made by another simgen version?)")
    for rel, data in records.files.items():
        write_atomic(dataroot / rel, data)
    write_atomic(part_path(dataroot, records.index), dump_json(records.tables))


def split_scenes(names: list[str], val_fraction: float) -> dict[str, list[str]]:
    """The last ceil(val_fraction * n) scenes are ``sim-val``: with a fraction below 1 at least
    one and at most n - 1 when n >= 2 (both splits non-empty); with 1 all of them (a set made for
    evaluation only)."""
    n = len(names)
    if val_fraction >= 1.0:
        return {"sim-train": [], "sim-val": list(names)}
    n_val = int(np.ceil(val_fraction * n)) if n >= 2 else 0
    if n >= 2:
        n_val = min(max(n_val, 1), n - 1)
    return {"sim-train": names[: n - n_val], "sim-val": names[n - n_val:]}


def read_part(dataroot: Path, scene_idx: int) -> dict[str, list[dict]]:
    """A scene's rows as written by :func:`write_scene`. Raises DataError for a damaged part."""
    path = part_path(dataroot, scene_idx)
    try:
        part = json.loads(path.read_text())
        missing = [name for name in PER_SCENE_TABLES if name not in part]
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError):
        part, missing = None, ["any"]
    if missing:
        # Damaged, or written by a simgen that wrote other tables: nothing is merged from it.
        raise DataError(f"{path}: a scene part without {missing[0]} records (damaged, or made by another "
                        f"simgen version); delete it and rerun the same command to make that scene again")
    return part


def merge(dataroot: Path, version: str, n_scenes: int, val_fraction: float) -> dict[str, int]:
    """Merge the scene parts into the 13 tables, splits.json and lidarseg.json (when any key
    frame has points: the devkit then lists ``lidarseg/<version>/``). Returns row counts per table."""
    tables = {name: [] for name in (*TABLES, "lidarseg")}
    tables.update(static_tables())
    for i in range(n_scenes):
        part = read_part(dataroot, i)
        for name in PER_SCENE_TABLES:
            tables[name].extend(part[name])
    out = dataroot / version
    for name in TABLES + (("lidarseg",) if tables["lidarseg"] else ()):
        write_atomic(out / f"{name}.json", dump_json(tables[name]))
    names = [s["name"] for s in tables["scene"]]
    write_atomic(out / "splits.json", dump_json(split_scenes(names, val_fraction)))
    return {name: len(rows) for name, rows in tables.items()}
