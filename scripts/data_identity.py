"""The identity of a benchmark dataset: a sha1 of its splits and of every annotation's class and pose.

    python scripts/data_identity.py DATAROOT [--version v1.0-sim]

`scripts/benchmark.sh` keeps it with each run's record, and restores a record only onto data of
the same identity. The layout decides it (a change of preset or of simgen's placement moves it);
the sensor-derived fields (num_lidar_pts, visibility) are left out, so that another CPU's ray
caster, which may count a point differently at an edge, cannot void the records. Poses are
rounded to the millimetre (rotations to 1e-4) for the same reason. A table that is missing,
junk or lacks a field is one line naming it, exit 2.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

from clfbev.errors import DataError, run_guarded


def data_identity(dataroot: Path, version: str = "v1.0-sim") -> str:
    """sha1 (hex) of splits.json and the sorted (class, translation, size, rotation) rows.

    Raises DataError naming the table when one is missing, not JSON or lacks a field."""
    tables = Path(dataroot) / version
    category = {c["token"]: c["name"] for c in _records(tables, "category", ("token", "name"))}
    class_of = {i["token"]: category.get(i["category_token"])
                for i in _records(tables, "instance", ("token", "category_token"))}
    annotations = _records(tables, "sample_annotation", ("instance_token", "translation", "size", "rotation"))
    rows = [(class_of.get(a["instance_token"]), *(round(v, 3) for v in a["translation"] + a["size"]),
             *(round(v, 4) for v in a["rotation"])) for a in annotations]
    if any(row[0] is None for row in rows):
        raise DataError(f"{tables}: an annotation's instance or category is not in instance.json / category.json")
    rows.sort()
    return hashlib.sha1(json.dumps([_load(tables, "splits"), rows]).encode()).hexdigest()


def _load(tables: Path, name: str):
    path = tables / f"{name}.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path} is missing") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: not valid JSON ({e})") from None


def _records(tables: Path, name: str, fields: tuple[str, ...]) -> list[dict]:
    """The records of table ``name``, each checked to have ``fields``."""
    records = _load(tables, name)
    if not isinstance(records, list):
        raise DataError(f"{tables / name}.json: expected a list of records")
    for i, r in enumerate(records):
        missing = [f for f in fields if not isinstance(r, dict) or f not in r]
        if missing:
            raise DataError(f"{tables / name}.json: record {i} lacks the field {missing[0]!r}")
    return records


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataroot", type=Path)
    ap.add_argument("--version", default="v1.0-sim")
    args = ap.parse_args(argv)
    return run_guarded(lambda: print(data_identity(args.dataroot, args.version)), prog="data_identity")


if __name__ == "__main__":
    sys.exit(main())
