"""A scene is made in memory and written by one writer: the records are the written scene, the
writer keeps its files inside the dataroot, and the dataset's record of the dropped lidar rings
is what the scans lost."""
from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import run_simgen
from simgen.config import load_preset
from simgen.errors import DataError
from simgen.settings import MakeSettings
from simgen.writer import PARTS_DIR, SceneRecords, dump_json, part_path, write_scene


def test_scene_records_are_the_written_scene(tiny_dataset):
    """Scene 1 of the tiny set (conftest's TINY_ARGS), made again in this process: every file's
    bytes and the part are those the command wrote, and nothing the scene wrote is missing."""
    from simgen.pipeline import scene_records
    s = MakeSettings(load_preset("tiny"), n_scenes=2, seed=7, samples_per_scene=3, version="v1.0-sim")
    records = scene_records(s, 1)
    assert records.index == 1 and records.n_samples == 3
    assert dump_json(records.tables) == part_path(tiny_dataset, 1).read_bytes()
    for rel, data in records.files.items():
        assert (tiny_dataset / rel).read_bytes() == data, rel
    referenced = {row["filename"] for row in records.tables["sample_data"] + records.tables["lidarseg"]}
    referenced |= {row["filename"] for row in records.tables["map"]}
    assert referenced == set(records.files)
    assert records.nbytes == sum(map(len, records.files.values())) + part_path(tiny_dataset, 1).stat().st_size


@pytest.mark.parametrize("rel", ["../escape.bin", "/etc/escape.bin", "samples/../../escape.bin",
                                 f"{PARTS_DIR}/scene-0000.json"])
def test_write_scene_keeps_files_inside_the_dataroot(tmp_path, rel):
    root = tmp_path / "data"
    records = SceneRecords(0, files={"maps/ok.png": b"png", rel: b"x"})
    with pytest.raises(DataError, match="not a path inside the dataroot"):
        write_scene(root, records)
    assert not root.exists() and not (tmp_path / "escape.bin").exists()


def test_write_scene_writes_the_part_last(tmp_path):
    records = SceneRecords(3, files={"samples/a.bin": b"a", "sweeps/b.bin": b"bb"})
    write_scene(tmp_path, records)
    assert (tmp_path / "samples/a.bin").read_bytes() == b"a" and (tmp_path / "sweeps/b.bin").read_bytes() == b"bb"
    part = part_path(tmp_path, 3)
    assert json.loads(part.read_text()) == records.tables
    assert part.stat().st_mtime_ns >= max(p.stat().st_mtime_ns for p in (tmp_path / "samples").iterdir())
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["a.bin", "b.bin", "scene-0003.json"]


def test_recorded_dropped_rings_are_the_rings_the_scans_lost(tmp_path):
    """degradation.json's rings per scene, against the ring column of every written sweep."""
    out = tmp_path / "drop"
    run_simgen("make", "--out", out, "--preset", "tiny", "--scenes", "2", "--samples-per-scene", "1",
               "--seed", "11", "--beam-drop", "6", "--workers", "1", "--quiet")
    record = json.loads((out / "v1.0-sim" / "degradation.json").read_text())
    sample_data = json.loads((out / "v1.0-sim" / "sample_data.json").read_text())
    scene_of_log = {f"simgen-11-{i:04d}": f"scene-{i:04d}" for i in range(2)}
    rings_seen = {name: set() for name in scene_of_log.values()}
    for sd in sample_data:
        if sd["fileformat"] == "pcd":
            points = np.fromfile(out / sd["filename"], dtype=np.float32).reshape(-1, 5)
            log = sd["filename"].split("/")[-1].split("__")[0]
            rings_seen[scene_of_log[log]] |= set(points[:, 4].astype(int).tolist())
    assert set(record["dropped_rings"]) == set(rings_seen)
    for scene, dropped in record["dropped_rings"].items():
        assert len(dropped) == 6 and len(set(dropped)) == 6
        assert rings_seen[scene] == set(range(32)) - set(dropped), scene
    assert record["dropped_rings"]["scene-0000"] != record["dropped_rings"]["scene-0001"]


def test_the_coordinating_process_stays_light():
    """The driver of `simgen make` writes and merges; it imports no renderer, ray caster or
    compiler (each worker imports the pipeline itself)."""
    import subprocess
    import sys
    code = ("import sys, simgen.make, simgen.ray_backend, simgen.writer; "
            "print(sorted(m for m in ('trimesh', 'pyrender', 'embreex', 'numba', 'ray') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "[]"
