"""clfbev train / eval / predict / show through the command line, as a user runs them.

A micro config (the tiny preset with smaller images and channels) keeps each step well under a
second; what is tested (checkpoints, resume, DDP, metrics files, errors) does not depend on size.
"""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from clfbev.errors import ConfigError
from clfbev.run.checkpoint import load_checkpoint, load_model
from clfbev.run.epochs import epoch_batches
from clfbev.run.loop import lr_at
from clfbev.run.train_config import TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def clfbev(*args, check=True, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "clfbev", *map(str, args)], capture_output=True, text=True,
                          env=ENV, **kw)
    if check and proc.returncode != 0:
        raise AssertionError(f"clfbev {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return proc


def train_args(data, out, micro, *extra):
    return ["train", "--data", data, "--out", out, "--config", micro, "--batch-size", "1", "--threads", "1",
            "--quiet", *extra]


# ---------------------------------------------------------------- pure parts

def test_lr_schedule_warmup_then_cosine():
    tc = TrainConfig(lr=1e-3, warmup_frac=0.1, min_lr_ratio=0.01)
    lrs = [lr_at(s, 100, tc) for s in range(100)]
    assert lrs[0] == pytest.approx(1e-4)                     # warmup starts at lr / 10
    assert all(a < b for a, b in zip(lrs[:10], lrs[1:11]))    # rising over the 10 warmup steps
    assert lrs[10] == pytest.approx(1e-3)                    # the peak
    assert all(a >= b for a, b in zip(lrs[10:], lrs[11:]))    # then never rising
    assert lr_at(100, 100, tc) == pytest.approx(1e-5)        # the floor at the end


def test_the_recipe_is_the_default_and_options_override_it(tmp_path):
    import argparse
    from clfbev.run.train_config import add_train_arguments, recipe, train_config_from
    p = argparse.ArgumentParser()
    add_train_arguments(p)
    parse = lambda *a: train_config_from(p.parse_args(["--data", "d", "--out", "o", *a]))  # noqa: E731
    assert parse() == recipe("tiny", "full")
    assert parse("--variant", "camera") == recipe("tiny", "camera")
    assert recipe("tiny", "camera").gt_paste == 0 < recipe("tiny", "lidar").gt_paste   # no lidar-only objects
    assert parse("--config", "paper") == TrainConfig()                                   # the paper's recipe
    custom = tmp_path / "c.yaml"
    custom.write_text("preset: paper\nfusion_dim: 128\n")
    assert parse("--config", str(custom)).lr == TrainConfig().lr                          # its preset's recipe
    tc = parse("--lr", "5e-4", "--no-augment", "--gt-paste", "0", "--epochs", "3")
    assert (tc.lr, tc.augment, tc.gt_paste, tc.epochs) == (5e-4, False, 0, 3)
    assert tc.batch_size == recipe("tiny", "full").batch_size
    with pytest.raises(ConfigError, match="--gt-paste-fade"):
        parse("--gt-paste-fade", "1.5")


def test_every_setting_has_one_generated_option_with_its_range(tmp_path):
    """The options are generated from TrainConfig's fields: each field has its option (also
    min_lr_ratio and precise_bn_batches), no option repeats a default (left out = the recipe's
    value), a preset's recipe sets only recipe fields, and the ranges come from the metadata."""
    import argparse
    from dataclasses import asdict, fields

    from clfbev.config import VARIANTS
    from clfbev.run.train_config import add_train_arguments, flag_of, recipe, train_config_from
    p = argparse.ArgumentParser()
    add_train_arguments(p)
    by_dest = {a.dest: a for a in p._actions}
    for f in fields(TrainConfig):
        assert flag_of(f) in by_dest[f.name].option_strings and by_dest[f.name].default is None, f.name
        note = "[recipe" if f.metadata["recipe"] else f"[default {f.default!r}"
        assert note in by_dest[f.name].help, f.name
    parse = lambda *a: train_config_from(p.parse_args(["--data", "d", "--out", "o", *a]))  # noqa: E731
    tc = parse("--min-lr-ratio", "0.1", "--precise-bn-batches", "0", "--save-every-steps", "5", "--no-gt-paste-balanced")
    assert (tc.min_lr_ratio, tc.precise_bn_batches, tc.save_every_steps, tc.gt_paste_balanced) == (0.1, 0, 5, False)
    recipe_fields = {f.name for f in fields(TrainConfig) if f.metadata["recipe"]}
    for preset in ("tiny", "paper"):
        for variant in VARIANTS:
            changed = {k for k, v in asdict(recipe(preset, variant)).items() if v != getattr(TrainConfig(), k)}
            assert changed <= recipe_fields, (preset, variant, changed)
    for flag, value in [("--lr", "0"), ("--lr", "nan"), ("--warmup-frac", "1"), ("--min-lr-ratio", "-0.5"),
                        ("--ckpt-minutes", "inf"), ("--seed", "-1"), ("--workers", "-2"), ("--epochs", "0")]:
        with pytest.raises(ConfigError, match=flag):
            parse(flag, value)
    with pytest.raises(SystemExit):
        p.parse_args(["--data", "d", "--out", "o", "--epochs", "2", "--max-steps", "3"])   # one length only


def test_a_resume_ignores_exactly_the_bookkeeping_settings():
    """Changing how often to save or how many loader processes still resumes; any other setting
    is refused, naming it. A setting the checkpoint lacks has its default."""
    from dataclasses import asdict, fields

    from clfbev.errors import CheckpointError
    from clfbev.run.train_config import BOOKKEEPING, check_resumable
    assert BOOKKEEPING == {"ckpt_minutes", "save_every_steps", "workers"}
    tc = TrainConfig()
    saved = asdict(tc)
    other = {bool: lambda v: not v, str: lambda v: v + "x", int: lambda v: v + 1, float: lambda v: v / 2 + 0.25}
    for f in fields(TrainConfig):
        changed = {**saved, f.name: other[type(getattr(tc, f.name))](getattr(tc, f.name))}
        if f.name in BOOKKEEPING:
            check_resumable(changed, tc, "last.pt")
        else:
            with pytest.raises(CheckpointError, match=rf"differs in: {f.name}\)"):
                check_resumable(changed, tc, "last.pt")
    check_resumable({k: v for k, v in saved.items() if k != "precise_bn_batches"}, tc, "last.pt")
    with pytest.raises(CheckpointError, match="'train'"):
        check_resumable({**saved, "momentum": 0.9}, tc, "last.pt")


def test_precise_batchnorm_is_the_exact_average_over_its_batches(tiny_dataset, micro):
    """After precise_batchnorm, a BatchNorm's running mean is the mean of the batch means it saw
    (cumulative, not exponential), its momentum is restored, and a second call repeats it."""
    from clfbev.config_file import load_config
    from clfbev.data import NuScenesDetection
    from clfbev.model import CLFusionBEV
    from clfbev.run.epochs import precise_batchnorm
    cfg = load_config(micro)
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-train", cfg.data_config())
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "lidar").eval()
    bn = model.lidar_encoder.vfe.point_mlp[1]
    seen = []
    bn.register_forward_pre_hook(lambda m, inputs: seen.append(inputs[0].mean(dim=0)))
    tc = TrainConfig(batch_size=1, precise_bn_batches=2)
    precise_batchnorm(model, ds, tc, None)
    assert len(seen) == 2 and not model.training and bn.momentum == 0.01
    torch.testing.assert_close(bn.running_mean, torch.stack(seen).mean(dim=0), atol=1e-6, rtol=1e-5)
    first = bn.running_mean.clone()
    precise_batchnorm(model, ds, tc, None)
    assert torch.equal(bn.running_mean, first)


