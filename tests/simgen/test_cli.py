"""Bad input gets one clear line, exit code 2 and nothing written; --help explains."""
from __future__ import annotations

import pytest

from conftest import run_simgen


def _bad(tmp_path, *args):
    out = tmp_path / "out"
    proc = run_simgen("make", "--out", out, *args, check=False)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert "Traceback" not in proc.stderr
    assert not out.exists(), "nothing may be written on bad input"
    return lines[-1]


def _one_line(tmp_path, *args) -> str:
    """`simgen make` on bad input: exit 2, exactly one line on stderr, nothing written."""
    out = tmp_path / "out"
    proc = run_simgen("make", "--out", out, *args, check=False)
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert not out.exists(), "nothing may be written on bad input"
    return proc.stderr.strip()


@pytest.mark.parametrize("text, field, value", [
    ("lidar:\n  max_range: .nan\n", "lidar.max_range", "nan"),
    ("camera:\n  zfar: .inf\n", "camera.zfar", "inf"),
    ("layout:\n  building_height: [-.inf, 30]\n", "layout.building_height", "-inf"),
])
def test_non_finite_preset_value(tmp_path, text, field, value):
    preset = tmp_path / "bad.yaml"
    preset.write_text(text)
    line = _one_line(tmp_path, "--scenes", "1", "--preset", preset)
    assert line == f"simgen: error: {preset}: {field}: expected a finite number, got {value}"


def test_yaml_syntax_error_in_a_preset(tmp_path):
    preset = tmp_path / "bad.yaml"
    preset.write_text("lidar:\n  max_range: [70\n  min_range: 1\n")
    line = _one_line(tmp_path, "--scenes", "1", "--preset", preset)
    assert line.startswith(f"simgen: error: {preset}: not valid YAML at line 3, column ")


def test_non_finite_flag(tmp_path):
    line = _one_line(tmp_path, "--scenes", "1", "--preset", "tiny", "--fog-visibility", "nan")
    assert line == "simgen: error: --fog-visibility: expected a finite number, got nan"


def test_an_internal_error_keeps_its_traceback(monkeypatch, capsys):
    """Only input errors become one line and exit 2: a bug (here a ValueError from inside the
    command) propagates with its traceback."""
    from simgen import cli
    from simgen.errors import DataError

    def broken(args):
        raise ValueError("an internal shape mismatch")
    monkeypatch.setattr(cli, "_run", broken)
    with pytest.raises(ValueError, match="an internal shape mismatch"):
        cli.main(["presets"])

    def bad_data(args):
        raise DataError("x.json: damaged")
    monkeypatch.setattr(cli, "_run", bad_data)
    assert cli.main(["presets"]) == 2
    assert capsys.readouterr().err == "simgen: error: x.json: damaged\n"


def test_unknown_preset_key(tmp_path):
    preset = tmp_path / "bad.yaml"
    preset.write_text("actors:\n  pedestrians_per_km: 10\n  unicorns: 3\n")
    msg = _bad(tmp_path, "--scenes", "1", "--preset", preset)
    assert str(preset) in msg and "actors" in msg and "unicorns" in msg


def test_out_of_range_preset_value(tmp_path):
    preset = tmp_path / "bad.yaml"
    preset.write_text("lidar:\n  max_range: 300\n")
    msg = _bad(tmp_path, "--scenes", "1", "--preset", preset)
    assert "lidar.max_range" in msg and "[70.0, 100.0]" in msg


@pytest.mark.parametrize("args, needle", [
    (("--scenes", "-3"), "--scenes"),
    (("--scenes", "1", "--resolution", "0x0"), "--resolution"),
    (("--scenes", "1", "--preset", "no_such_preset"), "no_such_preset"),
    (("--scenes", "1", "--workers", "0"), "--workers"),
    (("--scenes", "1", "--val-fraction", "1.5"), "--val-fraction must be in [0, 1]"),
])
def test_bad_arguments(tmp_path, args, needle):
    assert needle in _bad(tmp_path, *args)


def test_the_splits_and_a_set_for_evaluation_only():
    from simgen.writer import split_scenes
    names = [f"scene-{i:04d}" for i in range(5)]
    assert split_scenes(names, 0.2) == {"sim-train": names[:4], "sim-val": names[4:]}
    assert split_scenes(names, 0.0) == {"sim-train": names[:4], "sim-val": names[4:]}     # one val scene at least
    assert split_scenes(names, 0.99) == {"sim-train": names[:1], "sim-val": names[1:]}    # one train scene at least
    assert split_scenes(names, 1.0) == {"sim-train": [], "sim-val": names}
    assert split_scenes(names[:1], 1.0) == {"sim-train": [], "sim-val": names[:1]}


def test_unwritable_out(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("a file, not a folder")
    proc = run_simgen("make", "--scenes", "1", "--out", blocker / "data", check=False)
    assert proc.returncode == 2 and "--out" in proc.stderr and "Traceback" not in proc.stderr
    assert blocker.read_text() == "a file, not a folder"


def test_presets_and_help():
    proc = run_simgen("presets")
    names = [ln.split()[0] for ln in proc.stdout.splitlines()]
    assert {"urban", "dense_urban", "tiny"} <= set(names)
    help_text = run_simgen("make", "--help").stdout
    for flag in ("--scenes", "--preset", "--seed", "--workers", "--samples-per-scene", "--resolution", "--version"):
        assert flag in help_text


def test_check_reports_a_truncated_file(tiny_dataset, tmp_path):
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset, copy)
    pcd = next((copy / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    pcd.write_bytes(pcd.read_bytes()[:-7])
    proc = run_simgen("check", copy, check=False)
    assert proc.returncode == 1 and pcd.name in proc.stdout and "truncated" in proc.stdout
    seg = next((copy / "lidarseg" / "v1.0-sim").glob("*_lidarseg.bin"))
    seg.write_bytes(seg.read_bytes()[:-3])                 # a label file short of its sweep's points
    proc = run_simgen("check", copy, check=False)
    assert proc.returncode == 1 and f"{seg.name}: {seg.stat().st_size} labels for the" in proc.stdout
    (copy / "v1.0-sim" / "sample.json").write_text("[{")
    proc = run_simgen("check", copy, check=False)
    assert proc.returncode == 2 and "sample.json" in proc.stderr and "Traceback" not in proc.stderr


def test_show_writes_the_contact_sheet(tiny_dataset, tmp_path):
    """Six cameras in two rows and the lidar BEV beside them, its points in lidarseg colours."""
    import cv2
    import numpy as np
    out = tmp_path / "sheet.png"
    proc = run_simgen("show", tiny_dataset, "--sample", "1", "--out", out)
    assert proc.returncode == 0 and str(out) in proc.stdout
    sheet = cv2.imread(str(out))
    h, w = sheet.shape[:2]
    assert w == 3 * 640 + h                       # three 640-px camera tiles, then a square BEV
    bev = sheet[:, w - h:]
    road = np.all(bev == (191, 207, 0), axis=-1).sum()          # flat.driveable_surface, BGR
    building = np.all(bev == (135, 184, 222), axis=-1).sum()    # static.manmade
    assert road > 500 and building > 100, (road, building)
    proc = run_simgen("show", tiny_dataset, "--sample", "99", "--out", out, check=False)
    assert proc.returncode == 2 and "--sample 99" in proc.stderr and "Traceback" not in proc.stderr
