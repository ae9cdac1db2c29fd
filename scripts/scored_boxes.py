#!/usr/bin/env python
"""The boxes the devkit scores, per class and split of a dataroot, as JSON.

    python scripts/scored_boxes.py DATAROOT [--version v1.0-sim] [--out FILE]

A box is scored as `DetectionEval` scores it: it has a lidar or radar point and lies within its
class's `detection_cvpr_2019` range of the sample's LIDAR_TOP ego pose. `scripts/benchmark.sh`
writes OUT/scored.json with it, and the results table says how many boxes each AP rests on.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from clfbev import io
from clfbev.data import load_nuscenes
from clfbev.errors import run_guarded
from clfbev.run.evaluate import ego_distance, split_sample_tokens


def scored_boxes(dataroot: Path, version: str = "v1.0-sim") -> dict[str, dict[str, int]]:
    """{split: {class: scored boxes}} for every split of ``dataroot``'s splits.json, classes in the
    devkit's order (those with none left out)."""
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.detection.utils import category_to_detection_name

    nusc = load_nuscenes(dataroot, version)
    class_range = config_factory("detection_cvpr_2019").class_range
    splits = json.loads((Path(dataroot) / version / "splits.json").read_text())
    out = {}
    for split in splits:
        counts = dict.fromkeys(class_range, 0)
        for token in split_sample_tokens(nusc, split):
            for ann_token in nusc.get("sample", token)["anns"]:
                ann = nusc.get("sample_annotation", ann_token)
                name = category_to_detection_name(ann["category_name"])
                if (name in class_range and ann["num_lidar_pts"] + ann["num_radar_pts"] > 0
                        and ego_distance(nusc, ann) < class_range[name]):
                    counts[name] += 1
        out[split] = {k: v for k, v in counts.items() if v}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataroot", type=Path)
    ap.add_argument("--version", default="v1.0-sim")
    ap.add_argument("--out", type=Path, default=None, help="JSON file to write (default: stdout)")
    args = ap.parse_args(argv)

    def run() -> None:
        counts = scored_boxes(args.dataroot, args.version)
        if args.out is None:
            print(json.dumps(counts, indent=1))
        else:
            io.write_json(args.out, counts, indent=1)
    return run_guarded(run, prog="scored_boxes")


if __name__ == "__main__":
    sys.exit(main())
