"""Strict preset loading: every shipped preset loads, and every kind of bad input is one clear line."""
from __future__ import annotations

import dataclasses

import pytest

from simgen.config import LidarConfig, SceneConfig, list_presets, load_preset, with_degradation, with_resolution
from simgen.errors import ConfigError, InputError


def write(tmp_path, text, name="preset.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def config_error(path_or_name) -> str:
    with pytest.raises(ConfigError) as info:
        load_preset(str(path_or_name))
    msg = str(info.value)
    assert "\n" not in msg and msg.strip() == msg and msg, repr(msg)
    assert isinstance(info.value, InputError)
    return msg


def test_all_shipped_presets_load():
    presets = list_presets()
    assert {"tiny", "urban", "dense_urban"} <= set(presets)
    for name, path in presets.items():
        cfg = load_preset(name)
        assert isinstance(cfg, SceneConfig)
        assert cfg.name == name
        assert cfg.source == path.read_text()
        assert cfg.description
        # loading by path gives the same settings
        by_path = load_preset(str(path))
        assert dataclasses.replace(by_path, name=name) == cfg


def test_preset_values_are_applied():
    tiny = load_preset("tiny")
    assert (tiny.layout.blocks_x, tiny.layout.blocks_y, tiny.layout.block_pitch) == (2, 2, 70.0)
    assert tiny.layout.lanes_per_direction == 1
    assert tiny.camera.resolution == (400, 225)
    assert isinstance(tiny.layout.blocks_x, int) and isinstance(tiny.layout.block_pitch, float)
    assert tiny.lidar == LidarConfig()                     # left-out sections take the defaults


def test_empty_file_gives_defaults(tmp_path):
    path = write(tmp_path, "")
    cfg = load_preset(str(path))
    assert dataclasses.replace(cfg, name="custom", source="") == SceneConfig()
    assert cfg.name == str(path)


def test_valid_custom_file(tmp_path):
    path = write(tmp_path, "layout:\n  blocks_x: 4\n  building_height: [5, 40]\nego:\n  speed: [2.0, 2.0]\n"
                           "actors:\n  vehicle_mix: {car: 1, bus: 3}\n")
    cfg = load_preset(str(path))
    assert cfg.layout.blocks_x == 4 and cfg.layout.building_height == (5.0, 40.0)
    assert cfg.ego.speed == (2.0, 2.0)                     # min == max is allowed
    assert cfg.actors.vehicle_mix == {"car": 1.0, "bus": 3.0}


@pytest.mark.parametrize("text, field, extra", [
    # unknown key in a section; the message lists the allowed keys
    ("actors:\n  pedestrians_per_kilometre: 5\n", "actors", ["pedestrians_per_kilometre", "pedestrians_per_km"]),
    # unknown top-level section
    ("sensors:\n  lidar: 1\n", None, ["sensors", "layout"]),
    # wrong types
    ("actors:\n  pedestrians_per_km: lots\n", "actors.pedestrians_per_km", ["lots"]),
    ("layout:\n  blocks_x: true\n", "layout.blocks_x", []),
    ("layout:\n  blocks_x: 2.5\n", "layout.blocks_x", ["integer"]),
    ("description: 3\n", "description", ["string"]),
    ("layout: 3\n", "layout", ["mapping"]),
    ("layout:\n  building_height: 12\n", "layout.building_height", []),
    ("layout:\n  building_height: [3, 9, 12]\n", "layout.building_height", []),
    ("actors:\n  vehicle_mix: {car: 1, tractor: 2}\n", "actors.vehicle_mix", ["tractor"]),
    ("actors:\n  vehicle_mix: {car: 0}\n", "actors.vehicle_mix", []),
    # out of range: the message gives the allowed range
    ("actors:\n  pedestrians_per_km: -1\n", "actors.pedestrians_per_km", ["0.0", "1000.0"]),
    ("layout:\n  blocks_x: 13\n", "layout.blocks_x", ["1", "12"]),
    ("lidar:\n  max_range: 150\n", "lidar.max_range", ["70.0", "100.0"]),
    ("camera:\n  resolution: [1600, 0]\n", "camera.resolution", ["16", "4096"]),
    ("ego:\n  speed: [4, 20]\n", "ego.speed", ["15.0"]),
    # [min, max] given as [max, min]
    ("layout:\n  building_height: [30, 6]\n", "layout.building_height", ["min, max"]),
    ("ego:\n  speed: [12, 4]\n", "ego.speed", ["min, max"]),
    # not finite: NaN passes every comparison, so the range check alone would let it through
    ("lidar:\n  min_range: .nan\n", "lidar.min_range", ["finite", "nan"]),
    ("layout:\n  block_pitch: .inf\n", "layout.block_pitch", ["finite", "inf"]),
    ("ego:\n  speed: [4, .nan]\n", "ego.speed", ["finite"]),
    ("actors:\n  vehicle_mix: {car: .nan}\n", "actors.vehicle_mix.car", ["finite"]),
    ("layout:\n  building_gap: [8.0, 1.0]\n", "layout.building_gap", ["min, max"]),
])
def test_bad_field_is_one_line_naming_file_and_field(tmp_path, text, field, extra):
    path = write(tmp_path, text)
    msg = config_error(path)
    assert str(path) in msg
    if field is not None:
        assert f": {field}" in msg, msg
    for word in extra:
        assert word in msg, msg


def test_invalid_yaml(tmp_path):
    path = write(tmp_path, "layout:\n  blocks_x: [1, 2\n  blocks_y: 3\n")
    msg = config_error(path)
    assert str(path) in msg and "YAML" in msg


def test_tab_indented_yaml(tmp_path):
    path = write(tmp_path, "layout:\n\tblocks_x: 2\n")
    assert str(path) in config_error(path)


@pytest.mark.parametrize("text", ["- layout\n- actors\n", "just a string\n", "42\n"])
def test_non_mapping_top_level(tmp_path, text):
    path = write(tmp_path, text)
    msg = config_error(path)
    assert str(path) in msg and "mapping" in msg


def test_missing_file(tmp_path):
    path = tmp_path / "no_such_preset.yaml"
    msg = config_error(path)
    assert str(path) in msg
    assert "urban" in msg                           # it lists the presets that do exist


def test_unknown_preset_name():
    msg = config_error("no_such_preset_name")
    assert "no_such_preset_name" in msg and "tiny" in msg


def test_with_resolution():
    cfg = load_preset("tiny")
    out = with_resolution(cfg, 800, 450)
    assert out.camera.resolution == (800, 450)
    assert cfg.camera.resolution == (400, 225)                      # the input is not changed
    assert dataclasses.replace(out, camera=cfg.camera) == cfg
    for w, h in ((0, 450), (800, 0), (0, 0), (15, 450), (800, 4097), (-800, 450)):
        with pytest.raises(ConfigError) as info:
            with_resolution(cfg, w, h)
        msg = str(info.value)
        assert "\n" not in msg and f"{w}x{h}" in msg
    assert with_resolution(cfg, 16, 4096).camera.resolution == (16, 4096)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_flag_value(value):
    with pytest.raises(ConfigError) as info:
        with_degradation(load_preset("tiny"), fog_visibility=value)
    assert str(info.value) == f"--fog-visibility: expected a finite number, got {value!r}"


def test_configs_are_frozen():
    cfg = load_preset("tiny")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.layout.blocks_x = 5
