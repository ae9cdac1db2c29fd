"""The robustness suite: every checkpoint on every condition through the official DetectionEval,
with the robustness benchmarks' summary metrics and a report.

Conditions are (1) the first ``--set``, the clean reference; (2) every further ``--set``, a paired
degraded dataroot (same annotation tables, only the sensor data differ: simgen's fog, lens dirt,
...; with occluders in the world, also what the sensors see of each object, see
:func:`check_paired`); (3) every ``--corrupt`` load-time corruption applied to the clean set
(:mod:`clfbev.corruptions`). Every cell is one :func:`clfbev.run.evaluate.evaluate_model`.

Metrics per checkpoint m and condition c:

- ``RR = NDS_c / NDS_clean`` (resilience rate), ``mRR`` its mean over the degraded conditions;
- ``CE = (1 - NDS_c(m)) / (1 - NDS_c(baseline))`` (corruption error relative to the ``concat``
  checkpoint, as mCE is relative to a reference model), ``mCE`` its mean.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clfbev import io
from clfbev.corruptions import Corruption
from clfbev.data import NuScenesDetection
from clfbev.errors import ConfigError, DataError
from clfbev.run.evaluate import evaluate_model
from clfbev.run.experts_file import load_predictor

PAIRED_TABLES = ("sample_annotation", "instance", "sample", "ego_pose")
# What occluders placed in the world may change in a paired set's labels (simgen --occlusion):
# how much of each object the sensors see, never the object itself.
SEEN_FIELDS = ("visibility_token", "num_lidar_pts", "num_radar_pts")
BASELINE_VARIANT = "concat"


@dataclass(frozen=True)
class Condition:
    name: str
    dataroot: Path
    corruptions: tuple[Corruption, ...] = ()
    fog_severity: int | None = None     # from the set's degradation.json (0 for a clean set)


def check_paired(clean: Path, other: Path, version: str, name: str) -> None:
    """Refuse a set whose annotation tables differ from the clean set's: it is not paired.

    The tables must be byte-identical, except that ``sample_annotation`` records may differ in
    ``SEEN_FIELDS`` (a set with occluders in the world). Such a set is evaluated on its own labels:
    the devkit then leaves out, as it always does, the objects that no lidar point reaches.
    """
    for table in PAIRED_TABLES:
        a, b = clean / version / f"{table}.json", other / version / f"{table}.json"
        for p in (a, b):
            if not p.is_file():
                raise DataError(f"set {name}: {p} does not exist")
        if a.read_bytes() == b.read_bytes():
            continue
        why = f"{table}.json differs"
        if table == "sample_annotation":
            diff = _differing_field(a, b)
            if diff is None:
                continue
            why = f"{table}.json differs ({diff})"
        raise DataError(f"set {name} ({other}) is not paired with the clean set ({clean}): {why}; "
                        "make both with the same simgen preset world, --seed and --scenes")


def _differing_field(a: Path, b: Path) -> str | None:
    """The first difference between two sample_annotation tables outside ``SEEN_FIELDS``, or None."""
    try:
        ra, rb = json.loads(a.read_text()), json.loads(b.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{b}: not valid JSON ({e})") from None
    if len(ra) != len(rb):
        return f"{len(ra)} against {len(rb)} records"
    for x, y in zip(ra, rb):
        for key in sorted(x.keys() | y.keys()):
            if key not in SEEN_FIELDS and x.get(key) != y.get(key):
                return f"record {x.get('token')}: {key}"
    return None


def fog_severity_of(root: Path, version: str) -> int | None:
    """Fog severity recorded in ``degradation.json`` (0 without fog; None if not recorded)."""
    path = root / version / "degradation.json"
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
        s = rec["settings"]
        return int(s["fog"]) if not s.get("fog_visibility") else None
    except (ValueError, KeyError, TypeError, OverflowError):
        raise DataError(f"{path}: not a simgen degradation record") from None


def conditions_of(sets: list[tuple[str, Path]], corruptions: list[Corruption], version: str) -> list[Condition]:
    """The conditions of the ``--set`` dataroots (the first is the clean reference; the others
    must be paired with it) and of the ``--corrupt`` load-time corruptions of the clean set."""
    if not sets:
        raise ConfigError("give at least one --set NAME=DATAROOT (the first is the clean reference)")
    (clean_name, clean_root), others = sets[0], sets[1:]
    for name, root in sets:
        if not (root / version).is_dir():
            raise DataError(f"set {name}: no nuScenes tables at {root / version}")
    out = [Condition(clean_name, clean_root, (), fog_severity_of(clean_root, version) or 0)]
    for name, root in others:
        check_paired(clean_root, root, version, name)
        # A degraded set without fog (occlusion, lens dirt) is not a point of the fog curve.
        out.append(Condition(name, root, (), fog_severity_of(root, version) or None))
    out += [Condition(str(c), clean_root, (c,)) for c in corruptions]
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"condition names must be unique (--set NAME, --corrupt), got {names}")
    return out


def run(ckpts: list[tuple[str, Path]], conditions: list[Condition], out: Path, split: str, version: str,
        progress=print) -> dict:
    """Evaluate every checkpoint on every condition; returns (and writes) the robustness record."""
    if not ckpts:
        raise ConfigError("give at least one --ckpt NAME=CHECKPOINT")
    out.mkdir(parents=True, exist_ok=True)
    record = {"split": split, "conditions": [c.name for c in conditions], "clean": conditions[0].name,
              "fog_severity": {c.name: c.fog_severity for c in conditions}, "models": {}}
    for name, path in ckpts:
        model, ckpt = load_predictor(path)
        entry = {"checkpoint": str(path), "variant": ckpt["variant"], "metrics": {}}
        for cond in conditions:
            ds = NuScenesDetection(cond.dataroot, version, split, model.cfg.data_config(), cond.corruptions)
            summary = evaluate_model(model, ds, out / name / cond.name.replace(":", "_"))
            entry["metrics"][cond.name] = {"mAP": summary["mean_ap"], "NDS": summary["nd_score"],
                                           "AP": summary["mean_dist_aps"]}
            progress(f"{name:12s} {cond.name:24s} mAP {summary['mean_ap']:.4f}  NDS {summary['nd_score']:.4f}")
        record["models"][name] = entry
    summarise(record)
    io.write_json(out / "robustness.json", record)
    io.write_text(out / "robustness.md", markdown(record))
    plot(record, out / "robustness.png")
    return record


def summarise(record: dict) -> None:
    """Add RR / mRR and, when a ``concat`` checkpoint is present, CE / mCE, in place."""
    clean = record["clean"]
    degraded = [c for c in record["conditions"] if c != clean]
    base = next((n for n, m in record["models"].items() if m["variant"] == BASELINE_VARIANT), None)
    record["baseline"] = base
    for m in record["models"].values():
        nds0 = m["metrics"][clean]["NDS"]
        m["RR"] = {c: (m["metrics"][c]["NDS"] / nds0 if nds0 > 0 else math.nan) for c in record["conditions"]}
        m["mRR"] = float(np.mean([m["RR"][c] for c in degraded])) if degraded else math.nan
        if base is not None:
            b = record["models"][base]["metrics"]
            m["CE"] = {c: ((1 - m["metrics"][c]["NDS"]) / (1 - b[c]["NDS"]) if b[c]["NDS"] < 1 else math.nan)
                       for c in record["conditions"]}
            m["mCE"] = float(np.mean([m["CE"][c] for c in degraded])) if degraded else math.nan


def markdown(record: dict) -> str:
    """The report: NDS (mAP) per model and condition with mRR and mCE, then RR and CE per condition."""
    conds = record["conditions"]
    lines = ["# Robustness", "",
             f"Split `{record['split']}`; clean reference `{record['clean']}`; official DetectionEval for every "
             f"cell. RR = NDS_c / NDS_clean; CE = (1 - NDS_c) / (1 - NDS_c of the `{BASELINE_VARIANT}` baseline"
             f"{' `' + record['baseline'] + '`' if record.get('baseline') else ', absent here'}).", "",
             "## NDS (mAP)", "",
             "| model | variant | " + " | ".join(conds) + " | mRR | mCE |",
             "|---|---|" + "---:|" * (len(conds) + 2)]
    for name, m in record["models"].items():
        cells = [f"{m['metrics'][c]['NDS']:.4f} ({m['metrics'][c]['mAP']:.4f})" for c in conds]
        mce = f"{m['mCE']:.3f}" if "mCE" in m else "-"
        lines.append(f"| {name} | {m['variant']} | " + " | ".join(cells) + f" | {m['mRR']:.3f} | {mce} |")
    lines += ["", "## RR per condition", "", "| model | " + " | ".join(conds) + " |", "|---|" + "---:|" * len(conds)]
    for name, m in record["models"].items():
        lines.append(f"| {name} | " + " | ".join(f"{m['RR'][c]:.3f}" for c in conds) + " |")
    if record.get("baseline"):
        lines += ["", "## CE per condition", "", "| model | " + " | ".join(conds) + " |", "|---|" + "---:|" * len(conds)]
        for name, m in record["models"].items():
            lines.append(f"| {name} | " + " | ".join(f"{m['CE'][c]:.3f}" for c in conds) + " |")
    lines += ["", "![NDS against fog severity, and the other conditions](robustness.png)", ""]
    return "\n".join(lines)


def plot(record: dict, path: Path) -> None:
    """NDS against fog severity (one line per model), and a bar chart of the other conditions
    when there are any (a fog-only run gets the fog panel alone)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fog = {c: s for c, s in record["fog_severity"].items() if s is not None}
    other = [c for c in record["conditions"] if c not in fog]
    if other:
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 4.5), dpi=110, gridspec_kw={"width_ratios": [1, 1.6]})
    else:
        fig, a1 = plt.subplots(1, 1, figsize=(6, 4.5), dpi=110)
    for name, m in record["models"].items():
        pts = sorted((s, m["metrics"][c]["NDS"]) for c, s in fog.items())
        a1.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"{name} ({m['variant']})")
    a1.set_xlabel("fog severity (0 = clean)")
    a1.set_ylabel("NDS")
    a1.set_title("NDS under fog (paired sets)")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8)
    if other:
        names = list(record["models"])
        width = 0.8 / len(names)
        x = np.arange(len(other))
        for k, name in enumerate(names):
            a2.bar(x + k * width, [record["models"][name]["metrics"][c]["NDS"] for c in other], width, label=name)
        a2.set_xticks(x + width * (len(names) - 1) / 2)
        a2.set_xticklabels(other, rotation=25, ha="right", fontsize=8)
        a2.set_ylabel("NDS")
        a2.set_title("occlusion, corruptions and sensor failure")
        a2.grid(alpha=0.3, axis="y")
        a2.legend(fontsize=8)
    fig.tight_layout()
    io.save_figure(path, fig)
    plt.close(fig)