@pytest.mark.parametrize("n,bs,world", [(7, 2, 1), (7, 2, 2), (6, 1, 2), (3, 2, 2)])
def test_epoch_batches_shard_the_permutation(n, bs, world):
    shards = [epoch_batches(n, bs, seed=5, epoch=3, rank=r, world=world) for r in range(world)]
    steps = math.ceil(n / (bs * world))
    assert all(len(s) == steps for s in shards)               # every rank takes as many steps
    flat = [i for s in shards for b in s for i in b]
    assert set(flat) == set(range(n))                         # every sample is visited
    assert len(flat) == steps * bs * world                    # padding only to fill the last step
    if n % (bs * world) == 0:
        assert sorted(flat) == list(range(n))                 # no repeats when it divides
    assert shards == [epoch_batches(n, bs, 5, 3, r, world) for r in range(world)]   # deterministic
    assert shards != [epoch_batches(n, bs, 5, 4, r, world) for r in range(world)] or n < 4


# ---------------------------------------------------------------- the loop through the CLI

def test_train_eval_predict_show(tiny_dataset, micro, tmp_path):
    run = tmp_path / "run"
    out = clfbev(*train_args(tiny_dataset, run, micro, "--max-steps", "3", "--seed", "4"))
    assert "trained 3 steps" in out.stdout
    for name in ("last.pt", "best.pt", "run.json", "metrics.jsonl"):
        assert (run / name).is_file(), name
    assert list((run / "tb").glob("events.out.tfevents.*"))
    meta = json.loads((run / "run.json").read_text())
    assert meta["train"]["seed"] == 4 and meta["variant"] == "full" and meta["code_version"]
    assert meta["config"]["image_size"] == [64, 176]
    rows = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines()]
    train_rows = [r for r in rows if "train/loss" in r]
    assert [r["step"] for r in train_rows] == [1, 2, 3]
    assert all(math.isfinite(r["train/loss"]) and r["train/samples_per_s"] > 0 for r in train_rows)
    # every term the loss computes is logged, the angle's residual and the perspective head's too
    assert {"train/loss_reg_theta", "train/loss_depth", "train/loss_dir", "train/loss_cls"} <= set(train_rows[0])
    assert any("val/NDS" in r for r in rows)
    ckpt = load_checkpoint(run / "last.pt")
    assert ckpt["step"] == 3 and ckpt["variant"] == "full"

    ev = tmp_path / "eval"
    out = clfbev("eval", "--data", tiny_dataset, "--ckpt", run / "last.pt", "--out", ev, "--no-plots")
    summary = json.loads((ev / "metrics_summary.json").read_text())
    assert math.isfinite(summary["mean_ap"]) and math.isfinite(summary["nd_score"])
    assert (ev / "metrics_details.json").is_file()
    assert "NDS" in out.stdout and "car" in out.stdout
    sub = json.loads((ev / "results.json").read_text())
    assert set(sub["meta"]) >= {"use_camera", "use_lidar"} and len(sub["results"]) == 3   # the sim-val samples

    pred = tmp_path / "pred.json"
    clfbev("predict", "--data", tiny_dataset, "--ckpt", run / "last.pt", "--out", pred)
    assert len(json.loads(pred.read_text())["results"]) == 6    # every sample, split or not

    png = tmp_path / "show.png"
    clfbev("show", "--data", tiny_dataset, "--results", pred, "--sample", "2", "--out", png,
           "--attention", "--ckpt", run / "last.pt", "--cell", "10,5")
    import cv2
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 400 and img.shape[1] > 1000


