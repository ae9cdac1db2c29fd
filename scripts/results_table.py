#!/usr/bin/env python
"""Write docs/results.md from the run folders of scripts/benchmark.sh.

    python scripts/results_table.py benchmark_out --runs lidar_s0 full_s0 ... --out docs/results.md

Reads OUT/benchmark.json (the benchmark's settings), the dataset's splits, OUT/scored.json (the
boxes scored per class and split), OUT/staged.json (the stages' progress, for the pending runs) and per evaluated run RUN/run.json (config, recipe, code
version), RUN/cpu.json (the CPU seconds of its stages), RUN/code_id and
RUN/eval/metrics_summary.json (the devkit's summary). A run without the summary is listed as
pending with its stages' progress; a file that is junk or lacks a field the table needs is one
line naming it, exit 2. Runs of another code identity than the first are marked, never mixed in
silently. The file is replaced atomically, so a reader never sees half a table. It runs in a
second and needs no model.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from clfbev import io
from clfbev.config import ModelConfig
from clfbev.errors import ConfigError, DataError, run_guarded

VERSION = "v1.0-sim"
# The devkit's five TP errors (nuscenes.eval.detection.constants.TP_METRICS) and their columns.
TP_COLUMNS = {"trans_err": "mATE", "scale_err": "mASE", "orient_err": "mAOE", "vel_err": "mAVE", "attr_err": "mAAE"}
# The devkit's ten detection classes in its order (nuscenes.eval.detection.constants.DETECTION_NAMES),
# to name the ones not evaluated.
DETECTION_CLASSES = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian", "motorcycle",
                     "bicycle", "traffic_cone", "barrier")
# The runs' kinds (the name before _sSEED): the variant each trains, and its recipe.
KINDS = {"lidar": "lidar", "camera": "camera", "full": "full", "mcm": "mcm", "concat": "concat", "fullmd": "full"}
FUSED = ("full", "mcm", "concat", "fullmd")
# The fields each file must have for the table (``a.b``: field b of the object in field a).
SETTINGS_FIELDS = ("scenes", "samples_per_scene", "resolution", "data_seed", "val_fraction", "camera_steps",
                   "lidar_steps", "fusion_steps", "lidar_alone_steps", "camera_alone_steps")
RUN_FIELDS = ("config", "train.max_steps", "train.batch_size")
SUMMARY_FIELDS = ("mean_ap", "nd_score", "mean_dist_aps", *(f"tp_errors.{k}" for k in TP_COLUMNS))
CPU_FIELDS = ("stages", "cpu_s")


# ---------------------------------------------------------------- reading

def read_json(path: Path, fields: tuple[str, ...] = ()):
    """The JSON in ``path`` (None when there is no such file), with ``fields`` checked.

    Raises DataError naming the file when it is not JSON or lacks one of ``fields``."""
    if not path.exists():
        return None
    try:
        obj = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: not valid JSON ({e})") from None
    for name in fields:
        _require(obj, name, path)
    return obj


def _require(obj, name: str, path: Path) -> None:
    """DataError unless ``obj`` has the (dotted) field ``name``."""
    for key in name.split("."):
        if not isinstance(obj, dict) or key not in obj:
            raise DataError(f"{path}: lacks the field {name!r}")
        obj = obj[key]


def read_settings(out: Path) -> dict:
    """OUT/benchmark.json, the benchmark's settings."""
    settings = read_json(out / "benchmark.json", SETTINGS_FIELDS)
    if settings is None:
        raise DataError(f"{out / 'benchmark.json'} is missing: run scripts/benchmark.sh first")
    return settings


def read_stages(out: Path) -> dict:
    """{stage: its entry} of OUT/staged.json ({} before the first stage)."""
    record = read_json(out / "staged.json", ("stages",))
    return {} if record is None else record["stages"]


def kind_of(name: str) -> tuple[str, int]:
    """(kind, seed) of a run name KIND_sSEED."""
    kind, _, seed = name.rpartition("_s")
    return kind, int(seed)


def load_run(out: Path, name: str) -> dict:
    """Everything the table needs about one run folder."""
    run = out / name
    kind, seed = kind_of(name)
    summary = read_json(run / "eval" / "metrics_summary.json", SUMMARY_FIELDS)
    code_id = (run / "code_id").read_text().strip() if (run / "code_id").exists() else None
    return {
        "name": name, "kind": kind, "variant": KINDS[kind], "seed": seed, "summary": summary,
        "info": read_json(run / "run.json", RUN_FIELDS),
        "cpu": read_json(run / "cpu.json", CPU_FIELDS) if summary is not None else None,
        "code_id": code_id,
    }


