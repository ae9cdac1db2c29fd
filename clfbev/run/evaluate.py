"""Predictions -> nuScenes results JSON -> the official nuscenes-devkit ``DetectionEval``.

:func:`evaluate_model` is the one path from a model to its metrics, used by validation during
training, ``clfbev eval``, the robustness suite and the benchmark. The metric itself is never
re-implemented here: this module only converts the detector's lidar-frame boxes to the nuScenes
submission format (through :func:`clfbev.data.box_lidar_to_global`, the one place boxes leave
the lidar frame), restricts the devkit's ``detection_cvpr_2019`` config to the classes the split
has (:func:`detection_config_for`), and runs ``DetectionEval``.

Attributes: the model has no attribute head. ``attribute_name`` is DERIVED from the predicted
speed and class (moving/parked, moving/standing, with/without rider), not learned; the AAE it
gets is therefore a property of the velocity estimate. The speed thresholds are simgen's (0.3
m/s, 0.2 for walkers). Speed alone cannot tell a parked vehicle from one stopped in traffic, nor
a still cycle with its rider from one without: the rule answers the majority of each, which on
the benchmark's set (40 scenes, seed 1) is parked for 87 % of the slow vehicles (11,338 against
1,658 stopped) and without a rider for 94 % of the slow cycles (799 against 52).
"""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import numpy as np
import torch

from clfbev import io
from clfbev.attributes import attribute_for
from clfbev.data import Batch, NuScenesDetection, box_lidar_to_global, collate, split_scene_names
from clfbev.errors import DataError

MAX_PER_SAMPLE = 500          # the devkit's max_boxes_per_sample: it rejects a file with more
DEFAULT_META = {"use_camera": True, "use_lidar": True, "use_radar": False, "use_map": False, "use_external": False}


def detections_to_results(dets, sample_tokens, T_global_from_lidar, class_names) -> dict[str, list[dict]]:
    """Per-sample detections (lidar frame) -> ``{sample_token: [nuScenes result dict, ...]}``.

    dets : sequence of ``Detections`` (or ``(boxes (K, 9), scores (K,), labels (K,)[, still
        (K,) logits or None])``): boxes ``x, y, z, l, w, h, yaw, vx, vy`` in each sample's
        key-frame lidar frame; the attribute from the speed and the still logit where given
        (:func:`clfbev.attributes.attribute_for`).
    sample_tokens : one token per entry of ``dets``.
    T_global_from_lidar : one (4, 4) transform per entry (tensor or array, float64 preferred).
    class_names : label -> detection name.
    At most :data:`MAX_PER_SAMPLE` boxes per sample, highest scores first.
    """
    if not (len(dets) == len(sample_tokens) == len(T_global_from_lidar)):
        raise ValueError(f"got {len(dets)} detections, {len(sample_tokens)} tokens, {len(T_global_from_lidar)} transforms")
    results: dict[str, list[dict]] = {}
    for det, token, T in zip(dets, sample_tokens, T_global_from_lidar):
        boxes, scores, labels = det[:3]
        still = det[3] if len(det) > 3 and det[3] is not None else None
        still = None if still is None else np.asarray(torch.as_tensor(still).detach().cpu(), dtype=np.float64)
        T = np.asarray(torch.as_tensor(T, dtype=torch.float64).cpu())
        boxes = np.asarray(torch.as_tensor(boxes).detach().cpu(), dtype=np.float64)
        scores = np.asarray(torch.as_tensor(scores).detach().cpu(), dtype=np.float64)
        labels = np.asarray(torch.as_tensor(labels).detach().cpu(), dtype=np.int64)
        order = np.argsort(-scores, kind="stable")[:MAX_PER_SAMPLE]
        out = []
        for i in order:
            translation, size, rotation = box_lidar_to_global(boxes[i, :7], T)
            # A velocity is a direction: rotate only, no translation.
            v_lidar = np.array([boxes[i, 7], boxes[i, 8], 0.0]) if boxes.shape[1] >= 9 else np.zeros(3)
            v_global = T[:3, :3] @ v_lidar
            name = class_names[int(labels[i])]
            out.append({
                "sample_token": token,
                "translation": [float(v) for v in translation],
                "size": [float(v) for v in size],
                "rotation": [float(v) for v in rotation],
                "velocity": [float(v_global[0]), float(v_global[1])],
                "detection_name": name,
                "detection_score": float(scores[i]),
                "attribute_name": attribute_for(name, float(np.hypot(v_global[0], v_global[1])),
                                                None if still is None else float(still[i])),
            })
        results[token] = out
    return results


