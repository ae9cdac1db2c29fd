#!/usr/bin/env python
"""Write docs/results.md from the run folders of scripts/benchmark.sh.

    python scripts/results_table.py benchmark_out --runs lidar_s0 full_s0 ... --out docs/results.md

Reads OUT/benchmark.json (the benchmark's settings), the dataset's splits, and per run
RUN/run.json (recipe, code version), RUN/wall.jsonl (the timed parts) and
RUN/eval/metrics_summary.json (the devkit's summary). A run without the summary is listed as
pending; a file that is junk or lacks a field the table needs is one line naming it, exit 2.
The file is replaced atomically, so a reader never sees half a table. It runs in a second and
needs no model.
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
from clfbev.run.train_config import BOOKKEEPING, TrainConfig

VERSION = "v1.0-sim"
# The devkit's five TP errors (nuscenes.eval.detection.constants.TP_METRICS) and their columns.
TP_COLUMNS = {"trans_err": "mATE", "scale_err": "mASE", "orient_err": "mAOE", "vel_err": "mAVE", "attr_err": "mAAE"}
# The devkit's ten detection classes in its order (nuscenes.eval.detection.constants.DETECTION_NAMES),
# to name the ones not evaluated.
DETECTION_CLASSES = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian", "motorcycle",
                     "bicycle", "traffic_cone", "barrier")
# Train-config fields the recipe sets per variant (clfbev.run.train_config.recipe: the camera
# variant pastes nothing, as the pasted objects have no pixels): they must agree within a
# variant, not across.
PER_VARIANT = ("gt_paste",)
# The fields each file must have for the table (``a.b``: field b of the object in field a).
SETTINGS_FIELDS = ("scenes", "samples_per_scene", "resolution", "data_seed", "val_fraction", "steps")
RUN_FIELDS = ("config", "train.max_steps", "train.batch_size")
SUMMARY_FIELDS = ("mean_ap", "nd_score", "mean_dist_aps", *(f"tp_errors.{k}" for k in TP_COLUMNS))
PART_FIELDS = {"train": ("seconds", "to_step"), "eval": ("seconds",)}   # per stage, in wall.jsonl


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


def read_parts(path: Path) -> list[dict]:
    """The lines of RUN/wall.jsonl; a line torn by a kill is skipped."""
    parts = []
    if path.exists():
        for i, line in enumerate(path.read_text().splitlines(), 1):
            try:
                part = json.loads(line)
            except ValueError:
                continue
            if not isinstance(part, dict):
                raise DataError(f"{path}: line {i} is not a JSON object")
            missing = [k for k in PART_FIELDS.get(part.get("stage"), ()) if k not in part]
            if missing:
                raise DataError(f"{path}: line {i} lacks the field {missing[0]!r}")
            parts.append(part)
    return parts


def config_name(argv: list[str]) -> str:
    """The --config value of a recorded command line (clfbev train's default: tiny)."""
    for i, a in enumerate(argv):
        if a == "--config" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--config="):
            return a.split("=", 1)[1]
    return "tiny"


def load_run(out: Path, name: str) -> dict:
    """Everything the table needs about one run folder."""
    run = out / name
    variant, _, seed = name.rpartition("_s")
    info = read_json(run / "run.json", RUN_FIELDS)
    parts = read_parts(run / "wall.jsonl")
    train = [p for p in parts if p.get("stage") == "train"]
    evals = [p for p in parts if p.get("stage") == "eval"]
    return {
        "name": name, "variant": variant, "seed": int(seed),
        "summary": read_json(run / "eval" / "metrics_summary.json", SUMMARY_FIELDS),
        "info": info,
        "train_s": sum(p["seconds"] for p in train) if train else None,
        "train_parts": len(train),
        "eval_s": evals[-1]["seconds"] if evals else None,
        "step": max((p["to_step"] for p in train), default=0),
        "threads": sorted({p["threads"] for p in parts if "threads" in p}),
        "cores": sorted({p["cores"] for p in parts if "cores" in p}),
        "ends": sorted(p["end"] for p in parts if "end" in p),
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


# ---------------------------------------------------------------- formatting

def num(x, digits: int) -> str:
    """A metric; NaN (a TP error with no true positive) as n/a."""
    return "n/a" if x is None or x != x else f"{x:.{digits}f}"


def plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def minutes(seconds) -> str:
    return "" if seconds is None else f"{seconds / 60:.1f}"


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


def recipe_of(info: dict) -> dict:
    """The settings of a run that must agree across the table: all but the seed, the bookkeeping
    and, when --max-steps sets the length, the unused epoch count."""
    unused = ("seed", *BOOKKEEPING, *(("epochs",) if info["train"].get("max_steps") else ()))
    # A field a run predates (image_init) ran at its default, as for the model config.
    recorded = {**json.loads(json.dumps(dataclasses.asdict(TrainConfig()))), **info["train"]}
    train = {k: v for k, v in recorded.items() if k not in unused}
    return {"config_name": config_name(info.get("argv", [])), "config": with_defaults(info["config"]), "train": train}


def values_by_variant(started: list[dict], key: str) -> dict:
    """{value of train field ``key``: [variants with it]}, in table order."""
    values: dict = {}
    for r in started:
        v = r["info"]["train"].get(key)
        if r["variant"] not in values.setdefault(v, []):
            values[v].append(r["variant"])
    return values


def describe_train(train: dict) -> str:
    return ", ".join(f"{k}={v!r}" if isinstance(v, str) else f"{k}={v}" for k, v in train.items())


# ---------------------------------------------------------------- the document

def render(out: Path, run_names: list[str], now: float | None = None) -> str:
    """docs/results.md for the runs ``run_names`` (in table order) of the benchmark folder ``out``;
    ``now`` (seconds since the epoch) stamps it."""
    settings = read_settings(out)
    runs = [load_run(out, n) for n in run_names]
    started = [r for r in runs if r["info"] is not None]
    recipes = {r["name"]: recipe_of(r["info"]) for r in started}
    lines = header_lines(out, runs, now)
    lines += setup_lines(settings, split_sizes(out / "data"), runs, recipes)
    lines += runs_lines(runs, settings["steps"])
    lines += per_class_lines(runs)
    lines += seed_spread_lines(runs)
    lines += reproduce_lines(out, settings, run_names)
    lines += config_lines(recipes)
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


def setup_lines(settings: dict, sizes: dict | None, runs: list[dict], recipes: dict[str, dict]) -> list[str]:
    """The Setup section: data, recipe (checked to be one), evaluation, machine, code."""
    started = [r for r in runs if r["info"] is not None]
    lines = ["## Setup", "", f"- Data: {data_text(settings, sizes)}."]
    if recipes:
        lines += recipe_lines(settings["steps"], sizes, started, recipes)
    else:
        lines.append(f"- Recipe: the defaults of `clfbev train --config tiny`; no run has started yet. "
                     f"Step budget: {settings['steps']} optimizer steps per run.")
    lines.append("- Evaluation: `clfbev eval` on `sim-val`, the devkit's `DetectionEval` restricted to the classes "
                 "with ground truth (with lidar points) in the split. The attribute is derived from the predicted "
                 "speed, not learned, so mAAE follows from the velocity.")
    lines.append(machine_line(runs))
    lines += [code_line(runs, started), ""]
    return lines


def data_text(settings: dict, sizes: dict | None) -> str:
    """The dataset's settings, and the split sizes as the tables have them."""
    data = (f"`simgen make`, urban preset: {settings['scenes']} scenes x {settings['samples_per_scene']} key frames "
            f"at {settings['resolution']}, seed {settings['data_seed']}, val fraction {settings['val_fraction']}")
    if sizes:
        data += "; " + ", ".join(f"`{k}` {plural(sc, 'scene')} ({plural(sa, 'sample')})" for k, (sc, sa) in sizes.items())
    return data


def recipe_lines(steps: int, sizes: dict | None, started: list[dict], recipes: dict[str, dict]) -> list[str]:
    """The recipe as run.json has it, the step budget, and the runs whose recipe differs."""
    first_name, first = next(iter(recipes.items()))
    tr = first["train"]
    samples = steps * tr["batch_size"] * (started[0]["info"].get("world_size") or 1)
    epochs = f", {samples / sizes['sim-train'][1]:.1f} epochs of `sim-train`" if sizes and sizes.get("sim-train") else ""
    shown = {k: v for k, v in tr.items() if k not in PER_VARIANT}
    per_variant = "; ".join(
        f"`{k}` " + ", ".join(f"{v} ({', '.join(vs)})" for v, vs in values_by_variant(started, k).items())
        for k in PER_VARIANT if k in tr)
    lines = [f"- Recipe: the defaults of `clfbev train --config {first['config_name']}` (model config "
             f"`{first['config_name']}`), the same for every run of a variant but the seed. From `run.json`: "
             f"`{describe_train(shown)}`; per variant: {per_variant or 'nothing'}.",
             f"- Step budget: {steps} optimizer steps per run ({samples} samples{epochs}). No validation while "
             "training (`--val-split ''`), so nothing is selected on `sim-val`: the evaluated checkpoint is "
             "`last.pt`, the weights after the last step."]
    differ = recipe_differences(started, recipes)
    if differ:
        lines.append(f"- **Not one recipe:** these runs differ from `{first_name}`: {', '.join(differ)}. "
                     "Their rows are not comparable; rerun them in a fresh OUT.")
    return lines


def recipe_differences(started: list[dict], recipes: dict[str, dict]) -> list[str]:
    """```name` (fields)`` of each run whose recipe differs: the per-variant fields against the first
    run of its variant, the rest against the first run."""
    first = next(iter(recipes.values()))
    variant_of = {r["name"]: r["variant"] for r in started}
    differ = []
    for name, rec in recipes.items():
        twin = recipes[next(n for n in recipes if variant_of[n] == variant_of[name])]
        keys = [k for k in {**first["train"], **rec["train"]}
                if rec["train"].get(k) != (twin if k in PER_VARIANT else first)["train"].get(k)]
        keys += ["model config"] if rec["config"] != first["config"] or rec["config_name"] != first["config_name"] else []
        if keys:
            differ.append(f"`{name}` ({', '.join(keys)})")
    return differ


def machine_line(runs: list[dict]) -> str:
    """The cores and torch threads the parts recorded, and the wall time in all."""
    threads = sorted({t for r in runs for t in r["threads"]})
    cores = sorted({c for r in runs for c in r["cores"]})
    total = sum((r["train_s"] or 0) + (r["eval_s"] or 0) for r in runs)
    if cores:   # benchmark.sh records the cores (nproc) and the torch threads (THREADS) of every part
        per_run = "; ".join(f"`{r['name']}` {', '.join(map(str, r['threads']))}" for r in runs if r["threads"])
        machine = (f"{', '.join(map(str, cores))} CPU cores (`nproc`); torch threads per run: "
                   f"{per_run} (fewer than the cores when runs shared them). ")
    else:       # parts written before the cores were recorded: THREADS was nproc then
        machine = f"{', '.join(map(str, threads)) or '?'} CPU cores (`nproc`), all used as torch threads. "
    return (f"- Machine: {machine}"
            "Wall time: training (every part of a resumed run, an interrupted part included, so steps "
            "recomputed after a resume count twice; only a part killed together with the script is missing) "
            f"and evaluation, in minutes; {total / 3600:.1f} h in all.")


def code_line(runs: list[dict], started: list[dict]) -> str:
    """The code version of each run (one when all agree) and the days the parts ended."""
    days = sorted({e[:10] for r in runs for e in r["ends"]})
    when = "" if not days else f", run on {days[0]}" if len(days) == 1 else f", run from {days[0]} to {days[-1]}"
    versions = {r["name"]: r["info"].get("code_version", "?") for r in started}
    if len(set(versions.values())) == 1:
        code = f"`{next(iter(versions.values()))}`"
    else:
        code = ", ".join(f"`{n}` `{v}`" for n, v in versions.items()) or "?"
    return f"- Code: {code} (`run.json`'s code_version){when}."


def runs_lines(runs: list[dict], steps: int) -> list[str]:
    """The main table: one row per run, pending ones included."""
    rows = []
    for r in runs:
        s = r["summary"]
        if s is not None:
            ran = r["info"]["train"]["max_steps"] if r["info"] else steps
            metrics = [num(s["mean_ap"], 4), num(s["nd_score"], 4), *(num(s["tp_errors"][k], 3) for k in TP_COLUMNS)]
        else:
            ran = f"{r['step']} of {steps}"
            state = ("pending (not started)" if r["info"] is None and not r["step"] else
                     "pending (evaluation)" if r["step"] >= steps else "pending")
            metrics = [state, *[""] * (1 + len(TP_COLUMNS))]
        train_s = minutes(r["train_s"]) + (f" ({r['train_parts']} parts)" if r["train_parts"] > 1 else "")
        rows.append([f"`{r['name']}`", r["variant"], str(r["seed"]), str(ran), *metrics, train_s, minutes(r["eval_s"])])
    header = ["run", "variant", "seed", "steps", "mAP", "NDS", *TP_COLUMNS.values(), "train min", "eval min"]
    return ["## Runs (sim-val)", "", *table(header, rows, right_from=2), ""]


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
    """Mean ± half the range of mAP and NDS over the seeds of each variant run with several."""
    by_variant: dict[str, list[dict]] = {}
    for r in runs:
        by_variant.setdefault(r["variant"], []).append(r)
    multi = {v: rs for v, rs in by_variant.items() if len(rs) > 1}
    if not multi:
        return []
    rows = []
    for v, rs in multi.items():
        seeds = ", ".join(str(r["seed"]) for r in rs)
        ok = [r["summary"] for r in rs if r["summary"] is not None]
        if len(ok) < len(rs):
            rows.append([v, seeds, f"pending ({len(ok)} of {len(rs)} seeds done)", "", "", ""])
            continue
        cells = []
        for key in ("mean_ap", "nd_score"):
            m, h = mean_half_range([s[key] for s in ok])
            cells.append(f"{m:.4f} ± {h:.4f}")
        cells += [f"{2 * mean_half_range([s[k] for s in ok])[1]:.4f}" for k in ("mean_ap", "nd_score")]
        rows.append([v, seeds, *cells])
    return ["## Seed spread", "",
            "Mean ± half the range over the seeds, and the spread (max - min): the part of a difference "
            "between variants that one seed's luck can explain.", "",
            *table(["variant", "seeds", "mAP", "NDS", "mAP spread", "NDS spread"], rows, right_from=2), ""]


def reproduce_lines(out: Path, settings: dict, run_names: list[str]) -> list[str]:
    """The commands: the benchmark's invocation with every knob spelled out, and what it runs."""
    steps = settings["steps"]
    knobs = (f"SCENES={settings['scenes']} SAMPLES={settings['samples_per_scene']} RES={settings['resolution']} "
             f"STEPS={steps}" + ("" if str(out) == "benchmark_out" else f" OUT={out}"))
    data_dir = f"{out}/data"
    return [
        "## Reproduce",
        "",
        "```bash",
        f"{knobs} bash scripts/benchmark.sh            # all runs; rerun to resume",
        f"{knobs} bash scripts/benchmark.sh lidar full # or some variants (all their seeds)",
        "# what it runs, per run V_sS (V the variant, S the seed):",
        f".venv/bin/simgen make --scenes {settings['scenes']} --samples-per-scene {settings['samples_per_scene']} "
        f"--resolution {settings['resolution']} --seed {settings['data_seed']} --val-fraction {settings['val_fraction']} "
        f"--out {data_dir} --quiet",
        f".venv/bin/clfbev train --data {data_dir} --config tiny --variant V --seed S --out {out}/V_sS "
        f"--max-steps {steps} --val-split '' --threads $(nproc)    # --resume when {out}/V_sS/last.pt exists",
        f".venv/bin/clfbev eval --data {data_dir} --ckpt {out}/V_sS/last.pt --split sim-val --out {out}/V_sS/eval",
        f".venv/bin/python scripts/results_table.py {out} --runs {' '.join(run_names)} --out docs/results.md",
        "```",
        "",
    ]


def config_lines(recipes: dict[str, dict]) -> list[str]:
    """The first run's model config, one line per field: the form of a `--config` YAML file."""
    if not recipes:
        return []
    first = next(iter(recipes.values()))
    return [f"<details><summary>The model config <code>{first['config_name']}</code> (from run.json)</summary>",
            "", "```yaml", *(f"{k}: {json.dumps(v)}" for k, v in first["config"].items()), "```", "",
            "</details>", ""]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="the benchmark's folder (benchmark_out)")
    ap.add_argument("--runs", nargs="+", required=True, help="run names, in table order (VARIANT_sSEED)")
    ap.add_argument("--out", dest="results", type=Path, default=Path("docs/results.md"), help="markdown to write")
    args = ap.parse_args(argv)
    return run_guarded(lambda: write_table(args.out, args.runs, args.results), prog="results_table")


def write_table(out: Path, run_names: list[str], results: Path) -> None:
    """Render the table of ``run_names`` in ``out`` and replace ``results`` with it."""
    bad = [n for n in run_names if not n.rpartition("_s")[2].isdigit()]
    if bad:
        raise ConfigError(f"--runs: run names must be VARIANT_sSEED, got {', '.join(bad)}")
    text = render(out, run_names)
    io.write_text(results, text)
    n_done = sum((out / n / "eval" / "metrics_summary.json").exists() for n in run_names)
    print(f"benchmark: table {results} ({n_done} of {len(run_names)} runs done)")


if __name__ == "__main__":
    sys.exit(main())