def split_sizes(data: Path) -> dict[str, tuple[int, int]] | None:
    """{split: (scenes, samples)} of the dataset's splits.json, or None before it exists."""
    tables = data / VERSION
    splits = read_json(tables / "splits.json")
    if splits is None or not (tables / "sample.json").exists():
        return None
    try:
        scene_name = {s["token"]: s["name"] for s in read_json(tables / "scene.json")}
        per_scene: dict[str, int] = {}
        for s in read_json(tables / "sample.json"):
            per_scene[scene_name[s["scene_token"]]] = per_scene.get(scene_name[s["scene_token"]], 0) + 1
        return {k: (len(v), sum(per_scene.get(n, 0) for n in v)) for k, v in splits.items()}
    except (KeyError, TypeError, AttributeError) as e:
        raise DataError(f"{tables}: splits.json, scene.json and sample.json do not fit together ({e!r})") from None


def stages_of(name: str) -> list[str]:
    """The stages a run trains through, in order (scripts/benchmark.sh's needs_of and the run)."""
    kind, seed = kind_of(name)
    if kind in FUSED:
        return ["cache", f"camstage_s{seed}", f"lidarstage_s{seed}", name]
    return (["cache"] if kind == "camera" else []) + [name]


# ---------------------------------------------------------------- formatting

def num(x, digits: int) -> str:
    """A metric; NaN (a TP error with no true positive) as n/a."""
    return "n/a" if x is None or x != x else f"{x:.{digits}f}"


def plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def table(header: list[str], rows: list[list[str]], right_from: int) -> list[str]:
    align = ["---" if i < right_from else "---:" for i in range(len(header))]
    return ["| " + " | ".join(r) + " |" for r in (header, align, *rows)]


def mean_half_range(values: list[float]) -> tuple[float, float]:
    return sum(values) / len(values), (max(values) - min(values)) / 2


def with_defaults(config: dict) -> dict:
    """A run's model config with the fields it predates at their defaults (the loss weights
    too). A field is added with the default that keeps the earlier behaviour, which is also
    what loading such a checkpoint fills in, so a run recorded before the field ran with it."""
    defaults = json.loads(json.dumps(dataclasses.asdict(ModelConfig())))
    return {**defaults, **config, "loss": {**defaults["loss"], **config.get("loss", {})}}


def recipe_text(kind: str, settings: dict) -> str:
    """The run's recipe in a few words."""
    if kind == "lidar":
        return f"{settings['lidar_alone_steps']} steps"
    if kind == "camera":
        return f"{settings['camera_alone_steps']} steps, cached features"
    staged = f"staged: {settings['camera_steps']} + {settings['lidar_steps']} + {settings['fusion_steps']} steps"
    return staged + (", modality dropout" if kind == "fullmd" else "")


# ---------------------------------------------------------------- the document

def render(out: Path, run_names: list[str], now: float | None = None) -> str:
    """docs/results.md for the runs ``run_names`` (in table order) of the benchmark folder ``out``;
    ``now`` (seconds since the epoch) stamps it."""
    settings = read_settings(out)
    runs = [load_run(out, n) for n in run_names]
    stages = read_stages(out)
    done = [r for r in runs if r["summary"] is not None]
    reference = next((r["code_id"] for r in done), None)
    lines = header_lines(out, runs, now)
    lines += setup_lines(out, settings, split_sizes(out / "data"), done, reference)
    lines += runs_lines(runs, settings, stages, reference)
    lines += per_class_lines(runs)
    lines += seed_spread_lines(runs)
    lines += reproduce_lines(out, settings, run_names)
    lines += config_lines(done)
    return "\n".join(lines)


def header_lines(out: Path, runs: list[dict], now: float | None) -> list[str]:
    done = sum(r["summary"] is not None for r in runs)
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(now))
    return [
        "# Results: the benchmark",
        "",
        f"Written by `scripts/results_table.py` from `{out}` on {stamp}: **{done} of {len(runs)} runs done**. "
        "Generated, not edited by hand: `bash scripts/benchmark.sh` completes the missing runs and rewrites it.",
        "",
    ]


