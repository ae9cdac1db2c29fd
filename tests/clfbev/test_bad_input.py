"""Bad input through the command line, as a new user gives it: one line on stderr naming the file
or the field, exit code 2, no traceback. An internal error, by contrast, keeps its traceback.

Each file a command reads is fed junk, truncated, lacking a field or holding a non-finite value.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys

import pytest
import torch

from clfbev.config import tiny
from clfbev.errors import EXIT_BAD_INPUT, run_guarded
from clfbev.model import CLFusionBEV
from clfbev.run import cli
from clfbev.run.checkpoint import save_checkpoint

pytestmark = pytest.mark.usefixtures("one_thread")

MICRO = dataclasses.replace(tiny(), image_size=(64, 176), cam_width=8, fpn_ch=32, context_ch=16, vfe_ch=16,
                            fusion_dim=32, attn_heads=2, bev_channels=(16, 32), bev_blocks=1, bev_up_ch=16)
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def clfbev(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clfbev", *map(str, args)], capture_output=True, text=True,
                          env=ENV, timeout=600)


def assert_bad_input(proc: subprocess.CompletedProcess, *needles: str) -> None:
    """Exit 2 and one line on stderr, ``clfbev: error: ...``, holding every needle."""
    assert proc.returncode == EXIT_BAD_INPUT, (proc.returncode, proc.stderr[-3000:])
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    line = proc.stderr.strip()
    assert line.startswith("clfbev: error:") and len(line.splitlines()) == 1, line
    for needle in needles:
        assert needle in line, line


@pytest.fixture(scope="module")
def ckpt_state() -> dict:
    """What a checkpoint of a randomly initialised MICRO 'lidar' model holds (no optimizer)."""
    torch.manual_seed(0)
    model = CLFusionBEV(MICRO, "lidar")
    return {"model": model.state_dict(), "config": MICRO.to_dict(), "variant": "lidar", "step": 0, "epoch": 0}


def _eval(data, ckpt, out):
    return clfbev("eval", "--data", data, "--ckpt", ckpt, "--out", out, "--no-plots")


# ---------------------------------------------------------------- checkpoints

def test_a_text_file_as_checkpoint(tiny_dataset, tmp_path):
    text = tmp_path / "notes.pt"
    text.write_text("these are my notes, not a checkpoint\n")
    assert_bad_input(_eval(tiny_dataset, text, tmp_path / "e"), "notes.pt", "not a checkpoint")


def test_a_truncated_checkpoint(tiny_dataset, tmp_path, ckpt_state):
    whole = save_checkpoint(tmp_path / "whole.pt", ckpt_state)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 3])
    assert_bad_input(_eval(tiny_dataset, cut, tmp_path / "e"), "cut.pt", "corrupt")


@pytest.mark.parametrize("field", ["variant", "config", "model"])
def test_a_checkpoint_missing_a_field(tiny_dataset, tmp_path, ckpt_state, field):
    path = save_checkpoint(tmp_path / "lacking.pt", {k: v for k, v in ckpt_state.items() if k != field})
    assert_bad_input(_eval(tiny_dataset, path, tmp_path / "e"), "lacking.pt", field)


def test_a_checkpoint_with_a_field_of_the_wrong_kind(tiny_dataset, tmp_path, ckpt_state):
    path = save_checkpoint(tmp_path / "odd.pt", {**ckpt_state, "variant": "hybrid"})
    assert_bad_input(_eval(tiny_dataset, path, tmp_path / "e"), "odd.pt", "variant", "hybrid")
    path = save_checkpoint(tmp_path / "step.pt", {**ckpt_state, "step": -3})
    assert_bad_input(_eval(tiny_dataset, path, tmp_path / "e"), "step.pt", "step")


def test_a_checkpoint_with_non_finite_weights(tiny_dataset, tmp_path, ckpt_state):
    weights = dict(ckpt_state["model"])
    name = next(k for k, v in weights.items() if v.is_floating_point())
    weights[name] = torch.full_like(weights[name], float("nan"))
    path = save_checkpoint(tmp_path / "nan.pt", {**ckpt_state, "model": weights})
    assert_bad_input(_eval(tiny_dataset, path, tmp_path / "e"), "nan.pt", name)


def test_resuming_from_a_checkpoint_without_the_optimizer(tiny_dataset, micro, tmp_path, ckpt_state):
    """A checkpoint written for evaluation cannot be resumed: it lacks what training reads."""
    config = micro
    run = tmp_path / "run"
    save_checkpoint(run / "last.pt", ckpt_state)
    proc = clfbev("train", "--data", tiny_dataset, "--out", run, "--config", config, "--variant", "lidar",
                  "--resume", "--threads", "1", "--quiet")
    assert_bad_input(proc, "last.pt", "optimizer")


# ---------------------------------------------------------------- results files for `clfbev show`

@pytest.mark.parametrize("content,needle", [
    ("{not json", "not JSON"),
    (json.dumps({"meta": {}}), "'results'"),
    (json.dumps([1, 2, 3]), "'results'"),
    ("\x00\x01\x02binary", "not JSON"),
])
def test_show_refuses_a_junk_results_file(tiny_dataset, tmp_path, content, needle):
    results = tmp_path / "results.json"
    results.write_text(content)
    proc = clfbev("show", "--data", tiny_dataset, "--results", results, "--out", tmp_path / "s.png")
    assert_bad_input(proc, "results.json", needle)
    assert not (tmp_path / "s.png").exists()


@pytest.mark.parametrize("box,needle", [
    ({"size": [1, 1, 1], "rotation": [1, 0, 0, 0], "detection_name": "car"}, "translation"),
    ({"translation": [1, 2, float("nan")], "size": [1, 1, 1], "rotation": [1, 0, 0, 0], "detection_name": "car"},
     "translation"),
    ({"translation": [1, 2, 0], "size": [1, 1], "rotation": [1, 0, 0, 0], "detection_name": "car"}, "size"),
])
def test_show_refuses_a_results_box_lacking_a_field(tiny_dataset, tmp_path, box, needle):
    samples = json.loads((tiny_dataset / "v1.0-sim" / "sample.json").read_text())
    results = {s["token"]: [] for s in samples}
    results[samples[0]["token"]] = [{"sample_token": samples[0]["token"], **box}]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"meta": {}, "results": results}))
    proc = clfbev("show", "--data", tiny_dataset, "--results", path, "--sample", "0", "--out", tmp_path / "s.png")
    assert_bad_input(proc, "results.json", samples[0]["token"], needle)


# ---------------------------------------------------------------- outputs

def test_an_output_under_a_file_is_refused(tiny_dataset, tmp_path, ckpt_state):
    ckpt = save_checkpoint(tmp_path / "c.pt", ckpt_state)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert_bad_input(_eval(tiny_dataset, ckpt, blocker / "eval"), "--out", "a_file", "not a directory")
    assert_bad_input(clfbev("predict", "--data", tiny_dataset, "--ckpt", ckpt, "--out", tmp_path),
                     "--out", "is a directory")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only folder")
def test_an_unwritable_output_is_refused(tiny_dataset, tmp_path, ckpt_state):
    ckpt = save_checkpoint(tmp_path / "c.pt", ckpt_state)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        assert_bad_input(_eval(tiny_dataset, ckpt, locked / "eval"), "--out", "not writable")
    finally:
        locked.chmod(0o700)


def test_an_image_format_that_cannot_be_written_is_refused(tiny_dataset, tmp_path):
    proc = clfbev("show", "--data", tiny_dataset, "--results", tmp_path / "r.json", "--out", tmp_path / "s.xyz")
    assert proc.returncode == 2 and "s.xyz" in proc.stderr and "Traceback" not in proc.stderr


# ---------------------------------------------------------------- internal errors

def test_an_internal_value_error_keeps_its_traceback():
    """The guard maps only input errors to exit 2: a ValueError from inside is a bug and propagates."""
    def internal():
        raise ValueError("shapes (3, 4) and (5,) do not broadcast")

    with pytest.raises(ValueError, match="do not broadcast"):
        run_guarded(internal)


def test_an_internal_value_error_in_a_command_propagates(tiny_dataset, tmp_path, ckpt_state, monkeypatch):
    ckpt = save_checkpoint(tmp_path / "c.pt", ckpt_state)

    def broken_predict(*args, **kwargs):
        raise ValueError("internal: a tensor of the wrong shape")

    monkeypatch.setattr(cli, "predict_split", broken_predict)
    with pytest.raises(ValueError, match="wrong shape"):
        cli.main(["predict", "--data", str(tiny_dataset), "--ckpt", str(ckpt), "--out", str(tmp_path / "p.json")])


# ---------------------------------------------------------------- files of the model and data side
#
# The next tests cover checks that live in clfbev/config.py (a model config, in a file or in a
# checkpoint) and clfbev/data.py (the annotation tables): a YAML syntax error, a non-finite value
# in a config, a config value of the wrong type, annotation records lacking a field.

def _train(data, out, config, *extra):
    return clfbev("train", "--data", data, "--out", out, "--config", config, "--variant", "lidar", "--max-steps", "1",
                  "--batch-size", "1", "--val-split", "", "--threads", "1", "--quiet", *extra)


def test_a_config_file_with_a_yaml_syntax_error(tiny_dataset, micro, tmp_path):
    config = tmp_path / "broken.yaml"
    config.write_text(micro.read_text() + "bev_channels: [16, 32\n")
    assert_bad_input(_train(tiny_dataset, tmp_path / "run", config), "broken.yaml")


def test_a_config_file_with_a_non_finite_value(tiny_dataset, micro, tmp_path):
    config = tmp_path / "nan.yaml"
    config.write_text(micro.read_text() + "depth_bins: [1.0, .nan, 1.0]\n")
    assert_bad_input(_train(tiny_dataset, tmp_path / "run", config), "nan.yaml", "depth_bins")


def test_a_checkpoint_whose_config_has_a_value_of_the_wrong_type(tiny_dataset, tmp_path, ckpt_state):
    path = save_checkpoint(tmp_path / "odd.pt", {**ckpt_state, "config": {**MICRO.to_dict(), "fusion_dim": "wide"}})
    assert_bad_input(_eval(tiny_dataset, path, tmp_path / "e"), "odd.pt", "fusion_dim")


def test_annotations_lacking_translation(tiny_dataset, micro, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    table = data / "v1.0-sim" / "sample_annotation.json"
    records = json.loads(table.read_text())
    table.write_text(json.dumps([{k: v for k, v in r.items() if k != "translation"} for r in records]))
    config = micro
    assert_bad_input(_train(data, tmp_path / "run", config), "sample_annotation.json", "translation")
