"""`clfbev export`: a checkpoint's weights alone, xz-compressed, read wherever --ckpt is.

- the file holds exactly the checkpoint's weights, config and variant, no optimizer state, and is
  smaller than the checkpoint; the predictor loaded from it is the checkpoint's, tensor for tensor;
- a truncated or corrupt file, and an export of a file that is no checkpoint, are one line, exit 2.
"""
from __future__ import annotations

import lzma

import torch

from clfbev.run.checkpoint import RESUME_FIELDS, load_checkpoint, save_checkpoint
from clfbev.run.experts_file import load_predictor
from test_bad_input import assert_bad_input, ckpt_state, clfbev  # noqa: F401 (a fixture)


def test_export_keeps_the_weights_and_drops_the_optimizer(ckpt_state, tmp_path):
    model = ckpt_state["model"]
    optimizer = {"state": {0: {"exp_avg": torch.ones(4096)}}, "param_groups": [{"lr": 0.001, "params": [0]}]}
    src = save_checkpoint(tmp_path / "last.pt", {**ckpt_state, "optimizer": optimizer, "train": {"seed": 0},
                                                 "best_nds": -1.0, "code_version": "abc1234"})
    out = tmp_path / "weights.pt.xz"
    proc = clfbev("export", "--ckpt", src, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes()[:6] == b"\xfd7zXZ\x00" and out.stat().st_size < src.stat().st_size
    ckpt = load_checkpoint(out)
    assert not set(RESUME_FIELDS) & set(ckpt) and ckpt["code_version"] == "abc1234"
    assert ckpt["config"] == ckpt_state["config"] and ckpt["variant"] == "lidar"
    predictor, _ = load_predictor(out)
    loaded = predictor.state_dict()
    assert loaded.keys() == model.keys() and all(torch.equal(loaded[k], model[k]) for k in model)


def test_a_cut_or_foreign_export_is_one_line(ckpt_state, tmp_path):
    src = save_checkpoint(tmp_path / "last.pt", ckpt_state)
    out = tmp_path / "weights.pt.xz"
    assert clfbev("export", "--ckpt", src, "--out", out).returncode == 0
    cut = tmp_path / "cut.pt.xz"
    cut.write_bytes(out.read_bytes()[: out.stat().st_size // 2])
    assert_bad_input(clfbev("export", "--ckpt", cut, "--out", tmp_path / "again.pt.xz"), str(cut), "corrupt")
    junk = tmp_path / "junk.pt.xz"
    junk.write_bytes(lzma.compress(b"not a checkpoint"))
    assert_bad_input(clfbev("export", "--ckpt", junk, "--out", tmp_path / "again.pt.xz"), str(junk))
    assert not (tmp_path / "again.pt.xz").exists()
