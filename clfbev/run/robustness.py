"""The robustness suite: every checkpoint on every condition through the official DetectionEval,
beside the sensor-visibility oracle of each condition, with the robustness benchmarks' summary
metrics and a report (:mod:`clfbev.run.robustness_report`).

Conditions are (1) the first ``--set``, the clean reference; (2) every further ``--set``, a paired
degraded dataroot (same annotation tables, only the sensor data differ: simgen's fog, rain,
snowfall, night, lens dirt, ...; with occluders in the world, also what the sensors see of each
object, see :func:`check_paired`); (3) every ``--corrupt`` load-time corruption applied to the
clean set (:mod:`clfbev.corruptions`). Every cell is one :func:`clfbev.run.evaluate.evaluate_model`,
kept in ``OUT/MODEL/CONDITION/`` with the identity of what it evaluated: a rerun reuses the cells
whose checkpoint and data are unchanged, so an interrupted suite continues where it stopped.

Each condition is a point of a curve (``family`` and ``severity``: fog severity, rain or snowfall
rate, a corruption's severity; the clean set is severity 0 of every curve) or, with no family, a
bar of its own (night, occlusion, lens dirt, a set combining several).

Metrics per checkpoint m and condition c:

- ``RR = NDS_c / NDS_clean`` (resilience rate), ``mRR`` its mean over the degraded conditions;
- ``CE = (1 - NDS_c(m)) / (1 - NDS_c(baseline))`` (corruption error relative to the ``concat``
  checkpoint, as mCE is relative to a reference model), ``mCE`` its mean;
- ``share = NDS_c / NDS_c(oracle)``: how much of what the sensors still see the model finds.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from clfbev import io
from clfbev.corruptions import Corruption
from clfbev.data import NuScenesDetection
from clfbev.errors import ConfigError, DataError
from clfbev.run.evaluate import evaluate_model
from clfbev.run.experts_file import load_predictor
from clfbev.run.oracle import evaluate_oracle
from clfbev.run.robustness_report import markdown, plot, summarise
from clfbev.settings import DETECTION_CLASSES

PAIRED_TABLES = ("sample_annotation", "instance", "sample", "ego_pose")
# What occluders placed in the world may change in a paired set's labels (simgen --occlusion):
# how much of each object the sensors see, never the object itself.
SEEN_FIELDS = ("visibility_token", "num_lidar_pts", "num_radar_pts")
ORACLE = "oracle"          # the oracle's cells: OUT/oracle/CONDITION/


@dataclass(frozen=True)
class Condition:
    name: str
    dataroot: Path
    corruptions: tuple[Corruption, ...] = ()
    family: str | None = None      # the curve it is a point of (None: a bar of its own)
    severity: float = 0.0


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


def set_family(root: Path, version: str) -> tuple[str | None, float]:
    """A paired set's curve from its ``degradation.json``: ("fog", severity), ("rain", mm/h) or
    ("snow", mm/h) when that is all the set changes; (None, 0) for anything else (night,
    occluders, lens dirt, dead sensors, a combination) and for a set without a record."""
    path = root / version / "degradation.json"
    if not path.is_file():
        return None, 0.0
    try:
        rec = json.loads(path.read_text())
        d, w = rec["settings"], rec.get("weather", {})
        fog = 0.0 if d.get("fog_visibility") else float(d.get("fog", 0))
        changes = {"fog": fog, "rain": float(w.get("rain", 0.0)), "snow": float(w.get("snow", 0.0))}
        others = (d.get("fog_visibility") or w.get("night") or d.get("occlusion", "none") != "none"
                  or d.get("lens_occlusion") or d.get("beam_drop") or d.get("lidar_fov", 360) < 360
                  or d.get("drop_sensors"))
    except (ValueError, KeyError, TypeError, AttributeError, OverflowError):
        raise DataError(f"{path}: not a simgen degradation record") from None
    active = [(k, v) for k, v in changes.items() if v > 0]
    if len(active) == 1 and not others:
        return active[0]
    return None, 0.0


def corruption_family(c: Corruption) -> tuple[str | None, float]:
    """A load-time corruption's curve: its name (with its sensor), at its severity; the one
    without a severity (``lidar_missing``) and the one whose clean value is not 0 (``fov``: 360
    degrees) are bars."""
    if c.name in ("lidar_missing", "fov"):
        return None, 0.0
    return (f"{c.name}:{c.sensor}" if c.sensor else c.name), float(c.severity)


def conditions_of(sets: list[tuple[str, Path]], corruptions: list[Corruption], version: str) -> list[Condition]:
    """The conditions of the ``--set`` dataroots (the first is the clean reference; the others
    must be paired with it) and of the ``--corrupt`` load-time corruptions of the clean set."""
    if not sets:
        raise ConfigError("give at least one --set NAME=DATAROOT (the first is the clean reference)")
    (clean_name, clean_root), others = sets[0], sets[1:]
    for name, root in sets:
        if not (root / version).is_dir():
            raise DataError(f"set {name}: no nuScenes tables at {root / version}")
    out = [Condition(clean_name, clean_root)]
    for name, root in others:
        check_paired(clean_root, root, version, name)
        out.append(Condition(name, root, (), *set_family(root, version)))
    out += [Condition(str(c), clean_root, (c,), *corruption_family(c)) for c in corruptions]
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"condition names must be unique (--set NAME, --corrupt), got {names}")
    if ORACLE in names:
        raise ConfigError(f"'{ORACLE}' names the oracle's cells: give the condition another name")
    return out


def _digest(*paths: Path) -> str:
    """sha256 over the bytes of ``paths`` (absent ones count as empty)."""
    h = hashlib.sha256()
    for path in paths:
        h.update(path.read_bytes() if path.is_file() else b"")
    return h.hexdigest()


def _condition_identity(cond: Condition, version: str) -> dict:
    """What a cell's result depends on besides the model: the set's tables and record, the corruptions."""
    tables = cond.dataroot / version
    return {"condition": cond.name, "dataroot": str(cond.dataroot), "corruptions": [str(c) for c in cond.corruptions],
            "data_sha256": _digest(tables / "sample_data.json", tables / "sample_annotation.json",
                                   tables / "degradation.json")}


def _cell(out_dir: Path, identity: dict, compute) -> dict:
    """The devkit summary of one cell: reused from ``out_dir`` when its ``cell.json`` holds the
    same identity, else computed by ``compute()`` and recorded (the summary first, the identity
    last, so that an interrupted cell is computed again)."""
    ident_path, summary_path = out_dir / "cell.json", out_dir / "metrics_summary.json"
    if ident_path.is_file() and summary_path.is_file():
        try:
            if json.loads(ident_path.read_text()) == identity:
                return json.loads(summary_path.read_text())
        except ValueError:
            pass      # a cell cut short: computed again
    ident_path.unlink(missing_ok=True)
    summary = compute()
    io.write_json(summary_path, summary)
    io.write_json(ident_path, identity)
    return summary


def _cell_dir(out: Path, name: str, cond: Condition) -> Path:
    return out / name / cond.name.replace(":", "_")


def run(ckpts: list[tuple[str, Path]], conditions: list[Condition], out: Path, split: str, version: str,
        progress=print) -> dict:
    """Evaluate the oracle and every checkpoint on every condition; returns (and writes) the
    robustness record."""
    if not ckpts:
        raise ConfigError("give at least one --ckpt NAME=CHECKPOINT")
    if ORACLE in (name for name, _ in ckpts):
        raise ConfigError(f"'{ORACLE}' names the oracle's cells: give the checkpoint another name")
    out.mkdir(parents=True, exist_ok=True)
    record = {"split": split, "conditions": [c.name for c in conditions], "clean": conditions[0].name,
              "family": {c.name: [c.family, c.severity] for c in conditions}, "models": {}, "oracle": {}}
    for cond in conditions:
        ident = {**_condition_identity(cond, version), "split": split}
        summary = _cell(_cell_dir(out, ORACLE, cond), ident, lambda: evaluate_oracle(
            cond.dataroot, version, split, cond.corruptions, _cell_dir(out, ORACLE, cond), DETECTION_CLASSES))
        record["oracle"][cond.name] = {**_metrics(summary), "counts": summary["oracle_counts"]}
        progress(f"{ORACLE:12s} {cond.name:24s} mAP {summary['mean_ap']:.4f}  NDS {summary['nd_score']:.4f}")
    for name, path in ckpts:
        model, ckpt = load_predictor(path)
        entry = {"checkpoint": str(path), "variant": ckpt["variant"], "metrics": {}}
        model_ident = {"checkpoint_sha256": _digest(Path(path)), "split": split}
        for cond in conditions:
            cell = _cell_dir(out, name, cond)
            ident = {**_condition_identity(cond, version), **model_ident}
            ds = NuScenesDetection(cond.dataroot, version, split, model.cfg.data_config(), cond.corruptions)
            summary = _cell(cell, ident, lambda: evaluate_model(model, ds, cell))
            entry["metrics"][cond.name] = _metrics(summary)
            progress(f"{name:12s} {cond.name:24s} mAP {summary['mean_ap']:.4f}  NDS {summary['nd_score']:.4f}")
        record["models"][name] = entry
    summarise(record)
    io.write_json(out / "robustness.json", record)
    io.write_text(out / "robustness.md", markdown(record))
    plot(record, out / "robustness.png")
    return record


def _metrics(summary: dict) -> dict:
    return {"mAP": summary["mean_ap"], "NDS": summary["nd_score"], "AP": summary["mean_dist_aps"]}