def _weights_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_sigkill_then_resume_gives_identical_weights(tiny_dataset, micro, tmp_path):
    """Kill a run at an arbitrary moment after its 2nd checkpoint, resume it, and compare with an
    uninterrupted run of the same seed: every weight and optimizer moment bit-identical."""
    common = ["--max-steps", "6", "--save-every-steps", "1", "--val-split", "", "--seed", "1"]
    clfbev(*train_args(tiny_dataset, tmp_path / "a", micro, *common))

    b = tmp_path / "b"
    proc = subprocess.Popen([sys.executable, "-m", "clfbev", *map(str, train_args(tiny_dataset, b, micro, *common))],
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if (b / "last.pt").exists() and load_checkpoint(b / "last.pt")["step"] >= 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = load_checkpoint(b / "last.pt")["step"]
    assert 2 <= killed_at < 6, f"the run was not interrupted (checkpoint at step {killed_at})"

    clfbev(*train_args(tiny_dataset, b, micro, *common, "--resume"))
    ca, cb = load_checkpoint(tmp_path / "a" / "last.pt"), load_checkpoint(b / "last.pt")
    assert ca["step"] == cb["step"] == 6
    _weights_equal(ca["model"], cb["model"])
    for sa, sb in zip(ca["optimizer"]["state"].values(), cb["optimizer"]["state"].values()):
        _weights_equal(sa, sb)
    steps = [json.loads(ln)["step"] for ln in (b / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6]          # the log reads as one run


def test_ddp_two_gloo_processes(tiny_dataset, micro, tmp_path):
    run = tmp_path / "ddp"
    args = train_args(tiny_dataset, run, micro, "--max-steps", "2", "--val-split", "")
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                           "--master_port", "29533", "-m", "clfbev", *map(str, args)],
                          capture_output=True, text=True, env=ENV, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run / "run.json").read_text())["world_size"] == 2
    model, ckpt = load_model(run / "last.pt")
    assert ckpt["step"] == 2
    # 3 training samples, 2 ranks x batch 1: 2 steps per epoch, so step 2 closes epoch 1.
    assert ckpt["epoch"] == 1
    assert all(torch.isfinite(p).all() for p in model.parameters())


# ---------------------------------------------------------------- errors