def setup_lines(out: Path, settings: dict, sizes: dict | None, done: list[dict], reference: str | None) -> list[str]:
    """The Setup section: data, recipes, evaluation, CPU, code."""
    data = (f"`simgen make`, urban preset: {settings['scenes']} scenes x {settings['samples_per_scene']} key frames "
            f"at {settings['resolution']}, seed {settings['data_seed']}, val fraction {settings['val_fraction']}")
    if sizes:
        data += "; " + ", ".join(f"`{k}` {plural(sc, 'scene')} ({plural(sa, 'sample')})" for k, (sc, sa) in sizes.items())
    data_id = (out / "data_id").read_text().strip() if (out / "data_id").exists() else "not made yet"
    lines = ["## Setup", "", f"- Data: {data}; identity `{data_id}` (`scripts/data_identity.py`)."]
    scored = read_json(out / "scored.json")
    if scored:
        per_split = [f"`{split}` " + ", ".join(f"{c} {n}" for c, n in counts.items()) for split, counts in scored.items()]
        lines.append("- Boxes the devkit scores (a lidar point, within the class range; `scripts/scored_boxes.py`): "
                     + "; ".join(per_split) + ".")
    lines.append(
        f"- Recipes (`clfbev train --config tiny`, batch 2, no validation while training: the evaluated weights are "
        f"the last step's): `lidar` alone {settings['lidar_alone_steps']} steps; `camera` alone "
        f"{settings['camera_alone_steps']} steps on the frozen shipped encoder's cached features; the fused variants "
        f"in stages (`scripts/staged.sh`'s recipe): a camera stage of {settings['camera_steps']} cached steps and a "
        f"lidar stage of {settings['lidar_steps']} steps per seed, shared by that seed's fused runs, then each "
        f"variant's fusion stage of {settings['fusion_steps']} steps from both; `fullmd` is `full`'s fusion stage "
        "with modality dropout (a quarter of the samples without lidar, a quarter without cameras). The step "
        "budgets give `lidar`, `camera` and the staged `full` about the same CPU-hours; a fused run's CPU counts "
        "all its stages, the shared ones and the feature cache included.")
    lines.append("- Evaluation: `clfbev eval` on `sim-val`, the devkit's `DetectionEval` restricted to the classes "
                 "with ground truth (with lidar points) in the split.")
    total = sum(r["cpu"]["cpu_s"] for r in done)
    lines.append(f"- CPU: user + system seconds of each stage's processes (`staged.json`), a run's evaluation "
                 f"included; {total / 3600:.1f} CPU-hours over the done runs, shared stages counted in each.")
    lines += [code_line(done, reference), ""]
    return lines


def code_line(done: list[dict], reference: str | None) -> str:
    """The code identity of the runs, the other ones named."""
    if not done:
        return "- Code: no run evaluated yet."
    commits = sorted({r["info"].get("code_version", "?") for r in done if r["info"]})
    other = [r["name"] for r in done if r["code_id"] != reference]
    line = (f"- Code: identity `{reference}` (the git trees of `clfbev/` and `simgen/`), commit "
            f"{', '.join(f'`{c}`' for c in commits)} (`run.json`'s code_version where each run started).")
    if other:
        line += (f" **Not one code version:** {', '.join(f'`{n}`' for n in other)} ran on other code (marked "
                 "with \u2020); their rows do not compare with the others'.")
    return line


def progress(name: str, stages: dict) -> str:
    """A pending run's stages: done, started (with its parts) or not started."""
    parts = []
    for stage in stages_of(name):
        entry = stages.get(stage)
        state = "not started" if entry is None else "done" if entry["done"] else "started"
        parts.append(f"{stage} {state}")
    return "pending: " + ", ".join(parts)


def runs_lines(runs: list[dict], settings: dict, stages: dict, reference: str | None) -> list[str]:
    """The main table: one row per run, pending ones with their stages' progress."""
    rows = []
    for r in runs:
        s = r["summary"]
        mark = " \u2020" if s is not None and r["code_id"] != reference else ""
        if s is None:
            cells = [progress(r["name"], stages), *[""] * (2 + len(TP_COLUMNS))]
        else:
            cells = [f"{r['cpu']['cpu_s'] / 3600:.2f}", num(s["mean_ap"], 4), num(s["nd_score"], 4),
                     *(num(s["tp_errors"][k], 3) for k in TP_COLUMNS)]
        rows.append([f"`{r['name']}`{mark}", r["variant"], str(r["seed"]), recipe_text(r["kind"], settings), *cells])
    header = ["run", "variant", "seed", "recipe", "CPU-h", "mAP", "NDS", *TP_COLUMNS.values()]
    return ["## Runs (sim-val)", "", *table(header, rows, right_from=4), ""]


