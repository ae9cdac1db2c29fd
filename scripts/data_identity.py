"""The identity of a benchmark dataset: a sha1 of its splits and of every annotation's class and pose.

    python scripts/data_identity.py DATAROOT [--version v1.0-sim]

`scripts/benchmark.sh` keeps it with each run's record, and restores a record only onto data of
the same identity. The layout decides it (a change of preset or of simgen's placement moves it);
the sensor-derived fields (num_lidar_pts, visibility) are left out, so that another CPU's ray
caster, which may count a point differently at an edge, cannot void the records. Poses are
rounded to the millimetre (rotations to 1e-4) for the same reason.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path


def data_identity(dataroot: Path, version: str = "v1.0-sim") -> str:
    """sha1 (hex) of splits.json and the sorted (class, translation, size, rotation) rows."""
    tables = Path(dataroot) / version

    def load(name: str):
        return json.loads((tables / f"{name}.json").read_text())

    category = {c["token"]: c["name"] for c in load("category")}
    class_of = {i["token"]: category[i["category_token"]] for i in load("instance")}
    rows = sorted(
        (class_of[a["instance_token"]], *(round(v, 3) for v in a["translation"] + a["size"]),
         *(round(v, 4) for v in a["rotation"]))
        for a in load("sample_annotation")
    )
    return hashlib.sha1(json.dumps([load("splits"), rows]).encode()).hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataroot", type=Path)
    ap.add_argument("--version", default="v1.0-sim")
    args = ap.parse_args()
    print(data_identity(args.dataroot, args.version))


if __name__ == "__main__":
    main()
