"""scripts/results_table.py and scripts/benchmark.sh without training anything.

The table is fed fake but well-formed run folders: the devkit's metrics_summary.json (same keys
as DetectionMetrics.serialize, NaN TP errors included), run.json as clfbev train writes it, and
the cpu.json, code_id and staged.json that benchmark.sh writes. benchmark.sh is run from a copy
in an empty folder, so that what it creates (or must not create) is visible.
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
RUNS = ["lidar_s0", "full_s0", "concat_s0", "mcm_s0", "camera_s0", "fullmd_s0", "lidar_s1", "full_s1"]
CLASSES = ["car", "bus", "pedestrian", "traffic_cone"]   # the devkit's order, restricted
TP = ("trans_err", "scale_err", "orient_err", "vel_err", "attr_err")
SETTINGS = {"scenes": 3, "samples_per_scene": 3, "resolution": "352x198", "data_seed": 1, "val_fraction": 0.2,
            "camera_steps": 30, "lidar_steps": 10, "fusion_steps": 5, "lidar_alone_steps": 30, "camera_alone_steps": 90}


rt = script_module("results_table")


# ---------------------------------------------------------------- fake benchmark folders

TRAIN = {"train_split": "sim-train", "val_split": "", "version": "v1.0-sim", "seed": 0, "lr": 0.002,
         "batch_size": 2, "epochs": 8, "max_steps": 10}


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
    (out / "benchmark.json").write_text(json.dumps(SETTINGS))
    (out / "data_id").write_text("d4t4\n")
    scenes = [{"token": f"sc{i}", "name": f"scene-{i:04d}"} for i in range(3)]
    (tables / "scene.json").write_text(json.dumps(scenes))
    (tables / "sample.json").write_text(json.dumps([{"token": f"s{i}{j}", "scene_token": f"sc{i}"}
                                                    for i in range(3) for j in range(3)]))
    (tables / "splits.json").write_text(json.dumps({"sim-train": ["scene-0000", "scene-0001"],
                                                    "sim-val": ["scene-0002"]}))
    return out


def add_run(out: Path, name: str, metrics: dict | None = None, cpu: dict | None = None, code_id: str = "c0de",
            commit: str = "abc1234") -> Path:
    """A run folder as benchmark.sh leaves it (evaluated when ``metrics`` is given)."""
    run = out / name
    run.mkdir(parents=True)
    kind, _, seed = name.rpartition("_s")
    (run / "run.json").write_text(json.dumps({
        "config": {"vfe_ch": 32, "image_size": [128, 352]}, "variant": rt.KINDS[kind],
        "train": {**TRAIN, "seed": int(seed)}, "world_size": 1, "code_version": commit,
        "argv": ["/somewhere/clfbev", "train", "--config", "tiny"], "resumed_at_step": 0}))
    if metrics is not None:
        (run / "eval").mkdir()
        (run / "eval" / "metrics_summary.json").write_text(json.dumps(metrics))   # NaN as the devkit writes it
        cpu = cpu or {name: 3600.0}
        (run / "cpu.json").write_text(json.dumps({"stages": cpu, "cpu_s": sum(cpu.values())}))
        (run / "code_id").write_text(code_id + "\n")
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

def test_table_has_the_devkit_numbers_cpu_hours_and_setup(bench):
    aps = {"car": 0.5123, "bus": 0.0, "pedestrian": 0.25, "traffic_cone": 0.0449}
    add_run(bench, "lidar_s0", summary(0.2018, 0.3107, aps, tp_errors(0.4)), cpu={"lidar_s0": 4000, "eval_lidar_s0": 500})
    add_run(bench, "full_s0", summary(0.25, 0.35, aps, tp_errors(0.4)),
            cpu={"cache": 300, "camstage_s0": 1200, "lidarstage_s0": 1500, "full_s0": 1200, "eval_full_s0": 300})
    md = render(bench)

    runs = section(md, "Runs")
    cells = row(runs, "`lidar_s0`")
    assert cells[:4] == ["lidar", "0", "30 steps", "1.25"]                     # 4500 CPU-s
    assert cells[4:6] == ["0.2018", "0.3107"]
    assert cells[6:] == ["0.400", "0.500", "0.600", "0.700", "0.800"]          # mATE .. mAAE
    assert row(runs, "`full_s0`")[2:4] == ["staged: 30 + 10 + 5 steps", "1.25"]
    per_class = section(md, "Per-class AP")
    assert row(per_class, "run") == CLASSES                                       # the devkit's evaluated classes
    assert row(per_class, "`lidar_s0`") == ["0.512", "0.000", "0.250", "0.045"]
    assert "truck, trailer, construction_vehicle, motorcycle, bicycle, barrier" in per_class
    setup = section(md, "Setup")
    assert "3 scenes x 3 key frames at 352x198, seed 1" in setup and "identity `d4t4`" in setup
    assert "`sim-train` 2 scenes (6 samples), `sim-val` 1 scene (3 samples)" in setup
    assert "`lidar` alone 30 steps" in setup and "`camera` alone 90 steps" in setup
    assert "2.5 CPU-hours over the done runs" in setup
    assert "identity `c0de`" in setup and "`abc1234`" in setup and "Not one code version" not in setup
    assert "2 of 8 runs done" in md
    assert "/somewhere" not in md                                                # no recorded absolute path
    (bench / "scored.json").write_text(json.dumps({"sim-train": {"car": 120, "pedestrian": 80},
                                                   "sim-val": {"car": 30, "pedestrian": 20}}))
    assert "`sim-train` car 120, pedestrian 80; `sim-val` car 30, pedestrian 20." in section(render(bench), "Setup")


def test_the_scored_boxes_are_the_devkits(tiny_dataset):
    """scripts/scored_boxes.py counts, per class, the GT boxes the devkit's DetectionEval keeps."""
    from nuscenes import NuScenes
    from nuscenes.eval.common.config import config_factory
    from nuscenes.eval.common.loaders import add_center_dist, filter_eval_boxes

    counts = script_module("scored_boxes").scored_boxes(tiny_dataset)
    nusc = NuScenes("v1.0-sim", str(tiny_dataset), verbose=False)
    cfg = config_factory("detection_cvpr_2019")
    for split in ("sim-train", "sim-val"):
        splits = json.loads((tiny_dataset / "v1.0-sim" / "splits.json").read_text())
        scenes = {s["token"] for s in nusc.scene if s["name"] in splits[split]}
        gt = add_center_dist(nusc, _gt(nusc, scenes))
        kept = filter_eval_boxes(nusc, gt, cfg.class_range)
        expected = {}
        for box in kept.all:
            expected[box.detection_name] = expected.get(box.detection_name, 0) + 1
        assert counts[split] == {c: expected[c] for c in cfg.class_range if c in expected} and sum(expected.values()) > 5