def per_class_lines(runs: list[dict]) -> list[str]:
    """Per-class AP of the classes the devkit evaluated (those with GT in the split), in its order."""
    done = [r for r in runs if r["summary"] is not None]
    if not done:
        return []
    classes: list[str] = []
    for r in done:
        classes += [c for c in r["summary"]["mean_dist_aps"] if c not in classes]
    rows = []
    for r in runs:
        aps = r["summary"]["mean_dist_aps"] if r["summary"] else None
        rows.append([f"`{r['name']}`", *([num(aps.get(c), 3) if c in aps else "" for c in classes] if aps
                                        else ["pending", *[""] * (len(classes) - 1)])])
    lines = ["## Per-class AP (sim-val)", "", *table(["run", *classes], rows, right_from=1)]
    missing = [c for c in DETECTION_CLASSES if c not in classes]
    if missing:
        lines += ["", f"Not evaluated (no ground truth with lidar points in `sim-val`, or not generated): "
                      f"{', '.join(missing)}."]
    return [*lines, ""]


def seed_spread_lines(runs: list[dict]) -> list[str]:
    """Mean ± half the range of mAP and NDS over the seeds of each kind of run with several."""
    by_kind: dict[str, list[dict]] = {}
    for r in runs:
        by_kind.setdefault(r["kind"], []).append(r)
    multi = {k: rs for k, rs in by_kind.items() if len(rs) > 1}
    if not multi:
        return []
    rows = []
    for kind, rs in multi.items():
        seeds = ", ".join(str(r["seed"]) for r in rs)
        ok = [r["summary"] for r in rs if r["summary"] is not None]
        if len(ok) < len(rs):
            rows.append([kind, seeds, f"pending ({len(ok)} of {len(rs)} seeds done)", "", "", ""])
            continue
        cells = []
        for key in ("mean_ap", "nd_score"):
            m, h = mean_half_range([s[key] for s in ok])
            cells.append(f"{m:.4f} ± {h:.4f}")
        cells += [f"{2 * mean_half_range([s[k] for s in ok])[1]:.4f}" for k in ("mean_ap", "nd_score")]
        rows.append([kind, seeds, *cells])
    return ["## Seed spread", "",
            "Mean ± half the range over the seeds, and the spread (max - min): the part of a difference "
            "between variants that one seed's luck can explain.", "",
            *table(["run", "seeds", "mAP", "NDS", "mAP spread", "NDS spread"], rows, right_from=2), ""]


def reproduce_lines(out: Path, settings: dict, run_names: list[str]) -> list[str]:
    """The commands: the benchmark's invocation and where each stage's command is recorded."""
    return [
        "## Reproduce",
        "",
        "```bash",
        "bash scripts/benchmark.sh                  # every run; rerun to resume",
        "bash scripts/benchmark.sh lidar full       # or some variants (all their seeds)",
        "bash scripts/benchmark.sh --list           # each run's state",
        f".venv/bin/python scripts/results_table.py {out} --runs {' '.join(run_names)} --out docs/results.md",
        "```",
        "",
        f"Each stage's exact command is its `settings` in `{out}/staged.json`; each run's final weights are "
        f"`docs/results/RUN/weights.pt.xz` (`clfbev eval --data {out}/data --ckpt docs/results/RUN/weights.pt.xz "
        "--split sim-val --out EVAL` scores them again without training).",
        "",
    ]


def config_lines(done: list[dict]) -> list[str]:
    """The first done run's model config, one line per field: the form of a `--config` YAML file."""
    if not done or done[0]["info"] is None:
        return []
    config = with_defaults(done[0]["info"]["config"])
    return ["<details><summary>The model config <code>tiny</code> (from run.json)</summary>",
            "", "```yaml", *(f"{k}: {json.dumps(v)}" for k, v in config.items()), "```", "",
            "</details>", ""]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="the benchmark's folder (benchmark_out)")
    ap.add_argument("--runs", nargs="+", required=True, help="run names, in table order (KIND_sSEED)")
    ap.add_argument("--out", dest="results", type=Path, default=Path("docs/results.md"), help="markdown to write")
    args = ap.parse_args(argv)
    return run_guarded(lambda: write_table(args.out, args.runs, args.results), prog="results_table")


def write_table(out: Path, run_names: list[str], results: Path) -> None:
    """Render the table of ``run_names`` in ``out`` and replace ``results`` with it."""
    bad = [n for n in run_names if not n.rpartition("_s")[2].isdigit() or n.rpartition("_s")[0] not in KINDS]
    if bad:
        raise ConfigError(f"--runs: run names must be KIND_sSEED with KIND one of {', '.join(KINDS)}, "
                          f"got {', '.join(bad)}")
    text = render(out, run_names)
    io.write_text(results, text)
    n_done = sum((out / n / "eval" / "metrics_summary.json").exists() for n in run_names)
    print(f"benchmark: table {results} ({n_done} of {len(run_names)} runs done)")


if __name__ == "__main__":
    sys.exit(main())
