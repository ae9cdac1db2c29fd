"""`simgen check DIR`: validate a dataroot's tables, files and token integrity, and summarise it."""
from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from .errors import DataError
from .writer import DENSE_DIR, TABLES, dense_label_files

# table -> [(field, table it must reference)]; "" is allowed where a chain ends.
REFERENCES = {
    "sample": [("scene_token", "scene"), ("prev", "sample"), ("next", "sample")],
    "sample_data": [("sample_token", "sample"), ("ego_pose_token", "ego_pose"),
                    ("calibrated_sensor_token", "calibrated_sensor"), ("prev", "sample_data"), ("next", "sample_data")],
    "sample_annotation": [("sample_token", "sample"), ("instance_token", "instance"),
                          ("visibility_token", "visibility"), ("prev", "sample_annotation"), ("next", "sample_annotation")],
    "instance": [("category_token", "category"), ("first_annotation_token", "sample_annotation"),
                 ("last_annotation_token", "sample_annotation")],
    "scene": [("log_token", "log"), ("first_sample_token", "sample"), ("last_sample_token", "sample")],
    "calibrated_sensor": [("sensor_token", "sensor")],
    "lidarseg": [("sample_data_token", "sample_data")],
}


def load_tables(dataroot: Path, version: str) -> dict[str, list[dict]]:
    folder = Path(dataroot) / version
    if not folder.is_dir():
        raise DataError(f"{dataroot}: no {version}/ folder with nuScenes tables")
    tables = {}
    optional = ("lidarseg",)          # nuScenes-lidarseg: absent when no key frame has points
    for name in TABLES + optional:
        path = folder / f"{name}.json"
        if name in optional and not path.is_file():
            continue
        if not path.is_file():
            raise DataError(f"{path}: missing table")
        try:
            tables[name] = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise DataError(f"{path}: corrupt JSON ({e})") from None
        if not isinstance(tables[name], list):
            raise DataError(f"{path}: expected a list of records")
    return tables


def find_problems(dataroot: Path, tables: dict[str, list[dict]]) -> list[str]:
    """Every broken reference, duplicate token and missing or unreadable file."""
    problems = []
    tokens = {}
    for name, rows in tables.items():
        toks = [r.get("token") for r in rows]
        if None in toks:
            problems.append(f"{name}: a record has no token")
        dup = [t for t, c in Counter(toks).items() if c > 1]
        if dup:
            problems.append(f"{name}: duplicate token {dup[0]}")
        tokens[name] = set(toks)
    for name, refs in REFERENCES.items():
        for row in tables.get(name, []):
            for field, target in refs:
                value = row.get(field)
                if value != "" and value not in tokens[target]:
                    problems.append(f"{name} {row.get('token')}: {field} {value!r} is not a {target} token")
    for ann in tables["sample_annotation"]:
        for a in ann.get("attribute_tokens", []):
            if a not in tokens["attribute"]:
                problems.append(f"sample_annotation {ann['token']}: unknown attribute {a}")
    logs_in_maps = {t for m in tables["map"] for t in m.get("log_tokens", [])}
    if not tables["map"]:
        problems.append("map: the table is empty (nuscenes-devkit needs one)")
    for log in tables["log"]:
        if log["token"] not in logs_in_maps:
            problems.append(f"log {log['token']}: not in any map's log_tokens")
    files = [(r["filename"], r.get("fileformat")) for r in tables["sample_data"]] + \
            [(m["filename"], "png") for m in tables["map"]]
    for fname, fmt in files:
        path = Path(dataroot) / fname
        if not path.is_file():
            problems.append(f"{fname}: missing file")
            continue
        size = path.stat().st_size
        if fmt == "pcd" and size % 20:
            problems.append(f"{fname}: size {size} is not a multiple of 5 float32 values (truncated?)")
        elif fmt in ("jpg", "png"):
            with open(path, "rb") as f:
                head = f.read(4)
            magic = b"\xff\xd8\xff" if fmt == "jpg" else b"\x89PNG"
            if not head.startswith(magic):
                problems.append(f"{fname}: not a {fmt} file")
    return problems + _lidarseg_problems(dataroot, tables) + _dense_label_problems(dataroot, tables)


def _lidarseg_problems(dataroot: Path, tables: dict[str, list[dict]]) -> list[str]:
    """Each lidarseg label file: present, and one uint8 label per point of its sweep."""
    problems = []
    sweep_file = {r["token"]: r["filename"] for r in tables["sample_data"]}
    for rec in tables.get("lidarseg", []):
        path, pcd = Path(dataroot) / rec["filename"], sweep_file.get(rec["sample_data_token"])
        if not path.is_file():
            problems.append(f"{rec['filename']}: missing file")
        elif pcd is not None and (Path(dataroot) / pcd).is_file():
            n_points = (Path(dataroot) / pcd).stat().st_size // 20
            if path.stat().st_size != n_points:
                problems.append(f"{rec['filename']}: {path.stat().st_size} labels for the {n_points} points of {pcd}")
    return problems


def _dense_label_problems(dataroot: Path, tables: dict[str, list[dict]]) -> list[str]:
    """When the set has dense labels (a ``dense/`` folder): each camera image's depth and class
    images are present and decode as uint16 and uint8 images of the camera image's size."""
    if not (Path(dataroot) / DENSE_DIR).is_dir():
        return []
    problems = []
    cameras = [r for r in tables["sample_data"] if r.get("fileformat") == "jpg"]
    for rec in cameras:
        for rel, dtype in zip(dense_label_files(rec["filename"]), (np.uint16, np.uint8)):
            path = Path(dataroot) / rel
            if not path.is_file():
                problems.append(f"{rel}: missing file")
                continue
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None or img.dtype != dtype or img.shape != (rec["height"], rec["width"]):
                found = "not an image" if img is None else f"{img.dtype} {img.shape}"
                problems.append(f"{rel}: expected a {np.dtype(dtype).name} image of {rec['height']}x{rec['width']} "
                                f"(rows x columns), found {found}")
    return problems


def check_dataroot(dataroot: Path, version: str) -> int:
    """Print a summary and the problems; return 0 when the dataroot is valid, else 1."""
    tables = load_tables(dataroot, version)
    problems = find_problems(dataroot, tables)
    cat = {c["token"]: c["name"] for c in tables["category"]}
    inst_cat = {i["token"]: cat.get(i["category_token"], "?") for i in tables["instance"]}
    per_class = Counter(inst_cat.get(a["instance_token"], "?") for a in tables["sample_annotation"])
    splits_path = Path(dataroot) / version / "splits.json"
    splits = json.loads(splits_path.read_text()) if splits_path.is_file() else {}
    print(f"{dataroot}/{version}: {len(tables['scene'])} scenes, {len(tables['sample'])} samples, "
          f"{len(tables['sample_data'])} sample_data, {len(tables['sample_annotation'])} annotations")
    print("splits: " + ", ".join(f"{k} {len(v)}" for k, v in splits.items()))
    for name, n in sorted(per_class.items(), key=lambda kv: -kv[1]):
        print(f"  {name:30s} {n}")
    for p in problems[:50]:
        print(f"problem: {p}")
    if len(problems) > 50:
        print(f"... and {len(problems) - 50} more problems")
    print("OK" if not problems else f"{len(problems)} problems")
    return 0 if not problems else 1