def _gt(nusc, scenes):
    """The devkit's EvalBoxes of the GT of the samples of ``scenes``, as its load_gt builds them
    (which accepts only the official split names)."""
    from nuscenes.eval.common.data_classes import EvalBoxes
    from nuscenes.eval.detection.data_classes import DetectionBox
    from nuscenes.eval.detection.utils import category_to_detection_name
    boxes = EvalBoxes()
    for sample in nusc.sample:
        if sample["scene_token"] not in scenes:
            continue
        found = []
        for token in sample["anns"]:
            a = nusc.get("sample_annotation", token)
            name = category_to_detection_name(a["category_name"])
            if name is None:
                continue
            found.append(DetectionBox(sample_token=sample["token"], translation=a["translation"], size=a["size"],
                                      rotation=a["rotation"], velocity=nusc.box_velocity(token)[:2],
                                      num_pts=a["num_lidar_pts"] + a["num_radar_pts"], detection_name=name,
                                      detection_score=-1.0, attribute_name=""))
        boxes.add_boxes(sample["token"], found)
    return boxes


def test_pending_runs_are_listed_with_their_stages_progress(bench):
    add_run(bench, "lidar_s0", summary(0.2, 0.3, {"car": 0.4}, tp_errors(0.5)))
    add_run(bench, "full_s0")                                                     # trained, not evaluated
    (bench / "staged.json").write_text(json.dumps({"format": "clfbev-staged-v1", "stages": {
        "cache": {"done": True}, "camstage_s0": {"done": True}, "lidarstage_s0": {"done": False}}}))
    md = render(bench)
    runs = section(md, "Runs")
    assert row(runs, "`full_s0`")[3] == ("pending: cache done, camstage_s0 done, lidarstage_s0 started, "
                                         "full_s0 not started")
    assert row(runs, "`camera_s0`")[3] == "pending: cache done, camera_s0 not started"
    assert row(runs, "`lidar_s1`")[3] == "pending: lidar_s1 not started"
    assert row(section(md, "Per-class AP"), "`mcm_s0`")[0] == "pending"
    assert "1 of 8 runs done" in md


def test_seed_spread_is_mean_half_range_and_range(bench):
    add_run(bench, "lidar_s0", summary(0.10, 0.20, {"car": 0.3}, tp_errors(0.5)))
    add_run(bench, "lidar_s1", summary(0.14, 0.23, {"car": 0.35}, tp_errors(0.5)))
    add_run(bench, "full_s0", summary(0.09, 0.19, {"car": 0.3}, tp_errors(0.5)))
    add_run(bench, "fullmd_s0", summary(0.09, 0.19, {"car": 0.3}, tp_errors(0.5)))
    spread = section(render(bench), "Seed spread")
    assert row(spread, "lidar") == ["0, 1", "0.1200 ± 0.0200", "0.2150 ± 0.0150", "0.0400", "0.0300"]
    assert row(spread, "full")[:2] == ["0, 1", "pending (1 of 2 seeds done)"]
    assert "concat" not in spread and "fullmd" not in spread                     # one seed: no spread


