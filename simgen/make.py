"""`simgen make`: the scenes of a dataset in worker processes or Ray tasks, with a progress bar,
resumable.

Either backend makes each scene in memory (:func:`simgen.pipeline.scene_records`) and ships its
:class:`~simgen.writer.SceneRecords` back; this process writes each file once, the scene's table
part last, then merges the tables. This module and what it imports stay light (no trimesh,
pyrender or Embree): each worker imports :mod:`simgen.pipeline` itself.
"""
from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import os
import time
from contextlib import closing
from pathlib import Path
from typing import Iterator

from . import writer
from .degrade import visibility_of
from .errors import ConfigError
from .settings import MakeSettings, degradation_stream
from .weather.particles import rain_extinction, snow_extinction
from .writer import SceneRecords


def _worker_init(gl):
    # llvmpipe keeps its default render threads in every worker: one each made the pool slower.
    if gl:
        os.environ["PYOPENGL_PLATFORM"] = gl


def _task(args) -> SceneRecords:
    from .pipeline import scene_records
    s, idx, threads = args
    return scene_records(s, idx, threads)


def check_resume(s: MakeSettings, dataroot: Path) -> list[int]:
    """Scenes still to do. Refuses a dataroot that holds parts made with other settings."""
    settings_file = dataroot / writer.PARTS_DIR / "settings.json"
    fp = json.loads(writer.dump_json(s.fingerprint()))
    if settings_file.exists():
        try:
            old = json.loads(settings_file.read_text())
        except json.JSONDecodeError:
            old = None
        if old is not None and {k: v for k, v in old.items() if k != "n_scenes"} != fp:
            old_flat, new_flat = _flatten(old), _flatten(fp)
            differ = sorted(k for k in old_flat.keys() | new_flat.keys()
                            if k != "n_scenes" and old_flat.get(k) != new_flat.get(k))
            raise ConfigError(f"{dataroot}: holds a dataset made with other settings (differing: "
                              f"{', '.join(differ[:6])}{', ...' if len(differ) > 6 else ''}); "
                              f"use another --out or delete it")
    writer.write_atomic(settings_file, writer.dump_json(fp))
    return [i for i in range(s.n_scenes) if not writer.part_path(dataroot, i).exists()]


def _flatten(d: dict, prefix: str = "") -> dict:
    """Nested dicts -> {"a.b.c": leaf}."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def write_degradation_record(s: MakeSettings, dataroot: Path) -> None:
    """``<version>/degradation.json``: every degradation and weather setting, the derived fog
    extinction and visibility, the cameras' (fog, rain and snowfall together), the dropped rings per scene, and the pairing contract. Written for clean sets
    too (all off), so that a set always says what it is."""
    d = s.cfg.degrade
    w = s.cfg.weather
    camera_alpha = d.alpha + rain_extinction(w.rain) + snow_extinction(w.snow)
    rings = {f"scene-{i:04d}": [int(r) for r in degradation_stream(s, i)[0]]
             for i in range(s.n_scenes)} if d.beam_drop else {}
    record = {
        "settings": dataclasses.asdict(d),
        "fog_alpha_per_m": d.alpha,
        "fog_visibility_m": visibility_of(d.alpha) if d.alpha > 0 else None,
        # What the cameras see through: fog, rain and snowfall each attenuate by exp(-alpha d), so
        # their extinctions add; the visibility (MOR) is where a black object's contrast is 5 %.
        "camera_extinction_per_m": camera_alpha,
        "camera_visibility_m": visibility_of(camera_alpha) if camera_alpha > 0 else None,
        "failed_sensors": list(d.dropped),
        "dropped_rings": rings,
        "weather": dataclasses.asdict(s.cfg.weather),
        "preset": s.cfg.name,
        "seed": s.seed,
        "labels": ("clean world: sample_annotation, instance, sample and ego_pose equal those of the "
                   "undegraded run with the same preset, seed and scene count"
                   if d.occlusion == "none" else
                   "occluders are part of the world: the same objects, tracks and poses as the clean run, but "
                   "sample_annotation visibility and num_lidar_pts reflect the occluders"),
    }
    writer.write_atomic(dataroot / s.version / "degradation.json", writer.dump_json(record))


def make(s: MakeSettings, dataroot: Path, workers: int, progress: bool = True, ray: str | None = None) -> dict:
    """Generate (or finish) a dataset. Returns a summary with timings and table sizes.

    ``ray``: None runs the scenes on a local process pool of ``workers``; otherwise they are Ray
    tasks (:mod:`simgen.ray_backend`): ``"local"`` starts a Ray instance with ``workers`` CPUs,
    ``"auto"`` or ``"HOST:PORT"`` joins a cluster. The bytes are the same either way."""
    from tqdm import tqdm
    dataroot = Path(dataroot)
    start = time.perf_counter()
    cluster = None
    if ray is not None:
        # Joined before anything is written: an unreachable cluster leaves the dataroot untouched.
        from .ray_backend import RayRun
        cluster = RayRun.connect(ray, workers)
    bar = None
    try:
        todo = check_resume(s, dataroot)
        done_samples = 0
        bar = tqdm(total=s.n_scenes, initial=s.n_scenes - len(todo), unit="scene", disable=not progress,
                   desc="simgen make", dynamic_ncols=True)
        scenes = cluster.scenes(s, todo) if cluster else _pool_scenes(s, todo, workers)
        with closing(scenes) as results:
            for records in results:
                writer.write_scene(dataroot, records)
                done_samples += records.n_samples
                del records      # one finished scene at a time is held here
                bar.update(1)
                bar.set_postfix(samples_per_s=f"{done_samples / (time.perf_counter() - start):.2f}")
    finally:
        if bar is not None:
            bar.close()
        if cluster is not None:
            cluster.close()
    counts = writer.merge(dataroot, s.version, s.n_scenes, s.val_fraction)
    write_degradation_record(s, dataroot)
    return {"scenes": s.n_scenes, "generated_scenes": len(todo), "samples": counts["sample"],
            "seconds": time.perf_counter() - start, "tables": counts}


def _pool_scenes(s: MakeSettings, todo: list[int], workers: int) -> Iterator[SceneRecords]:
    """The scenes ``todo`` made on a local process pool; yields their records in completion order."""
    n_proc = max(1, min(workers, len(todo)))
    # The cores left to each worker process cast its lidar rays in parallel.
    threads = max(1, len(os.sched_getaffinity(0)) // n_proc)
    tasks = [(s, i, threads) for i in todo]
    if n_proc == 1:
        yield from map(_task, tasks)
        return
    ctx = mp.get_context("spawn")
    pool = ctx.Pool(n_proc, initializer=_worker_init, initargs=(s.gl,))
    try:
        yield from pool.imap_unordered(_task, tasks)
    finally:
        # Every result is in (or the run is being abandoned): the workers write nothing, so
        # stopping them loses nothing and spares the wait for their interpreters to finalise.
        pool.terminate()
        pool.join()
