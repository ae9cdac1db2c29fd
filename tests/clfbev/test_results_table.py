"""scripts/results_table.py and scripts/benchmark.sh without training anything.

The table is fed fake but well-formed run folders: the devkit's metrics_summary.json (same keys
as DetectionMetrics.serialize, NaN TP errors included), run.json as clfbev train writes it, and
the wall.jsonl parts that benchmark.sh appends. benchmark.sh is run from a copy in an empty
folder, so that what it creates (or must not create) is visible.
"""
from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import script_module

ROOT = Path(__file__).resolve().parents[2]
RUNS = ["lidar_s0", "full_s0", "concat_s0", "mcm_s0", "camera_s0", "lidar_s1", "full_s1"]
CLASSES = ["car", "bus", "pedestrian", "traffic_cone"]   # the devkit's order, restricted
TP = ("trans_err", "scale_err", "orient_err", "vel_err", "attr_err")


rt = script_module("results_table")


# ---------------------------------------------------------------- fake benchmark folders

TRAIN = {"train_split": "sim-train", "val_split": "", "version": "v1.0-sim", "seed": 0, "lr": 0.001,
         "weight_decay": 0.01, "warmup_frac": 0.05, "min_lr_ratio": 0.01, "grad_clip": 10.0, "batch_size": 2,
         "epochs": 20, "max_steps": 10, "augment": True, "modality_dropout": 0.0, "gt_paste": 8, "workers": 0,
         "ckpt_minutes": 10.0, "save_every_steps": 0}


def summary(mean_ap: float, nds: float, aps: dict, tp: dict) -> dict:
    """A metrics_summary.json as the devkit writes it (clfbev.run.evaluate)."""
    label_tp = {c: {k: (float("nan") if c == "traffic_cone" and k != "trans_err" else tp[k]) for k in TP}
                for c in aps}
    return {"label_aps": {c: {"0.5": ap, "1.0": ap, "2.0": ap, "4.0": ap} for c, ap in aps.items()},
            "mean_dist_aps": aps, "mean_ap": mean_ap, "label_tp_errors": label_tp, "tp_errors": tp,
            "tp_scores": {k: max(0.0, 1 - v) for k, v in tp.items()}, "nd_score": nds, "eval_time": 1.5,
            "cfg": {"class_range": {c: 50 for c in aps}, "dist_fcn": "center_distance"}, "meta": {"use_lidar": True}}


def tp_errors(base: float) -> dict:
    return {k: base + i / 10 for i, k in enumerate(TP)}


@pytest.fixture
def bench(tmp_path) -> Path:
    """A benchmark folder with its settings and a 3-scene dataset's tables (2 train, 1 val)."""
    out = tmp_path / "benchmark_out"
    tables = out / "data" / "v1.0-sim"
    tables.mkdir(parents=True)
    (out / "benchmark.json").write_text(json.dumps({"scenes": 3, "samples_per_scene": 3, "resolution": "352x198",
                                                    "data_seed": 1, "val_fraction": 0.2, "steps": 10}))
    scenes = [{"token": f"sc{i}", "name": f"scene-{i:04d}"} for i in range(3)]
    (tables / "scene.json").write_text(json.dumps(scenes))
    (tables / "sample.json").write_text(json.dumps([{"token": f"s{i}{j}", "scene_token": f"sc{i}"}
                                                    for i in range(3) for j in range(3)]))
    (tables / "splits.json").write_text(json.dumps({"sim-train": ["scene-0000", "scene-0001"],
                                                    "sim-val": ["scene-0002"]}))
    return out


def add_run(out: Path, name: str, metrics: dict | None = None, parts=((0, 10, 60),), eval_s: int | None = 30,
            train: dict | None = None, code: str = "abc1234", config: dict | None = None) -> Path:
    run = out / name
    run.mkdir(parents=True)
    variant, _, seed = name.rpartition("_s")
    (run / "run.json").write_text(json.dumps({
        "config": {"vfe_ch": 32, "image_size": [128, 352], **(config or {})}, "variant": variant,
        "train": {**TRAIN, "seed": int(seed), **(train or {})}, "world_size": 1, "code_version": code,
        "argv": ["/somewhere/clfbev", "train", "--config", "tiny", "--variant", variant], "resumed_at_step": 0}))
    lines = [json.dumps({"stage": "train", "from_step": a, "to_step": b, "seconds": s, "exit": 0, "threads": 2,
                         "end": "2026-12-01T10:00:00Z"}) for a, b, s in parts]
    if metrics is not None:
        (run / "eval").mkdir()
        (run / "eval" / "metrics_summary.json").write_text(json.dumps(metrics))   # NaN as the devkit writes it
        if eval_s is not None:
            lines.append(json.dumps({"stage": "eval", "seconds": eval_s, "threads": 2, "end": "2026-12-01T11:00:00Z"}))
    (run / "wall.jsonl").write_text("".join(ln + "\n" for ln in lines) + '{"stage": "tra')   # a torn last line
    return run


