"""The sensor-visibility oracle scored: the ground truth each condition's sensors still see
(:mod:`clfbev.oracle`), sent as predictions of score 1 to the devkit's ``DetectionEval`` against
the condition's full ground truth. Its NDS is the most any detector reaches under the
condition; a model's NDS as a share of it tells "the weather hid it" from "the model missed it".
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from clfbev.oracle import Oracle, Sight
from clfbev.run.evaluate import evaluate, write_results


def sights(oracle: Oracle, progress: bool = False) -> list[Sight]:
    """Every sample's :class:`Sight`, in the split's order."""
    return [oracle.sight(i) for i in tqdm(range(len(oracle)), desc="oracle", disable=not progress, leave=False)]


def oracle_results(nusc, tokens: list[str], seen: list[Sight]) -> dict[str, list[dict]]:
    """The seen annotations of the samples ``tokens`` that the devkit evaluates, as nuScenes
    detection results: the annotation's own box, velocity (0 where the devkit knows none), attribute, score 1."""
    from nuscenes.eval.detection.utils import category_to_detection_name

    results = {}
    for token, sight in zip(tokens, seen):
        boxes = []
        for ann_token in np.asarray(sight.tokens, object)[sight.seen]:
            ann = nusc.get("sample_annotation", ann_token)
            name = category_to_detection_name(ann["category_name"])
            # The devkit evaluates only annotations its table gives a point; any other box,
            # seen or not, would be a false positive.
            if name is None or ann["num_lidar_pts"] + ann["num_radar_pts"] == 0:
                continue
            velocity = np.nan_to_num(nusc.box_velocity(ann_token)[:2])
            attributes = [nusc.get("attribute", t)["name"] for t in ann["attribute_tokens"]]
            boxes.append({"sample_token": token, "translation": list(ann["translation"]), "size": list(ann["size"]),
                          "rotation": list(ann["rotation"]), "velocity": [float(v) for v in velocity],
                          "detection_name": name, "detection_score": 1.0,
                          "attribute_name": attributes[0] if attributes else ""})
        results[token] = boxes
    return results


def evaluate_oracle(dataroot: str | Path, version: str, split: str, corruptions, out_dir: str | Path,
                    class_names, progress: bool = False) -> dict:
    """Score one condition's oracle (``out_dir``: results.json and the devkit's summary).
    Returns the devkit's summary with ``oracle_counts``: the annotations seen by the lidar, by a
    camera, by either, and in all."""
    oracle = Oracle(dataroot, version, split, corruptions)
    seen = sights(oracle, progress)
    tokens = oracle.ds.sample_tokens
    path = write_results(Path(out_dir) / "results.json", oracle_results(oracle.ds.nusc, tokens, seen))
    summary = evaluate(oracle.ds.nusc, path, split, out_dir, class_names)
    summary["oracle_counts"] = {
        "lidar": int(sum((s.lidar_points > 0).sum() for s in seen)),
        "camera": int(sum(s.camera.sum() for s in seen)),
        "seen": int(sum(s.seen.sum() for s in seen)),
        "annotations": int(sum(len(s.tokens) for s in seen)),
    }
    return summary
