"""The weather as a dataset setting: validated flags, recorded, and paired with the clear day
(the same world, poses, labels and tokens; the lidar unchanged at night; rate 0 is the clean set)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from conftest import TINY_ARGS, run_simgen
from simgen.weather.particles import rain_extinction, snow_extinction

PAIRED = ("sample_annotation", "instance", "sample", "ego_pose", "sample_data", "calibrated_sensor")


def _files(root: Path, folder: str) -> dict[str, bytes]:
    """Every file under ``root/folder``, by its path relative to ``root``."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted((root / folder).rglob("*")) if p.is_file()}


def test_bad_weather_flags_exit_2_with_one_line(tmp_path):
    for args, needle in ((["--rain", "-1"], "--rain"), (["--snow", "nan"], "--snow"), (["--rain", "201"], "--rain"),
                         (["--snow", "25"], "--snow"), (["--night", "--renderer", "mitsuba"], "--night")):
        proc = run_simgen("make", "--out", tmp_path / "x", *TINY_ARGS, *args, check=False)
        assert proc.returncode == 2, (args, proc.stderr)
        line = proc.stderr.strip()
        assert len(line.splitlines()) == 1 and needle in line and "Traceback" not in line, line
        assert not (tmp_path / "x").exists()


def test_bad_weather_in_a_preset_names_the_file_and_field(tmp_path):
    from simgen.config import load_preset
    from simgen.errors import ConfigError
    for text, needle in (("weather:\n  rain: -3\n", "weather.rain"), ("weather:\n  hail: 2\n", "'hail'"),
                         ("weather:\n  night: 1\n", "weather.night"),
                         ("camera:\n  renderer: mitsuba\nweather:\n  night: true\n", "weather.night")):
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        try:
            load_preset(str(bad))
        except ConfigError as e:
            assert str(bad) in str(e) and needle in str(e) and "\n" not in str(e), str(e)
        else:
            raise AssertionError(f"accepted {text!r}")


def test_clear_weather_keeps_the_fingerprint_and_rate_0_is_the_clean_set(tmp_path, tiny_dataset):
    """`--rain 0 --snow 0` is the clean set, byte for byte, and resumes a clean set's parts."""
    from simgen.config import load_preset, with_weather
    from simgen.settings import MakeSettings
    cfg = load_preset("tiny")
    assert "weather" not in MakeSettings(cfg, 1, 0, 1, "v").fingerprint()
    assert MakeSettings(with_weather(cfg, rain=0.0, snow=0.0), 1, 0, 1, "v").fingerprint() == \
        MakeSettings(cfg, 1, 0, 1, "v").fingerprint()
    assert MakeSettings(with_weather(cfg, rain=5.0), 1, 0, 1, "v").fingerprint()["cfg"]["weather"]["rain"] == 5.0
    out = tmp_path / "zero"
    run_simgen("make", "--out", out, "--workers", "1", *TINY_ARGS, "--rain", "0", "--snow", "0")
    for folder in ("samples", "sweeps", "v1.0-sim"):
        assert _files(out, folder) == _files(tiny_dataset, folder), folder


def test_rain_snow_and_night_together_pair_with_the_clear_day(tmp_path, tiny_dataset):
    """Every setting combines with the others; the labels, the world's poses and the tokens stay
    the clear day's; the weather is recorded; the sensors' files change."""
    out = tmp_path / "storm"
    run_simgen("make", "--out", out, "--workers", "1", *TINY_ARGS, "--rain", "25", "--snow", "1", "--night",
               "--fog", "1")
    for table in PAIRED:
        assert (out / "v1.0-sim" / f"{table}.json").read_bytes() == \
               (tiny_dataset / "v1.0-sim" / f"{table}.json").read_bytes(), table
    rec = json.loads((out / "v1.0-sim" / "degradation.json").read_text())
    assert rec["weather"] == {"rain": 25.0, "snow": 1.0, "night": True} and rec["settings"]["fog"] == 1
    # The cameras see through the fog, the rain and the snowfall at once: their extinctions add.
    alpha = 0.005 + rain_extinction(25.0) + snow_extinction(1.0)
    assert rec["camera_extinction_per_m"] == pytest.approx(alpha, rel=1e-12)
    assert rec["camera_visibility_m"] == pytest.approx(math.log(20.0) / alpha, rel=1e-12)
    scene = json.loads((out / "v1.0-sim" / "scene.json").read_text())[0]
    assert "rain 25 mm/h" in scene["description"] and "night" in scene["description"]
    clean, storm = _files(tiny_dataset, "samples"), _files(out, "samples")
    assert clean.keys() == storm.keys()
    changed = [k for k in clean if clean[k] != storm[k]]
    assert any("LIDAR_TOP" in k for k in changed) and any("CAM_" in k for k in changed)


def test_night_alone_keeps_every_lidar_byte(tmp_path, tiny_dataset):
    """The lidar is an active sensor: at night its sweeps are the day's, byte for byte; only the
    camera images change."""
    out = tmp_path / "night"
    run_simgen("make", "--out", out, "--workers", "1", *TINY_ARGS, "--night")
    day, night = _files(tiny_dataset, "samples"), _files(out, "samples")
    lidar = [k for k in day if "LIDAR_TOP" in k]
    assert lidar and all(day[k] == night[k] for k in lidar)
    assert _files(tiny_dataset, "sweeps") == _files(out, "sweeps")
    assert all(day[k] != night[k] for k in day if "CAM_" in k)
    lidarseg = _files(tiny_dataset, "lidarseg")
    assert lidarseg and lidarseg == _files(out, "lidarseg")


def test_fog_at_night_scatters_the_night_sky_not_daylight():
    """Koschmieder's airlight is the light the fog scatters: at night the night sky's, so the fogged
    sky and the far road are dark (the day's airlight would paint a bright veil on a night image)."""
    import numpy as np
    from simgen import degrade, rig
    from simgen.config import load_preset, with_degradation, with_weather
    from simgen.sensor_effects import degrade_image
    from simgen.settings import MakeSettings, weather_streams
    from simgen.weather import veil
    cam = rig.cameras((160, 90))[0]
    depth = np.zeros((90, 160), np.float32)
    depth[45:] = 400.0                                       # the lower half far away, the upper half sky
    dark = np.full((90, 160, 3), 5, np.uint8)
    for night, airlight in ((False, degrade.AIRLIGHT), (True, veil.rendered_sky(True))):
        cfg = with_weather(with_degradation(load_preset("tiny"), fog=5), night=night)
        s = MakeSettings(cfg, 1, 0, 1, "v1.0-sim")
        img = degrade_image(dark, depth, cam, cfg, s, 0, 0, weather_streams(s, 0), 0.0).astype(float)
        # fog 5 over 400 m leaves exp(-24) of the scene: sky and far road are the airlight (plus the
        # night's zero-mean sensor noise, averaged out over the patch)
        assert np.abs(img.reshape(-1, 3).mean(0) - airlight).max() < 1.5, (night, img.reshape(-1, 3).mean(0))
