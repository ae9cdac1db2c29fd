"""Where a model finds the objects of one class: per range band from the ego, the GT boxes (with
lidar points) and the share of them with a predicted box of that class within 2 m scored above
a threshold, and the median of the best such score.

    python scripts/recall_by_range.py DATAROOT RESULTS.json [--split sim-val] [--cls car] [--thr 0.3]

RESULTS is a results file of `clfbev eval` or `clfbev predict` (nuScenes submission format).
Prints a markdown table. A missing or junk file is one line naming it, exit 2.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from clfbev.errors import DataError, run_guarded
from clfbev.run.evaluate import ego_distance, split_sample_tokens

BANDS = ((0, 10), (10, 20), (20, 35), (35, 50))
MATCH_M = 2.0


def best_scores(nusc, results: dict, split: str, cls: str) -> tuple[np.ndarray, np.ndarray]:
    """(G,) ego distance of each GT box of ``cls`` with lidar points in ``split``, and (G,) the
    best score of a predicted ``cls`` box within MATCH_M of its centre (0 where none)."""
    from nuscenes.eval.detection.utils import category_to_detection_name
    dist, best = [], []
    for token in split_sample_tokens(nusc, split):
        preds = [b for b in results.get(token, []) if b["detection_name"] == cls]
        centres = np.array([b["translation"][:2] for b in preds]).reshape(-1, 2)
        scores = np.array([b["detection_score"] for b in preds])
        for ann_token in nusc.get("sample", token)["anns"]:
            ann = nusc.get("sample_annotation", ann_token)
            if category_to_detection_name(ann["category_name"]) != cls or ann["num_lidar_pts"] == 0:
                continue
            near = np.hypot(*(centres - np.array(ann["translation"][:2])).T) <= MATCH_M
            dist.append(ego_distance(nusc, ann))
            best.append(float(scores[near].max()) if near.any() else 0.0)
    return np.array(dist), np.array(best)


def table(dist: np.ndarray, best: np.ndarray, thr: float) -> str:
    rows = ["| range | GT | best score, median | share with a box > %.1f within 2 m |" % thr, "|---|---:|---:|---:|"]
    for lo, hi in BANDS:
        sel = (dist >= lo) & (dist < hi)
        if sel.any():
            rows.append(f"| {lo}-{hi} m | {sel.sum()} | {np.median(best[sel]):.2f} | {(best[sel] > thr).mean():.2f} |")
        else:
            rows.append(f"| {lo}-{hi} m | 0 | - | - |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataroot", type=Path)
    p.add_argument("results", type=Path)
    p.add_argument("--split", default="sim-val")
    p.add_argument("--version", default="v1.0-sim")
    p.add_argument("--cls", default="car")
    p.add_argument("--thr", type=float, default=0.3)
    a = p.parse_args(argv)
    try:
        results = json.loads(a.results.read_text())["results"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DataError(f"{a.results}: not a results file ({type(e).__name__}: {e})") from None
    from clfbev.data import load_nuscenes
    nusc = load_nuscenes(a.dataroot, a.version)
    dist, best = best_scores(nusc, results, a.split, a.cls)
    print(table(dist, best, a.thr))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_guarded(main, prog="recall_by_range"))
