"""`simgen make`: the scenes of a dataset in worker processes or Ray tasks, with a progress bar,
resumable.

This module and what it imports stay light (no trimesh, pyrender or Embree): the coordinating
process only checks the dataroot, hands out scene indices and merges the tables. Each worker
imports :mod:`simgen.pipeline` itself.
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

from . import degrade as D
from . import writer as W
from .config import ConfigError
from .settings import MakeSettings, scene_rng


def _worker_init(gl):
    # llvmpipe keeps its default thread count in every worker: measured, 2 workers with 2 render
    # threads each finish sooner here than with 1 each (33.8 s against 36.7 s, 4 scenes).
    if gl:
        os.environ["PYOPENGL_PLATFORM"] = gl


def _task(args):
    from .pipeline import generate_scene
    s, dataroot, idx, threads = args
    return idx, generate_scene(s, dataroot, idx, threads)


def check_resume(s: MakeSettings, dataroot: Path) -> list[int]:
    """Scenes still to do. Refuses a dataroot that holds parts made with other settings."""
    settings_file = dataroot / W.PARTS_DIR / "settings.json"
    fp = json.loads(W.dump_json(s.fingerprint()))
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
    W.write_atomic(settings_file, W.dump_json(fp))
    return [i for i in range(s.n_scenes) if not W.part_path(dataroot, i).exists()]


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
    """``<version>/degradation.json``: every degradation setting, the derived fog extinction and
    visibility, the dropped rings per scene, and the pairing contract. Written for clean sets
    too (all off), so that a set always says what it is."""
    d = s.cfg.degrade
    rings = {f"scene-{i:04d}": [int(r) for r in D.choose_rings(d.beam_drop, scene_rng(s.seed, i, 2))]
             for i in range(s.n_scenes)} if d.beam_drop else {}
    record = {
        "settings": dataclasses.asdict(d),
        "fog_alpha_per_m": d.alpha,
        "fog_visibility_m": D.visibility_of(d.alpha) if d.alpha > 0 else None,
        "failed_sensors": list(d.dropped),
        "dropped_rings": rings,
        "preset": s.cfg.name,
        "seed": s.seed,
        "labels": ("clean world: sample_annotation, instance, sample and ego_pose equal those of the "
                   "undegraded run with the same preset, seed and scene count"
                   if d.occlusion == "none" else
                   "occluders are part of the world: the same objects, tracks and poses as the clean run, but "
                   "sample_annotation visibility and num_lidar_pts reflect the occluders"),
    }
    W.write_atomic(dataroot / s.version / "degradation.json", W.dump_json(record))


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
        scenes = cluster.scenes(s, dataroot, todo) if cluster else _pool_scenes(s, dataroot, todo, workers)
        with closing(scenes) as results:
            for _idx, n in results:
                done_samples += n
                bar.update(1)
                bar.set_postfix(samples_per_s=f"{done_samples / (time.perf_counter() - start):.2f}")
    finally:
        if bar is not None:
            bar.close()
        if cluster is not None:
            cluster.close()
    counts = W.merge(dataroot, s.version, s.n_scenes, s.val_fraction)
    write_degradation_record(s, dataroot)
    return {"scenes": s.n_scenes, "generated_scenes": len(todo), "samples": counts["sample"],
            "seconds": time.perf_counter() - start, "tables": counts}


def _pool_scenes(s: MakeSettings, dataroot: Path, todo: list[int], workers: int) -> Iterator[tuple[int, int]]:
    """The scenes ``todo`` on a local process pool (each worker writes its scene's files into
    ``dataroot``); yields ``(scene index, samples)`` in completion order."""
    n_proc = max(1, min(workers, len(todo)))
    # The cores left to each worker process cast its lidar rays in parallel.
    threads = max(1, len(os.sched_getaffinity(0)) // n_proc)
    tasks = [(s, dataroot, i, threads) for i in todo]
    if n_proc == 1:
        yield from map(_task, tasks)
        return
    ctx = mp.get_context("spawn")
    pool = ctx.Pool(n_proc, initializer=_worker_init, initargs=(s.gl,))
    try:
        yield from pool.imap_unordered(_task, tasks)
    finally:
        # Every result is in (or the run is being abandoned): the workers hold nothing
        # unwritten, since a scene's part file is its last, atomic write. Stopping them
        # spares the wait for their interpreters to finalise (about 0.7 s with 2 workers).
        pool.terminate()
        pool.join()
