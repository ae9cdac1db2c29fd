"""scripts/staged.sh, the staged recipe in one command, and scripts/staged_record.py, its record:
a done stage is skipped, an interrupted one resumed, other settings refused, each part's CPU
time recorded; and (slow) a recipe killed with SIGKILL inside each of its four stages ends with
the fused weights of an uninterrupted one, bit for bit.

The recipe runs the micro model of tests/conftest.py on the tiny dataset, with a seeded micro
encoder saved as the encoder checkpoint its frozen image features come from.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from clfbev.camera_encoder import CameraEncoder
from clfbev.config_file import load_config
from clfbev.run.checkpoint import load_checkpoint
from clfbev.run.experts_file import load_predictor
from clfbev.run import train as train_module
from clfbev.run.image_init import save_encoder
from clfbev.run.train_config import TrainConfig

from conftest import script_module

pytestmark = pytest.mark.usefixtures("one_thread")

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "staged.sh"
RECIPE_STAGES = ("cache", "camera", "lidar", "fusion")


@pytest.fixture(scope="module")
def encoder_ckpt(tmp_path_factory, micro) -> Path:
    cfg = load_config(micro)
    torch.manual_seed(3)
    path = tmp_path_factory.mktemp("enc") / "encoder.pt"
    save_encoder(path, CameraEncoder.from_config(cfg), cfg, ["test"], {}, 0, "test")
    return path


def recipe_env(data, micro, encoder, out, steps: int, **more) -> dict:
    """The environment of a micro recipe of ``steps`` steps per training stage into ``out``."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "PY": sys.executable, "DATA": str(data), "OUT": str(out),
            "CONFIG": str(micro), "IMAGE_INIT": str(encoder), "THREADS": "1", "SEED": "1",
            "CAMERA_STEPS": str(steps), "LIDAR_STEPS": str(steps), "FUSION_STEPS": str(steps),
            "TRAIN_ARGS": "--batch-size 1 --precise-bn-batches 2 --save-every-steps 1 --quiet",
            "DROP_LIDAR": "0.25", "DROP_CAMERA": "0.3333", **more}      # the dropout's draws resume too


def staged(env: dict, *args) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=900)


def start_staged(env: dict, *args) -> subprocess.Popen:
    """The recipe in a process group of its own, so that SIGKILL reaches every process of it."""
    return subprocess.Popen(["bash", str(SCRIPT), *args], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)


def kill_when(proc: subprocess.Popen, ready, what: str) -> None:
    """SIGKILL ``proc``'s process group as soon as ``ready()`` holds (polled)."""
    deadline = time.monotonic() + 600
    while not ready():
        assert proc.poll() is None, f"the recipe ended before {what}"
        assert time.monotonic() < deadline, f"no {what} within 600 s"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def step_of(run: Path) -> int:
    """The step of RUN/last.pt; -1 without one."""
    return load_checkpoint(run / "last.pt")["step"] if (run / "last.pt").exists() else -1


def record(out: Path) -> dict:
    return json.loads((out / "staged.json").read_text())