def write_results(path, results: dict, meta: dict | None = None) -> Path:
    """Write the nuScenes submission ``{"meta": ..., "results": ...}`` atomically, so a crash
    never leaves a half-written file that a later evaluation would read."""
    return io.write_json(path, {"meta": {**DEFAULT_META, **(meta or {})}, "results": results})


def split_sample_tokens(nusc, split: str) -> list[str]:
    """Sample tokens of the scenes of ``split`` (official or from splits.json)."""
    names = set(split_scene_names(Path(nusc.dataroot), nusc.version, split))
    return [s["token"] for s in nusc.sample if nusc.get("scene", s["scene_token"])["name"] in names]


def ego_distance(nusc, ann: dict) -> float:
    """xy distance (m) from the ego pose of the annotation's lidar key frame to its centre: the
    devkit's ``add_center_dist``, which its range filter compares with ``class_range``."""
    sample = nusc.get("sample", ann["sample_token"])
    pose = nusc.get("ego_pose", nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["ego_pose_token"])
    return float(np.hypot(ann["translation"][0] - pose["translation"][0],
                          ann["translation"][1] - pose["translation"][1]))


def detection_config_for(nusc, split: str, class_names):
    """``detection_cvpr_2019`` restricted to what ``split`` has, as the devkit needs it.

    class_range : every class with any GT box in the split (the devkit's filter indexes it for
        each GT box, lidar points or not).
    class_names : classes with at least one GT box the devkit keeps (``filter_eval_boxes``: lidar
        points, and closer to the ego than the class range), intersected with the model's
        ``class_names``. A class without evaluable GT would count as AP 0.
    """
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.detection.utils import category_to_detection_name

    cfg = config_factory("detection_cvpr_2019")
    with_gt, evaluable = set(), set()
    for token in split_sample_tokens(nusc, split):
        for ann_token in nusc.get("sample", token)["anns"]:
            ann = nusc.get("sample_annotation", ann_token)
            name = category_to_detection_name(ann["category_name"])
            if name is None:
                continue
            with_gt.add(name)
            if ann["num_lidar_pts"] > 0 and ego_distance(nusc, ann) < cfg.class_range[name]:
                evaluable.add(name)
    cfg.class_range = {k: v for k, v in cfg.class_range.items() if k in with_gt}
    cfg.class_names = [k for k in cfg.class_range if k in evaluable and k in set(class_names)]
    if not cfg.class_names:
        raise DataError(f"split '{split}' of {nusc.dataroot} has no GT with lidar points within the class range "
                        f"of the classes {list(class_names)}")
    return cfg


def evaluate(nusc, results_path, split: str, out_dir, class_names, plots: bool = False) -> dict:
    """Run the devkit's ``DetectionEval`` on ``results_path`` over ``split``; returns the devkit's
    ``metrics_summary`` dict (``mean_ap``, ``nd_score``, ``mean_dist_aps``, ...), also written with
    ``metrics_details.json`` to ``out_dir`` (and, with ``plots``, the devkit's PR and TP curves
    to ``out_dir/plots``).

    The results must cover exactly the split's sample tokens. Predictions of classes without GT
    in the split are dropped first (the devkit's range filter would fail on them); they cannot
    change the AP of the evaluated classes anyway. The filtered file is what is evaluated.
    """
    from nuscenes.eval.detection.evaluate import DetectionEval

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = detection_config_for(nusc, split, class_names)
    sub = json.loads(Path(results_path).read_text())
    expected = set(split_sample_tokens(nusc, split))
    got = set(sub["results"])
    if got != expected:
        raise DataError(f"{results_path}: results cover {len(got)} samples, split '{split}' has {len(expected)} "
                         f"({len(expected - got)} missing, {len(got - expected)} extra)")
    sub["results"] = {tok: [b for b in boxes if b["detection_name"] in cfg.class_range]
                      for tok, boxes in sub["results"].items()}
    if not any(sub["results"].values()):
        # No box at all (e.g. a model early in training): the metrics are defined (AP 0, TP
        # errors 1), but DetectionEval cannot start, as it reads the box type off the first box.
        # One score-0 box 10 km away is added; the devkit's range filter removes it before any
        # matching, so it cannot change a metric.
        token = sorted(expected)[0]
        sub["results"][token] = [{
            "sample_token": token, "translation": [1e4, 1e4, 0.0], "size": [1.0, 1.0, 1.0],
            "rotation": [1.0, 0.0, 0.0, 0.0], "velocity": [0.0, 0.0], "detection_name": cfg.class_names[0],
            "detection_score": 0.0, "attribute_name": attribute_for(cfg.class_names[0], 0.0)}]
    filtered = out_dir / "results_eval.json"
    io.write_json(filtered, sub)

    ev = DetectionEval(nusc, cfg, str(filtered), eval_set=split, output_dir=str(out_dir), verbose=False)
    metrics, details = ev.evaluate()
    if plots:
        _render_curves(ev, metrics, details)
    # What DetectionEval.main writes, without its prints and plots.
    summary = metrics.serialize()
    summary["meta"] = ev.meta.copy()
    io.write_json(out_dir / "metrics_summary.json", summary)
    io.write_json(out_dir / "metrics_details.json", details.serialize())
    return summary


