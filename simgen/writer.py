"""nuScenes tables and files: deterministic tokens, atomic writes, per-scene parts and the merge.

Each scene is written on its own: sensor files first, then its table records as one part file
``<dataroot>/.parts/scene-NNNN.json``. Only when every part exists are the 13 tables (and
``splits.json``, and nuScenes-lidarseg's ``lidarseg.json``) merged into ``<dataroot>/<version>/``,
each written to a temporary name and renamed. So a half-written scene is never referenced, and a
rerun finishes what is missing.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import cv2
import numpy as np

from . import lidarseg as LS
from .config import ConfigError
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


def token(*parts) -> str:
    """A 32-hex-digit token, a pure function of its parts (so of the seed, never of time)."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary name and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def dump_json(obj) -> bytes:
    return json.dumps(obj, indent=0, separators=(",", ":")).encode()


def write_jpeg(path: Path, rgb: np.ndarray, quality: int) -> None:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    write_atomic(path, buf.tobytes())


def write_png(path: Path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    write_atomic(path, buf.tobytes())


def write_pointcloud(path: Path, points: np.ndarray) -> None:
    """(n, 5) x, y, z, intensity, ring -> the nuScenes .pcd.bin layout (float32, row-major)."""
    write_atomic(path, np.ascontiguousarray(points, dtype=np.float32).tobytes())


def static_tables() -> dict[str, list[dict]]:
    """The tables shared by all scenes: sensors, categories, attributes, visibility levels."""
    sensors = [{"token": token("sensor", ch), "channel": ch, "modality": "camera"} for ch in CAMERAS]
    sensors.append({"token": token("sensor", LIDAR), "channel": LIDAR, "modality": "lidar"})
    describe = {name: f"simgen {cls}" for cls, name in CATEGORY.items()}
    describe.update({LS.NAMES[i]: f"simgen static world: {what}" for i, what in (
        (LS.ROAD, "asphalt, lane markings, crosswalks"), (LS.SIDEWALK, "sidewalks and curbs"), (LS.TERRAIN, "lawns"),
        (LS.PLAZA, "paved lots"), (LS.MANMADE, "buildings, poles, bins"), (LS.VEGETATION, "trees, hedges"))})
    describe[LS.NAMES[LS.NOISE]] = "simgen: fog returns"
    return {
        "sensor": sensors,
        # All of nuScenes-lidarseg's classes with their indices (the devkit needs 0..31 without gaps).
        "category": [{"token": token("category", name), "name": name, "index": i,
                      "description": describe.get(name, "not generated")} for i, name in enumerate(LS.NAMES)],
        "attribute": [{"token": token("attribute", name), "name": name, "description": name} for name in ATTRIBUTES],
        "visibility": [{"token": k, "level": v, "description": f"visibility of whole object is {v[1:]} %"}
                       for k, v in VISIBILITY_LEVELS.items()],
    }


def part_path(dataroot: Path, scene_idx: int) -> Path:
    return dataroot / PARTS_DIR / f"scene-{scene_idx:04d}.json"


def write_part(dataroot: Path, scene_idx: int, records: dict[str, list[dict]]) -> None:
    missing = set(PER_SCENE_TABLES) - set(records)
    assert not missing, missing
    write_atomic(part_path(dataroot, scene_idx), dump_json(records))


def split_scenes(names: list[str], val_fraction: float) -> dict[str, list[str]]:
    """The last ceil(val_fraction * n) scenes are ``sim-val`` (at least one when n >= 2)."""
    n = len(names)
    n_val = int(np.ceil(val_fraction * n)) if n >= 2 else 0
    if n >= 2:
        n_val = min(max(n_val, 1), n - 1)
    return {"sim-train": names[: n - n_val], "sim-val": names[n - n_val:]}


def merge(dataroot: Path, version: str, n_scenes: int, val_fraction: float) -> dict[str, int]:
    """Merge the scene parts into the 13 tables, splits.json and lidarseg.json (when any key
    frame has points: the devkit then lists ``lidarseg/<version>/``). Returns row counts per table."""
    tables = {name: [] for name in (*TABLES, "lidarseg")}
    tables.update(static_tables())
    for i in range(n_scenes):
        path = part_path(dataroot, i)
        try:
            part = json.loads(path.read_text())
            missing = [name for name in PER_SCENE_TABLES if name not in part]
        except (json.JSONDecodeError, UnicodeDecodeError, TypeError):
            part, missing = None, ["any"]
        if missing:
            # Damaged, or written by a simgen that wrote other tables: nothing is merged from it.
            raise ConfigError(f"{path}: a scene part without {missing[0]} records (damaged, or made by another "
                              f"simgen version); delete it and rerun the same command to make that scene again")
        for name in PER_SCENE_TABLES:
            tables[name].extend(part[name])
    out = dataroot / version
    for name in TABLES + (("lidarseg",) if tables["lidarseg"] else ()):
        write_atomic(out / f"{name}.json", dump_json(tables[name]))
    names = [s["name"] for s in tables["scene"]]
    write_atomic(out / "splits.json", dump_json(split_scenes(names, val_fraction)))
    return {name: len(rows) for name, rows in tables.items()}