def test_a_done_stage_is_skipped_an_interrupted_one_resumed_other_settings_refused(tiny_dataset, micro,
                                                                                  encoder_ckpt, tmp_path):
    out = tmp_path / "out"
    env = recipe_env(tiny_dataset, micro, encoder_ckpt, out, 6)
    proc = start_staged(env, "lidar")
    kill_when(proc, lambda: step_of(out / "lidar") >= 2, "a lidar checkpoint at step 2")
    killed_at = step_of(out / "lidar")
    assert 2 <= killed_at < 6, f"the stage was not interrupted (checkpoint at step {killed_at})"
    assert record(out)["stages"]["lidar"]["done"] is False

    again = staged(env, "lidar")
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"staged: lidar resumes from {out}/lidar/last.pt" in again.stdout
    assert step_of(out / "lidar") == 6
    steps = [json.loads(line)["step"] for line in (out / "lidar" / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6]                # continued, not restarted
    lidar = record(out)["stages"]["lidar"]
    assert lidar["done"] is True and [p["ended"] for p in lidar["parts"]] == [False, True]
    assert lidar["parts"][1]["exit"] == 0 and lidar["parts"][1]["user_s"] > 0
    assert lidar["settings"].startswith("data:") and "--max-steps 6 --out" in lidar["settings"]

    before = (out / "lidar" / "last.pt").stat().st_mtime_ns
    third = staged(env, "lidar")
    assert third.returncode == 0 and "staged: lidar done earlier (skipped)" in third.stdout
    assert (out / "lidar" / "last.pt").stat().st_mtime_ns == before
    assert record(out)["stages"]["lidar"]["parts"] == lidar["parts"]
    listed = staged(env, "--list")
    assert listed.stdout.splitlines()[:4] == ["cache pending", "camera pending", "lidar done", "fusion pending"]

    # Other settings for a started stage: one line, exit 2, nothing run.
    changed = staged({**env, "LIDAR_STEPS": "7"}, "lidar")
    assert changed.returncode == 2 and changed.stderr.count("\n") == 1, changed.stderr
    assert "the lidar stage in" in changed.stderr and "(--max-steps 6 -> 7)" in changed.stderr
    assert step_of(out / "lidar") == 6
    # A stage whose inputs are not done, an unknown stage, a variant without fusion: refused too.
    fusion = staged(env, "fusion")
    assert fusion.returncode == 2 and "the fusion stage needs the cache stage done first" in fusion.stderr
    for bad, needle in ((["camra"], "unknown stage 'camra'"), (["--list"], "not a fused variant")):
        proc = staged({**env, "FUSION_VARIANT": "lidar"} if bad == ["--list"] else env, *bad)
        assert proc.returncode == 2 and needle in proc.stderr, proc.stderr


def test_a_part_records_its_cpu_time_and_exit_and_a_killed_one_keeps_its_time_so_far(tmp_path):
    rec = script_module("staged_record")
    burn = "import sys, time\nt = time.process_time()\nwhile time.process_time() - t < {s}: pass\nsys.exit({rc})"
    out = tmp_path / "out"
    assert rec.run(out, "x", "--a 1", [sys.executable, "-c", burn.format(s=0.4, rc=3)]) == 3
    assert rec.state(out, "x", "--a 1") == "started"
    assert rec.run(out, "x", "--a 1", [sys.executable, "-c", burn.format(s=0.4, rc=0)]) == 0
    assert rec.state(out, "x", "--a 1") == "done"
    r = record(out)
    parts = r["stages"]["x"]["parts"]
    assert [p["exit"] for p in parts] == [3, 0] and all(p["ended"] for p in parts)
    for p in parts:
        assert 0.4 <= p["user_s"] + p["sys_s"] <= p["wall_s"] + 0.05, p
    assert r["stages"]["x"]["cpu_s"] == pytest.approx(sum(p["user_s"] + p["sys_s"] for p in parts), abs=2e-3)
    assert r["cpu_hours"] == pytest.approx(r["cpu_s"] / 3600, abs=1e-4)
    with pytest.raises(rec.Refused, match=r"the x stage in .* other settings \(--a 1 -> 2\)"):
        rec.state(out, "x", "--a 2")

    # The CPU of a set of done stages (a benchmark run's), and a refusal for one not done.
    assert rec.cpu(out, ["x"]) == {"stages": {"x": r["stages"]["x"]["cpu_s"]}, "cpu_s": r["stages"]["x"]["cpu_s"]}
    with pytest.raises(rec.Refused, match="the stage z is not done"):
        rec.cpu(out, ["x", "z"])

    # The recorder killed with SIGKILL mid-part: the part keeps the CPU time of its last rewrite.
    code = (f"import sys; sys.path.insert(0, {str(ROOT / 'scripts')!r}); import staged_record as r; "
            f"r.INTERIM_S = 0.2; sys.exit(r.main(sys.argv[1:]))")
    proc = subprocess.Popen([sys.executable, "-c", code, "run", str(out), "y", "", "--", sys.executable, "-c",
                             burn.format(s=30, rc=0)], start_new_session=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        time.sleep(0.2)
        part = record(out)["stages"].get("y", {"parts": [{"user_s": 0}]})["parts"][0]
        if part["user_s"] >= 0.5:
            break
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    part = record(out)["stages"]["y"]["parts"][0]
    assert part["ended"] is False and part["exit"] is None and 0.5 <= part["user_s"] + part["sys_s"] < 30
    assert rec.state(out, "y", "") == "started"


def test_two_processes_recording_other_stages_of_one_out_keep_both(tmp_path):
    """Two benchmark runs side by side record their stages in one staged.json: each write merges
    into the file as it is, under a lock, so neither stage's parts are lost."""
    out = tmp_path / "out"
    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 1.0: pass"
    code = (f"import sys; sys.path.insert(0, {str(ROOT / 'scripts')!r}); import staged_record as r; "
            f"r.INTERIM_S = 0.02; sys.exit(r.main(sys.argv[1:]))")
    procs = [subprocess.Popen([sys.executable, "-c", code, "run", str(out), stage, f"--{stage} 1", "--",
                               sys.executable, "-c", burn]) for stage in ("a", "b")]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    stages = record(out)["stages"]
    assert set(stages) == {"a", "b"}
    for entry in stages.values():
        part = entry["parts"][0]
        assert entry["done"] and len(entry["parts"]) == 1 and part["user_s"] + part["sys_s"] >= 0.9, part


class Killed(Exception):
    """Where a kill would stop the run."""


def test_the_last_steps_checkpoint_comes_after_precise_batchnorm(tiny_dataset, micro, tmp_path, monkeypatch):
    """A run stopped between its last step and precise BatchNorm must not leave a last.pt of the
    last step, from which a resume would count the run as finished without precise BN."""
    def killed(*_args, **_kw):
        raise Killed
    monkeypatch.setattr(train_module, "precise_batchnorm", killed)
    tc = TrainConfig(max_steps=3, save_every_steps=1, val_split="", batch_size=1, image_init="", gt_paste=0)
    with pytest.raises(Killed):
        train_module.train(tiny_dataset, tmp_path / "run", load_config(micro), "lidar", tc, progress=False)
    assert load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 2


@pytest.mark.slow      # two micro recipes, one killed inside each stage and resumed: about 2 minutes
def test_a_recipe_killed_inside_each_stage_ends_with_the_uninterrupted_weights(tiny_dataset, micro, encoder_ckpt,
                                                                               tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    env_a, env_b = (recipe_env(tiny_dataset, micro, encoder_ckpt, out, 6) for out in (a, b))
    whole = staged(env_a)
    assert whole.returncode == 0, whole.stderr[-3000:]
    assert [f"staged: {s} starts" in whole.stdout for s in RECIPE_STAGES] == [True] * 4

    # Inside the cache stage: its manifest written, the stage not done; inside each training
    # stage: its last.pt at step 2 or later (its last step's checkpoint comes after precise BN).
    inside = {"cache": lambda: (b / "cache" / "encoder.json").exists(),
              "camera": lambda: step_of(b / "camera") >= 2, "lidar": lambda: step_of(b / "lidar") >= 2,
              "fusion": lambda: step_of(b / "fusion") >= 2}
    for stage in RECIPE_STAGES:
        kill_when(start_staged(env_b), inside[stage], f"the {stage} stage under way")
        assert record(b)["stages"][stage]["done"] is False, stage
        if stage != "cache":
            assert 2 <= step_of(b / stage) < 6, stage
    last = staged(env_b)
    assert last.returncode == 0, last.stderr[-3000:]
    assert "staged: fusion resumes from" in last.stdout and "staged: lidar done earlier (skipped)" in last.stdout

    for stage in ("camera", "lidar", "fusion"):
        ca, cb = load_checkpoint(a / stage / "last.pt"), load_checkpoint(b / stage / "last.pt")
        assert ca["step"] == cb["step"] == 6
        assert ca["model"].keys() == cb["model"].keys()
        for k in ca["model"]:
            assert torch.equal(ca["model"][k], cb["model"][k]), (stage, k)
        for sa, sb in zip(ca["optimizer"]["state"].values(), cb["optimizer"]["state"].values()):
            for k in sa:
                assert torch.equal(sa[k], sb[k]), (stage, k)
    cache_files = sorted(p.relative_to(a / "cache") for p in (a / "cache").rglob("*.feat"))
    assert cache_files and cache_files == sorted(p.relative_to(b / "cache") for p in (b / "cache").rglob("*.feat"))
    for name in cache_files:
        assert (a / "cache" / name).read_bytes() == (b / "cache" / name).read_bytes()
    stages = record(b)["stages"]
    assert all(stages[s]["done"] and len(stages[s]["parts"]) >= 2 for s in RECIPE_STAGES)
    # The experts file holds exactly the three stages' weights.
    experts, _ = load_predictor(b / "experts.pt")
    for role, stage in (("fused", "fusion"), ("camera", "camera"), ("lidar", "lidar")):
        weights = load_checkpoint(b / stage / "last.pt")["model"]
        assert all(torch.equal(weights[k], v) for k, v in experts.expert(role).state_dict().items()), role
    assert record(b)["cpu_s"] > 0 and "in all:" in last.stdout