def _assert_bad_input(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr
    line = proc.stderr.strip()
    assert line.startswith("clfbev: error:") and len(line.splitlines()) == 1, line
    for n in needles:
        assert n in line, line


def test_bad_input_exits_2(tiny_dataset, micro, tmp_path):
    run = tmp_path / "run"
    clfbev(*train_args(tiny_dataset, run, micro, "--max-steps", "1", "--val-split", ""))
    ckpt = run / "last.pt"

    _assert_bad_input(clfbev(*train_args(tmp_path / "nowhere", tmp_path / "r2", micro), check=False), "nowhere")
    _assert_bad_input(clfbev(*train_args(tiny_dataset, tmp_path / "r3", micro, "--split", "sim-nope"), check=False),
                      "sim-nope", "splits.json")
    bad_cfg = tmp_path / "bad.yaml"
    bad_cfg.write_text("preset: tiny\nvfe_chanels: 4\n")
    _assert_bad_input(clfbev(*train_args(tiny_dataset, tmp_path / "r4", bad_cfg), check=False), "bad.yaml", "vfe_chanels")

    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])     # a truncated file
    _assert_bad_input(clfbev("eval", "--data", tiny_dataset, "--ckpt", corrupt, "--out", tmp_path / "e1", check=False),
                      "corrupt.pt")
    _assert_bad_input(clfbev("eval", "--data", tiny_dataset, "--ckpt", tmp_path / "none.pt", "--out", tmp_path / "e2",
                             check=False), "none.pt")
    # A checkpoint of another config or variant.
    _assert_bad_input(clfbev("eval", "--data", tiny_dataset, "--ckpt", ckpt, "--config", "tiny", "--out",
                             tmp_path / "e3", check=False), "another config", "image_size")
    _assert_bad_input(clfbev("predict", "--data", tiny_dataset, "--ckpt", ckpt, "--variant", "lidar", "--out",
                             tmp_path / "p.json", check=False), "variant")
    _assert_bad_input(clfbev(*train_args(tiny_dataset, run, micro, "--variant", "concat", "--resume"), check=False),
                      "variant")
    # Training into a run folder that already has a checkpoint, without --resume.
    _assert_bad_input(clfbev(*train_args(tiny_dataset, run, micro), check=False), "--resume")
    assert load_checkpoint(ckpt)["step"] == 1          # nothing already written was damaged
    _assert_bad_input(clfbev(*train_args(tiny_dataset, tmp_path / "r5", micro, "--batch-size", "0"), check=False),
                      "--batch-size")
    # The split must exist in the dataroot for eval too.
    _assert_bad_input(clfbev("eval", "--data", tiny_dataset, "--ckpt", ckpt, "--split", "sim-test", "--out",
                             tmp_path / "e4", check=False), "sim-test")


def test_non_finite_loss_stops_and_keeps_the_checkpoint(tiny_dataset, micro, tmp_path, monkeypatch):
    from clfbev.config_file import load_config
    from clfbev.errors import TrainError
    from clfbev.run import train as train_module
    from clfbev.run.train import train

    real_loss, calls = train_module.training_loss, []

    def loss_then_nan(outputs, targets, cfg):
        out = real_loss(outputs, targets, cfg)
        calls.append(1)
        if len(calls) == 3:
            out = {**out, "loss": out["loss"] * float("nan")}
        return out

    monkeypatch.setattr(train_module, "training_loss", loss_then_nan)
    tc = TrainConfig(max_steps=5, batch_size=1, val_split="", save_every_steps=1)
    with pytest.raises(TrainError, match="non-finite loss .* step 3.*last.pt is kept"):
        train(tiny_dataset, tmp_path / "run", load_config(micro), "full", tc, progress=False)
    ckpt = load_checkpoint(tmp_path / "run" / "last.pt")
    assert ckpt["step"] == 2
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())


def test_code_version_is_dirty_only_for_the_package_files(tmp_path):
    """A run's code version reads -dirty when the package's own tracked files are modified, not
    when a doc or a script beside it is."""
    from clfbev.run.run_log import code_version

    def git(*args):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path, check=True,
                       capture_output=True)

    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "model.py").write_text("x = 1\n")
    (tmp_path / "README.md").write_text("doc\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-q", "-m", "one")
    clean = code_version(pkg)
    assert len(clean) >= 7 and not clean.endswith("-dirty")
    (tmp_path / "README.md").write_text("changed doc\n")
    (tmp_path / "notes.txt").write_text("untracked\n")
    assert code_version(pkg) == clean
    (pkg / "model.py").write_text("x = 2\n")
    assert code_version(pkg) == clean + "-dirty"
