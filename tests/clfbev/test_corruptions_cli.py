"""``--corrupt`` on the command line: every severity out of range is refused with one line that
names the flag and the allowed range (exit 2); the new corruptions are conditions of
``clfbev robustness`` like the others."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
import torch

from clfbev.config_file import config_from_dict
from clfbev.corruptions import PER_SENSOR, RANGES, Corruption, parse
from clfbev.model import CLFusionBEV
from clfbev.run import cli
from clfbev.run.checkpoint import save_checkpoint

pytestmark = pytest.mark.usefixtures("one_thread")

NEW = ["misalign:LIDAR_TOP:2", "misalign:CAM_FRONT:1", "late:LIDAR_TOP:1", "late:CAM_BACK:2", "motion_blur:21",
       "density:0.4"]


def _out_of_range() -> list[tuple[str, float, float]]:
    """(--corrupt text, lo, hi) for a severity just below and just above every corruption's range."""
    cases = []
    for name, (lo, hi) in RANGES.items():
        if name == "lidar_missing":
            continue
        sensor = "CAM_FRONT:" if name in PER_SENSOR else ""
        cases += [(f"{name}:{sensor}{lo - 1:g}", lo, hi), (f"{name}:{sensor}{hi + 1:g}", lo, hi)]
    return cases


def _refused(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as exit_:
        cli.build_parser().parse_args(list(argv))
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err.strip().splitlines()[-1]        # argparse's usage lines come first, as for every option


@pytest.mark.parametrize("text, lo, hi", _out_of_range())
def test_a_severity_out_of_range_is_one_line_naming_the_flag_and_range(capsys, text, lo, hi):
    for command in (["eval", "--data", "d", "--ckpt", "c", "--out", "o"],
                    ["robustness", "--ckpt", "a=c", "--set", "clean=d", "--out", "o"]):
        line = _refused(capsys, *command, "--corrupt", text)
        assert line.startswith(f"clfbev {command[0]}: error: argument --corrupt: --corrupt {text}: "), line
        assert f"[{lo}, {hi}]" in line, line
        kind = "an integer" if isinstance(lo, int) else "a number"
        assert f"severity must be {kind} in [{lo}, {hi}]" in line, line


@pytest.mark.parametrize("text, needle", [
    ("misalign:2", "misalign:SENSOR:SEVERITY"), ("late:CAM_MIDDLE:1", "LIDAR_TOP, CAM_FRONT_LEFT"),
    ("late:LIDAR_TOP:1.5", "an integer in [1, 20]"), ("motion_blur:fast", "not a number (allowed: [1.0, 100.0])"),
    ("lidar_missing:1", "lidar_missing (no severity)"), ("blur:3", "known: beam_missing"),
    ("density:CAM_FRONT:0.2", "density:SEVERITY (SEVERITY in [0.0, 1.0])"),
])
def test_a_malformed_corruption_is_one_line(capsys, text, needle):
    line = _refused(capsys, "eval", "--data", "d", "--ckpt", "c", "--out", "o", "--corrupt", text)
    assert f"--corrupt {text}: " in line and needle in line, line


def test_the_new_names_parse_and_print_back():
    args = cli.build_parser().parse_args(["eval", "--data", "d", "--ckpt", "c", "--out", "o",
                                          *[a for t in NEW for a in ("--corrupt", t)]])
    assert [str(c) for c in args.corrupt] == NEW
    assert args.corrupt[0] == Corruption("misalign", 2.0, "LIDAR_TOP")
    assert args.corrupt[3] == Corruption("late", 2.0, "CAM_BACK")


def test_the_refusal_through_the_real_command():
    proc = subprocess.run([sys.executable, "-m", "clfbev", "eval", "--data", "d", "--ckpt", "c", "--out", "o",
                           "--corrupt", "misalign:LIDAR_TOP:12"], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].endswith(
        "--corrupt misalign:LIDAR_TOP:12: misalign's severity must be a number in [0.0, 10.0], got 12")


def test_robustness_reports_the_new_conditions(tiny_dataset, tmp_path):
    cfg = config_from_dict({"image_size": [64, 176], "cam_width": 8, "fpn_ch": 32, "context_ch": 16, "vfe_ch": 16,
                            "fusion_dim": 32, "attn_heads": 2, "bev_channels": [16, 32], "bev_blocks": 1,
                            "bev_up_ch": 16, "prior_prob": 0.9, "lidar_bev_stride": 4})
    torch.manual_seed(4)
    ckpt = save_checkpoint(tmp_path / "concat.pt", {"model": CLFusionBEV(cfg, "concat").state_dict(),
                                                    "config": cfg.to_dict(), "variant": "concat", "step": 0,
                                                    "epoch": 0, "best_nds": -1.0})
    conditions = ["misalign:LIDAR_TOP:2", "late:CAM_FRONT:1", "motion_blur:21"]
    out = tmp_path / "rob"
    proc = subprocess.run([sys.executable, "-m", "clfbev", "robustness", "--ckpt", f"concat={ckpt}",
                           "--set", f"clean={tiny_dataset}", *[a for t in conditions for a in ("--corrupt", t)],
                           "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rec = json.loads((out / "robustness.json").read_text())
    assert rec["conditions"] == ["clean", *conditions]
    m = rec["models"]["concat"]
    assert all(math.isfinite(m["metrics"][c]["NDS"]) for c in rec["conditions"])
    assert set(m["RR"]) == set(rec["conditions"])
    md = (out / "robustness.md").read_text()
    assert all(f" {c} |" in md for c in conditions)
    assert all((out / "concat" / c.replace(":", "_")).is_dir() for c in conditions)
    assert [str(parse(c)) for c in conditions] == conditions