def test_a_run_of_other_code_is_marked(bench):
    add_run(bench, "lidar_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)))
    add_run(bench, "full_s0", summary(0.1, 0.2, {"car": 0.3}, tp_errors(0.5)), code_id="0ther", commit="def5678")
    md = render(bench)
    assert row(section(md, "Runs"), "`full_s0` \u2020")[0] == "full"
    assert row(section(md, "Runs"), "`lidar_s0`")[0] == "lidar"
    setup = section(md, "Setup")
    assert "**Not one code version:** `full_s0`" in setup and "`abc1234`, `def5678`" in setup


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
    ("lidar_s0/cpu.json", "{\"stages\": {}}", "cpu.json: lacks the field 'cpu_s'"),
    ("staged.json", "{}", "staged.json: lacks the field 'stages'"),
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
    for bad in ("full", "fulll_s0"):
        assert rt.main([str(bench), "--runs", "lidar_s0", bad, "--out", str(bench.parent / "r.md")]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and f"got {bad}" in err


# ---------------------------------------------------------------- benchmark.sh

def bench_sh(tmp_path: Path, *args: str, git: bool = False, **env: str) -> subprocess.CompletedProcess:
    """Run a copy of benchmark.sh from an empty repository folder (it works from its parent),
    with ``env`` added to the environment; with ``git``, the folder is a git repository whose
    clfbev/ and simgen/ hold one file each."""
    repo = tmp_path / "repo"
    if not repo.exists():
        (repo / "scripts").mkdir(parents=True)
        shutil.copy(ROOT / "scripts" / "benchmark.sh", repo / "scripts" / "benchmark.sh")
        if git:
            for package in ("clfbev", "simgen"):
                (repo / package).mkdir()
                (repo / package / "__init__.py").write_text(f"# {package}\n")
            for cmd in (["init", "-q"], ["add", "clfbev", "simgen", "scripts"],
                        ["-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "code"]):
                subprocess.run(["git", *cmd], cwd=repo, check=True, capture_output=True)
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
    assert some == ["lidar_s0", "full_s0", "fullmd_s0", "lidar_s1", "full_s1"]  # the default order kept
    runs = bench_sh(tmp_path, "--list", "full_s1", "camera").stdout.split()[::2]
    assert runs == ["camera_s0", "full_s1"]                                     # runs by name, too
    assert sorted(p.name for p in (tmp_path / "repo").iterdir()) == ["scripts"]
    assert set(rt.KINDS) == {r.rpartition("_s")[0] for r in RUNS}               # the table knows every run


def test_a_recorded_run_counts_only_with_the_same_settings_data_and_code(tmp_path):
    """docs/results/RUN holds an evaluated run's record: --list calls it recorded when its
    benchmark.json is this benchmark's settings, its code_id this checkout's code (and its data_id
    OUT's data, once made), pending otherwise; the OUT folder wins."""
    bench_sh(tmp_path, "--list", git=True)                          # makes the repo copy
    repo = tmp_path / "repo"
    trees = subprocess.run(["git", "rev-parse", "HEAD:clfbev", "HEAD:simgen"], cwd=repo, capture_output=True,
                           text=True, check=True).stdout
    code = subprocess.run(["sha1sum"], input=trees, capture_output=True, text=True).stdout[:12]
    settings = ('{"scenes": 40, "samples_per_scene": 20, "resolution": "704x396", "data_seed": 1, '
                '"val_fraction": 0.2, "camera_steps": 3600, "lidar_steps": 1200, "fusion_steps": 600, '
                '"lidar_alone_steps": 3600, "camera_alone_steps": 12000}')
    for name, written, code_id in (("lidar_s0", settings, code), ("full_s0", settings.replace("600,", "700,"), code),
                                   ("camera_s0", settings, "0ther")):
        rec = repo / "docs" / "results" / name
        rec.mkdir(parents=True)
        (rec / "benchmark.json").write_text(written + "\n")
        (rec / "metrics_summary.json").write_text("{}")
        (rec / "code_id").write_text(code_id + "\n")
    state = dict(zip(*[iter(bench_sh(tmp_path, "--list").stdout.split())] * 2))
    assert state["lidar_s0"] == "recorded" and state["lidar_s1"] == "pending"
    assert state["full_s0"] == "pending" and state["camera_s0"] == "pending"    # other settings, other code
    # An uncommitted change to the code makes it other code.
    (repo / "simgen" / "__init__.py").write_text("# changed\n")
    assert bench_sh(tmp_path, "--list", "lidar_s0").stdout.split() == ["lidar_s0", "pending"]
    subprocess.run(["git", "checkout", "-q", "simgen"], cwd=repo, check=True)
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