def section(md: str, title: str) -> str:
    return md.split(f"## {title}", 1)[1].split("\n## ", 1)[0]


def row(text: str, first: str) -> list[str]:
    """The cells of the table row whose first cell is ``first``."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[0] == first:
            return cells[1:]
    raise AssertionError(f"no row {first!r} in:\n{text}")


def render(bench: Path, runs=RUNS) -> str:
    out = bench.parent / "results.md"
    assert rt.main([str(bench), "--runs", *runs, "--out", str(out)]) == 0
    return out.read_text()


# ---------------------------------------------------------------- the table

def test_table_has_the_devkit_numbers_wall_time_and_setup(bench):
    aps = {"car": 0.5123, "bus": 0.0, "pedestrian": 0.25, "traffic_cone": 0.0449}
    add_run(bench, "lidar_s0", summary(0.2018, 0.3107, aps, tp_errors(0.4)), parts=((0, 4, 100), (4, 10, 140)))
    md = render(bench)

    cells = row(section(md, "Runs"), "`lidar_s0`")
    assert cells[:5] == ["lidar", "0", "10", "0.2018", "0.3107"]
    assert cells[5:10] == ["0.400", "0.500", "0.600", "0.700", "0.800"]          # mATE .. mAAE
    assert cells[10:] == ["4.0 (2 parts)", "0.5"]                                 # 240 s train, 30 s eval
    per_class = section(md, "Per-class AP")
    assert row(per_class, "run") == CLASSES                                       # the devkit's evaluated classes
    assert row(per_class, "`lidar_s0`") == ["0.512", "0.000", "0.250", "0.045"]
    assert "truck, trailer, construction_vehicle, motorcycle, bicycle, barrier" in per_class
    setup = section(md, "Setup")
    assert "3 scenes x 3 key frames at 352x198, seed 1" in setup
    assert "`sim-train` 2 scenes (6 samples), `sim-val` 1 scene (3 samples)" in setup
    assert "--config tiny" in setup and "lr=0.001" in setup and "per variant: `gt_paste` 8 (lidar)" in setup
    assert "seed=" not in setup
    assert "10 optimizer steps per run (20 samples, 3.3 epochs" in setup
    assert "`abc1234`" in setup and "2 CPU cores (`nproc`), all used" in setup       # parts without "cores"
    assert "1 of 7 runs done" in md
    reproduce = section(md, "Reproduce")
    assert "SCENES=3 SAMPLES=3 RES=352x198 STEPS=10" in reproduce and "--max-steps 10 --val-split ''" in reproduce
    assert "/somewhere" not in md                                                # no recorded absolute path


def test_pending_runs_are_listed_with_their_progress(bench):
    add_run(bench, "lidar_s0", summary(0.2, 0.3, {"car": 0.4}, tp_errors(0.5)))
    add_run(bench, "full_s0", parts=((0, 3, 50), (3, 7, 60)))                    # interrupted at step 7
    add_run(bench, "concat_s0", parts=((0, 10, 70),))                             # trained, not evaluated
    md = render(bench)
    runs = section(md, "Runs")
    assert row(runs, "`full_s0`")[:4] == ["full", "0", "7 of 10", "pending"]
    assert row(runs, "`full_s0`")[-2:] == ["1.8 (2 parts)", ""]
    assert row(runs, "`concat_s0`")[2:4] == ["10 of 10", "pending (evaluation)"]
    for name in ("mcm_s0", "camera_s0", "lidar_s1", "full_s1"):
        assert row(runs, f"`{name}`")[2:4] == ["0 of 10", "pending (not started)"]
    assert row(section(md, "Per-class AP"), "`mcm_s0`")[0] == "pending"
    assert "1 of 7 runs done" in md


def test_seed_spread_is_mean_half_range_and_range(bench):
    add_run(bench, "lidar_s0", summary(0.10, 0.20, {"car": 0.3}, tp_errors(0.5)))
    add_run(bench, "lidar_s1", summary(0.14, 0.23, {"car": 0.35}, tp_errors(0.5)))
    add_run(bench, "full_s0", summary(0.09, 0.19, {"car": 0.3}, tp_errors(0.5)))
    spread = section(render(bench), "Seed spread")
    assert row(spread, "lidar") == ["0, 1", "0.1200 ± 0.0200", "0.2150 ± 0.0150", "0.0400", "0.0300"]
    assert row(spread, "full")[:2] == ["0, 1", "pending (1 of 2 seeds done)"]
    assert "concat" not in spread                                                # one seed: no spread


def test_the_cores_and_each_runs_threads(bench):
    add_run(bench, "lidar_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)))
    add_run(bench, "full_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)))
    for name, threads in (("lidar_s0", 1), ("full_s0", 2)):
        (bench / name / "wall.jsonl").write_text(json.dumps(
            {"stage": "train", "from_step": 0, "to_step": 10, "seconds": 60, "exit": 0, "threads": threads,
             "cores": 2, "end": "2026-12-01T10:00:00Z"}) + "\n")
    setup = section(render(bench), "Setup")
    assert "2 CPU cores (`nproc`); torch threads per run: `lidar_s0` 1; `full_s0` 2" in setup


def test_a_run_with_another_recipe_is_flagged(bench):
    add_run(bench, "lidar_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)))
    add_run(bench, "full_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)), train={"lr": 0.002}, code="def5678")
    # Bookkeeping, and the epoch count that --max-steps overrides, do not change a result.
    add_run(bench, "concat_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)),
            train={"ckpt_minutes": 3.0, "save_every_steps": 5, "workers": 2, "epochs": 12})
    add_run(bench, "mcm_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)), train={"gt_paste_fade": 0.2})
    # The recipe pastes nothing for the camera variant: that is one recipe, per variant. But the
    # second seed of a variant must paste as its first.
    add_run(bench, "camera_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)), train={"gt_paste": 0})
    add_run(bench, "lidar_s1", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)), train={"gt_paste": 0, "seed": 1})
    setup = section(render(bench), "Setup")
    flagged = setup.split("**Not one recipe:**")[1].split("\n")[0]
    assert "`full_s0` (lr)" in flagged and "`mcm_s0` (gt_paste_fade)" in flagged   # a field only one run has
    assert "concat_s0" not in flagged and "lidar_s0`:" in flagged
    assert "camera_s0" not in flagged and "`lidar_s1` (gt_paste)" in flagged
    assert "per variant: `gt_paste` 8 (lidar, full, concat, mcm), 0 (camera, lidar)" in setup
    assert "`full_s0` `def5678`" in setup


def test_a_field_a_run_predates_counts_at_its_default(bench):
    """A run recorded before a config field existed ran with the field's default: a later run
    with that default is the same recipe, one with another value is not."""
    add_run(bench, "lidar_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)))
    add_run(bench, "lidar_s1", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)),
            config={"velocity_tower": 0, "loss": {"semantic": 0.0}})
    assert "Not one recipe" not in section(render(bench), "Setup")
    add_run(bench, "full_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)), config={"velocity_tower": 32})
    flagged = section(render(bench), "Setup").split("**Not one recipe:**")[1].split("\n")[0]
    assert "`full_s0` (model config)" in flagged and "lidar_s1" not in flagged


def test_the_write_is_atomic(bench, monkeypatch):
    add_run(bench, "lidar_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)))
    out = bench.parent / "docs" / "results.md"
    out.parent.mkdir()
    out.write_text("old table\n")

    def crash(src, dst):
        raise OSError("disk full")
    monkeypatch.setattr(rt.io.os, "replace", crash)
    with pytest.raises(OSError):
        rt.main([str(bench), "--runs", *RUNS, "--out", str(out)])
    assert out.read_text() == "old table\n"                                     # the old file, whole
    assert sorted(p.name for p in out.parent.iterdir()) == ["results.md"]       # no temporary left
    monkeypatch.undo()
    assert rt.main([str(bench), "--runs", *RUNS, "--out", str(out)]) == 0
    assert out.read_text().startswith("# Results") and sorted(p.name for p in out.parent.iterdir()) == ["results.md"]


def test_a_missing_benchmark_is_one_line(tmp_path, capsys):
    assert rt.main([str(tmp_path / "nothing"), "--runs", *RUNS, "--out", str(tmp_path / "r.md")]) == 2
    assert "benchmark.json is missing" in capsys.readouterr().err and not (tmp_path / "r.md").exists()


def test_the_bookkeeping_fields_are_the_train_configs():
    """One list of the fields that do not change a result, shared with a resume."""
    from clfbev.run.train_config import BOOKKEEPING
    assert rt.BOOKKEEPING is BOOKKEEPING
    assert {"ckpt_minutes", "save_every_steps", "workers"} <= BOOKKEEPING


def test_the_detection_classes_are_the_devkits():
    from nuscenes.eval.detection.constants import DETECTION_NAMES
    assert list(rt.DETECTION_CLASSES) == list(DETECTION_NAMES)


@pytest.mark.parametrize("file, text, expected", [
    ("benchmark.json", "{\"scenes\": 3,", "benchmark.json: not valid JSON"),
    ("benchmark.json", "{\"scenes\": 3}", "benchmark.json: lacks the field 'samples_per_scene'"),
    ("lidar_s0/run.json", "\x00\xff junk", "run.json: not valid JSON"),
    ("lidar_s0/run.json", "{\"config\": {}, \"train\": {\"max_steps\": 10}}", "run.json: lacks the field 'train.batch_size'"),
    ("lidar_s0/eval/metrics_summary.json", "{\"mean_ap\": 0.1}", "metrics_summary.json: lacks the field 'nd_score'"),
    ("lidar_s0/eval/metrics_summary.json", "[1, 2]", "metrics_summary.json: lacks the field 'mean_ap'"),
    ("lidar_s0/wall.jsonl", "{\"stage\": \"train\", \"seconds\": 3}\n", "wall.jsonl: line 1 lacks the field 'to_step'"),
    ("lidar_s0/wall.jsonl", "[]\n", "wall.jsonl: line 1 is not a JSON object"),
    ("data/v1.0-sim/sample.json", "[{\"token\": \"s00\"}]", "do not fit together"),
])
def test_a_junk_file_is_one_line_naming_it(bench, capsys, file, text, expected):
    add_run(bench, "lidar_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)))
    (bench / file).write_bytes(text.encode("latin-1"))
    out = bench.parent / "r.md"
    assert rt.main([str(bench), "--runs", *RUNS, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and expected in err and "Traceback" not in err
    assert not out.exists()


def test_a_bad_run_name_is_one_line(bench, capsys):
    assert rt.main([str(bench), "--runs", "lidar_s0", "full", "--out", str(bench.parent / "r.md")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "VARIANT_sSEED, got full" in err


# ---------------------------------------------------------------- benchmark.sh

def bench_sh(tmp_path: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    """Run a copy of benchmark.sh from an empty repository folder (it works from its parent),
    with ``env`` added to the environment."""
    repo = tmp_path / "repo"
    if not repo.exists():
        (repo / "scripts").mkdir(parents=True)
        shutil.copy(ROOT / "scripts" / "benchmark.sh", repo / "scripts" / "benchmark.sh")
    return subprocess.run(["bash", str(repo / "scripts" / "benchmark.sh"), *args], capture_output=True, text=True,
                          timeout=30, env={**os.environ, **env})


def test_an_unknown_variant_is_one_line_exit_2_and_creates_nothing(tmp_path):
    proc = bench_sh(tmp_path, "lidar", "fulll")
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "'fulll'" in lines[0] and "lidar camera concat mcm full" in lines[0]
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == \
        ["repo", "repo/scripts", "repo/scripts/benchmark.sh"]


def test_the_runs_their_order_and_the_variants_clfbev_knows(tmp_path):
    source = (ROOT / "clfbev" / "config.py").read_text()      # parsed, not imported: no torch here
    known = next(ast.literal_eval(n.value) for n in ast.parse(source).body
                 if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "VARIANTS")
    every = bench_sh(tmp_path, "--list", *known)
    assert every.returncode == 0, every.stderr
    assert every.stdout.split() == [w for r in RUNS for w in (r, "pending")]
    assert bench_sh(tmp_path, "--list").stdout == every.stdout                  # the default: all five
    some = bench_sh(tmp_path, "--list", "full", "lidar").stdout.split()[::2]
    assert some == ["lidar_s0", "full_s0", "lidar_s1", "full_s1"]               # the default order kept
    runs = bench_sh(tmp_path, "--list", "full_s1", "camera").stdout.split()[::2]
    assert runs == ["camera_s0", "full_s1"]                                     # runs by name, too
    assert sorted(p.name for p in (tmp_path / "repo").iterdir()) == ["scripts"]


def test_a_recorded_run_counts_only_with_the_same_settings(tmp_path):
    """docs/results/RUN holds an evaluated run's record: --list calls it recorded when its
    benchmark.json is this benchmark's settings (and its data_id OUT's data, once made),
    pending otherwise; the OUT folder wins."""
    bench_sh(tmp_path, "--list")                                    # makes the repo copy
    repo = tmp_path / "repo"
    settings = ('{"scenes": 40, "samples_per_scene": 20, "resolution": "704x396", "data_seed": 1, '
                '"val_fraction": 0.2, "steps": 1200}')
    for name, written in (("lidar_s0", settings), ("full_s0", settings.replace("1200", "600"))):
        rec = repo / "docs" / "results" / name
        rec.mkdir(parents=True)
        (rec / "benchmark.json").write_text(written + "\n")
        (rec / "metrics_summary.json").write_text("{}")
    state = dict(zip(*[iter(bench_sh(tmp_path, "--list").stdout.split())] * 2))
    assert state["lidar_s0"] == "recorded" and state["full_s0"] == "pending" and state["lidar_s1"] == "pending"
    # Once OUT's data exists, its identity must match the record's too: another layout's
    # record is not restored.
    (repo / "docs" / "results" / "lidar_s0" / "data_id").write_text("a1\n")
    (repo / "benchmark_out").mkdir()
    for data_id, expected in (("a1", "recorded"), ("b2", "pending")):
        (repo / "benchmark_out" / "data_id").write_text(data_id + "\n")
        assert bench_sh(tmp_path, "--list", "lidar_s0").stdout.split() == ["lidar_s0", expected]
    (repo / "benchmark_out" / "lidar_s0").mkdir()
    (repo / "benchmark_out" / "lidar_s0" / "last.pt").write_bytes(b"")
    assert "lidar_s0 started" in bench_sh(tmp_path, "--list", "lidar_s0").stdout
    # A smoke test's records go beside its own RESULTS, not into docs/results.
    smoke = bench_sh(tmp_path, "--list", "lidar_s0", RESULTS=str(tmp_path / "smoke" / "results.md"),
                     OUT=str(tmp_path / "smoke_out"))
    assert smoke.stdout.split() == ["lidar_s0", "pending"]


def test_the_data_identity_follows_the_layout_not_the_sensor_counts(tiny_dataset, tmp_path):
    """scripts/data_identity.py: the same for a copy and for other num_lidar_pts / visibility;
    another for an annotation moved by 1 cm or for other splits."""
    mod = script_module("data_identity")
    copy = tmp_path / "data"
    shutil.copytree(tiny_dataset / "v1.0-sim", copy / "v1.0-sim")
    table = copy / "v1.0-sim" / "sample_annotation.json"
    original = json.loads(table.read_text())
    base = mod.data_identity(tiny_dataset)
    assert mod.data_identity(copy) == base

    def identity_with(edit) -> str:
        anns = json.loads(json.dumps(original))
        edit(anns[0])
        table.write_text(json.dumps(anns))
        return mod.data_identity(copy)

    assert identity_with(lambda a: a.update(num_lidar_pts=a["num_lidar_pts"] + 7, visibility_token="1")) == base
    assert identity_with(lambda a: a["translation"].__setitem__(0, a["translation"][0] + 0.01)) != base
    table.write_text(json.dumps(original))
    splits = copy / "v1.0-sim" / "splits.json"
    s = json.loads(splits.read_text())
    s["sim-train"], s["sim-val"] = s["sim-val"], s["sim-train"]
    splits.write_text(json.dumps(s))
    assert mod.data_identity(copy) != base


@pytest.mark.parametrize("table, text, expected", [
    ("category", None, "category.json is missing"),
    ("instance", "[{\"token\": ", "instance.json: not valid JSON"),
    ("sample_annotation", "[{\"instance_token\": \"x\"}]", "record 0 lacks the field 'translation'"),
    ("sample_annotation", "{}", "expected a list of records"),
])
def test_a_junk_table_is_one_line_for_the_data_identity(tmp_path, capsys, table, text, expected):
    mod = script_module("data_identity")
    tables = tmp_path / "data" / "v1.0-sim"
    tables.mkdir(parents=True)
    for name, records in (("category", [{"token": "c", "name": "car"}]), ("instance", [{"token": "i", "category_token": "c"}]),
                          ("sample_annotation", []), ("splits", {"sim-train": []})):
        (tables / f"{name}.json").write_text(json.dumps(records))
    assert mod.main([str(tmp_path / "data")]) == 0
    if text is None:
        (tables / f"{table}.json").unlink()
    else:
        (tables / f"{table}.json").write_text(text)
    assert mod.main([str(tmp_path / "data")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and expected in err and "Traceback" not in err