def _render_curves(ev, metrics, details) -> None:
    """The devkit's PR and TP curves (``DetectionEval.render``) as PNGs in ``ev.plot_dir``,
    without its summary plot, which assumes all ten classes are evaluated. Each curve is drawn
    by the devkit on a figure of its own and written atomically."""
    from nuscenes.eval.detection.render import class_pr_curve, class_tp_curve, dist_pr_curve
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def save(name: str) -> None:
        io.save_figure(Path(ev.plot_dir) / name, plt.gcf())
        plt.close("all")

    cfg = ev.cfg
    for name in cfg.class_names:
        class_pr_curve(details, metrics, name, cfg.min_precision, cfg.min_recall)
        save(f"{name}_pr.png")
        class_tp_curve(details, metrics, name, cfg.min_recall, cfg.dist_th_tp)
        save(f"{name}_tp.png")
    for dist_th in cfg.dist_ths:
        dist_pr_curve(details, metrics, dist_th, cfg.min_precision, cfg.min_recall)
        save(f"dist_pr_{dist_th}.png")


# Evaluation keeps low-confidence boxes (up to MAX_PER_SAMPLE): average precision integrates over
# the whole score range, and a cut at the config's display threshold would only lose recall.
EVAL_SCORE_THR = 0.01


@torch.no_grad()
def predict_split(model, dataset: NuScenesDetection, batch_size: int = 1,
                  score_thr: float | None = EVAL_SCORE_THR) -> dict[str, list[dict]]:
    """Run ``model`` (in eval mode) over every sample of ``dataset``; nuScenes results dict with
    one (possibly empty) entry per sample token. ``score_thr`` None: the config's threshold."""
    model.eval()
    device = next(model.parameters()).device
    class_names = model.cfg.class_names
    # Collated for the model's config: the oracle lift's depth bins, where it has one, are projected here.
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False,
                                         collate_fn=partial(collate, model_cfg=model.cfg))
    results: dict[str, list[dict]] = {}
    for batch in loader:
        batch: Batch = batch.to(device)
        dets = model.predict(batch, score_thr=score_thr)
        results.update(detections_to_results(dets, batch.sample_tokens, batch.T_global_from_lidar.cpu(), class_names))
    return results


def evaluate_model(model, dataset: NuScenesDetection, out_dir: str | Path, *, batch_size: int = 1,
                   score_thr: float | None = None, plots: bool = False) -> dict:
    """Predict every sample of ``dataset``'s split, write ``out_dir/results.json``, and score it
    with the devkit's ``DetectionEval``; returns the devkit's summary dict (``mean_ap``,
    ``nd_score``, ...), also written to ``out_dir`` (:func:`evaluate`).

    score_thr : keep boxes scoring at least this (None: :data:`EVAL_SCORE_THR`).
    The model is left in the mode (train or eval) it came in.
    """
    was_training = model.training
    results = predict_split(model, dataset, batch_size=batch_size,
                            score_thr=EVAL_SCORE_THR if score_thr is None else score_thr)
    path = write_results(Path(out_dir) / "results.json", results)
    summary = evaluate(dataset.nusc, path, dataset.split, out_dir, model.cfg.class_names, plots=plots)
    model.train(was_training)
    return summary
