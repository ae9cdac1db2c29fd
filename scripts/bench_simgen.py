"""The generator's benchmarks: lidar, rendering, `simgen make` (one and two workers, scaling,
the Ray backend), a worker's memory, the path tracer and the demo. Keys: see scripts/bench.py.

Run as ``python scripts/bench_simgen.py worker_memory OUT N`` it is the child process that
generates N scenes one after another and reports its own RSS (``bench_worker_memory``).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_common import ROOT, child_main, median_ms, run_child, run_make


def bench_lidar(repeats: int) -> dict:
    """One urban sweep on all cores and on one thread (alternating), and the bare Embree floor."""
    import trimesh

    from simgen import geometry as geo
    from simgen.config import load_preset
    from simgen.lidar import LidarScanner, RayTarget
    from simgen.pipeline import build_world
    from simgen.settings import MakeSettings
    cfg = load_preset("urban")
    world = build_world(MakeSettings(cfg, 1, 0, 10, "v1.0-sim"), 0)
    threads = len(os.sched_getaffinity(0))
    scanner = LidarScanner(cfg.lidar, world, threads=threads)
    single = LidarScanner(cfg.lidar, world, threads=1)
    rng = np.random.default_rng(0)
    t = 1.0
    scanner.scan(t, rng)
    single.scan(t, rng)
    # Alternating, so that both see the same machine load.
    a, b = [], []
    for _ in range(repeats):
        a.append(median_ms(lambda: scanner.scan(t, rng), 1))
        b.append(median_ms(lambda: single.scan(t, rng), 1))
    sweep_ms, sweep_1_ms = float(np.median(a)), float(np.median(b))
    # The floor: the whole scene at t as one mesh, the same rays, bare intersects_first.
    boxes = world.boxes_at(t)
    meshes = [world.static_mesh] + [a.mesh.copy().apply_transform(geo.pose_2d(*boxes[i, :2], boxes[i, 6], boxes[i, 2]))
                                    for i, a in enumerate(world.actors) if a.annotate]
    scene_mesh = trimesh.util.concatenate(meshes)
    target = RayTarget(scene_mesh, np.zeros(len(scene_mesh.faces)))
    _, origin, dirs = scanner.sweep_rays(t)
    target.first_triangles(origin, dirs)
    floor_ms = median_ms(lambda: target.first_triangles(origin, dirs), repeats)
    return {"lidar_ms_per_sweep": sweep_ms, "lidar_ms_per_sweep_1_thread": sweep_1_ms, "lidar_threads": threads,
            "lidar_embree_floor_ms": floor_ms, "lidar_rays_per_sweep": len(dirs)}


def bench_render(repeats: int) -> dict:
    """One 1600x900 camera of an urban world: rgb + depth + id pass."""
    from simgen import geometry as geo
    from simgen import rig
    from simgen.camera import Renderer
    from simgen.config import load_preset
    from simgen.pipeline import build_world
    from simgen.settings import MakeSettings
    cfg = load_preset("urban")
    world = build_world(MakeSettings(cfg, 1, 0, 10, "v1.0-sim"), 0)
    r = Renderer(cfg.camera)
    r.set_world(world, key=0)
    cam = rig.cameras(cfg.camera.resolution)[0]
    b = world.boxes_at(1.0)
    poses = {a.id: geo.pose_2d(*b[i, :2], b[i, 6], b[i, 2]) for i, a in enumerate(world.actors) if a.annotate}
    T_global_from_cam = world.ego_pose(1.0) @ cam.T_ego_from_cam
    r.render(cam, T_global_from_cam, poses)
    ms = median_ms(lambda: r.render(cam, T_global_from_cam, poses), repeats)
    r.close()
    return {"render_ms_per_image_1600x900": ms}


SPIN = "x = 0\nfor i in range(20_000_000):\n    x += i\n"


def cpu_ceiling_2_procs() -> float:
    """The machine's own limit on a 2-process speedup, now: a pure-Python loop run alone
    (twice, one after the other) against two copies at once. Shared or virtual cores give less
    than 2."""
    def run(n: int) -> float:
        t = time.perf_counter()
        procs = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(n)]
        for proc in procs:
            proc.wait()
        return time.perf_counter() - t
    serial = run(1) + run(1)
    return serial / run(2)


def make_pairs(tmp: Path, pairs: int, n: int, k: int, res: str) -> dict:
    """One and two workers alternately, a fresh dataroot each time, each pair followed by the
    CPU ceiling: the ratios of a pair see the same machine load; medians are reported."""
    t1, t2, ceil = [], [], []
    for r in range(pairs):
        t1.append(run_make(tmp / f"w1_{n}_{r}", n, k, 1, res))
        t2.append(run_make(tmp / f"w2_{n}_{r}", n, k, 2, res))
        ceil.append(cpu_ceiling_2_procs())
    ratios = [a / b for a, b in zip(t1, t2)]
    return {"speedup": float(np.median(ratios)), "runs": [round(r, 3) for r in ratios],
            "ceiling": float(np.median(ceil)), "ceiling_runs": [round(c, 3) for c in ceil],
            "t1": float(np.median(t1)), "t2": float(np.median(t2))}


def bench_make(quick: bool) -> dict:
    """A whole 1600x900 sample on one worker, and the 2-worker speedup of `make`."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        samples = 4 if quick else 10
        sample_s = run_make(tmp / "one", 1, samples, 1, "1600x900") / samples
        n, k, res = (2, 2, "800x450") if quick else (4, 6, "800x450")
        m = make_pairs(tmp, 1 if quick else 3, n, k, res)
    return {"sample_s_1600x900": sample_s, "make_speedup_2_workers": m["speedup"],
            "make_speedup_2_workers_runs": m["runs"],
            "cpu_ceiling_2_procs": m["ceiling"], "cpu_ceiling_2_procs_runs": m["ceiling_runs"],
            "make_1_worker_s": m["t1"], "make_2_workers_s": m["t2"]}


WEATHER_CONDITIONS = {"rain50": ("--rain", "50"), "snow2.5": ("--snow", "2.5"), "night": ("--night",),
                      "rain25_snow1_night": ("--rain", "25", "--snow", "1", "--night")}


def bench_weather(quick: bool) -> dict:
    """A whole 1600x900 sample under each weather against the clear day: `make` of one urban
    scene (one worker), clear and weather alternately with a fresh dataroot each time, so each
    pair's ratio sees the same machine load; the median ratio and every pair are reported."""
    samples, pairs = (2, 1) if quick else (4, 3)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, flags in WEATHER_CONDITIONS.items():
            ratios = []
            for r in range(pairs):
                clear = run_make(tmp / f"clear_{name}_{r}", 1, samples, 1, "1600x900")
                weather = run_make(tmp / f"{name}_{r}", 1, samples, 1, "1600x900", flags=flags)
                ratios.append(weather / clear)
                shutil.rmtree(tmp / f"clear_{name}_{r}")
                shutil.rmtree(tmp / f"{name}_{r}")
            out[f"weather_sample_ratio_{name}"] = float(np.median(ratios))
            out[f"weather_sample_ratio_{name}_runs"] = [round(x, 3) for x in ratios]
    return out


def bench_scaling(quick: bool) -> dict:
    """The worker speedup on a longer run (16 scenes x 6 samples, 800x450), where the fixed
    costs of a run (interpreter, imports, compiled-kernel load, the last scene's wait) weigh
    less than in the 4-scene `make` pairs."""
    with tempfile.TemporaryDirectory() as tmp:
        m = make_pairs(Path(tmp), 1 if quick else 2, 8 if quick else 16, 6, "800x450")
    return {"make_speedup_2_workers_16_scenes": m["speedup"], "make_speedup_2_workers_16_scenes_runs": m["runs"],
            "cpu_ceiling_2_procs_16_scenes": m["ceiling"],
            "make_16_scenes_1_worker_s": m["t1"], "make_16_scenes_2_workers_s": m["t2"]}


def bench_worker_memory(quick: bool) -> dict:
    """Scenes one after another in one process (as a worker runs them): peak and growth of RSS."""
    n = 3 if quick else 8
    with tempfile.TemporaryDirectory() as tmp:
        r = run_child("bench_simgen", "worker_memory", tmp, n)
    return {"worker_peak_rss_mb": r["peak"], "worker_rss_growth_mb": r["rss"][-1] - r["rss"][1],
            "worker_rss_per_scene_mb": [round(v) for v in r["rss"]]}


def worker_memory(out: str, n_scenes: str) -> dict:
    """(Child process) RSS after each of ``n_scenes`` urban scenes of 2 samples, and the peak."""
    import resource

    from simgen.config import load_preset
    from simgen.pipeline import generate_scene
    from simgen.settings import MakeSettings
    s = MakeSettings(load_preset("urban"), int(n_scenes), 0, 2, "v1.0-sim")
    rss = []
    for i in range(s.n_scenes):
        generate_scene(s, Path(out), i)
        with open("/proc/self/statm") as f:
            rss.append(int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20)
    return {"rss": rss, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


MITSUBA_SPP = 16


def bench_mitsuba(quick: bool) -> dict:
    """One 800x450 camera image path-traced by Mitsuba (rgb pass only) at MITSUBA_SPP."""
    from simgen import rig
    from simgen.config import load_preset, with_resolution
    from simgen.mitsuba_camera import MitsubaRenderer, actor_poses_at
    from simgen.pipeline import build_world
    from simgen.settings import MakeSettings
    cfg = with_resolution(load_preset("urban"), 800, 450)
    world = build_world(MakeSettings(cfg, 1, 0, 1, "v1.0-sim"), 0)
    cam = rig.cameras(cfg.camera.resolution)[0]
    T_global_from_cam = world.ego_pose(0.5) @ cam.T_ego_from_cam
    poses = actor_poses_at(world, 0.5)
    r = MitsubaRenderer(cfg.camera, spp=MITSUBA_SPP)
    try:
        ms = median_ms(lambda: r.render(world, cam, T_global_from_cam, poses, with_ids=False), 2 if quick else 3)
    finally:
        r.close()
    return {"mitsuba_s_per_image_800x450": ms / 1000, "mitsuba_spp": MITSUBA_SPP, "mitsuba_variant": r.variant}


def bench_demo(quick: bool) -> dict:
    """`bash scripts/demo.sh` from scratch (its data and run folders removed first)."""
    for sub in ("data", "run", "eval"):
        shutil.rmtree(ROOT / "demo_out" / sub, ignore_errors=True)
    t0 = time.perf_counter()
    subprocess.run(["bash", "scripts/demo.sh"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    timing = json.loads((ROOT / "demo_out" / "timing.json").read_text())
    return {"demo_total_s": time.perf_counter() - t0, **{f"demo_{k}": v for k, v in timing.items() if k != "scenes"}}


def bench_ray(quick: bool) -> dict:
    """`make --ray` (a local Ray instance of 2 CPUs) against the local pool of 2 workers: 8 urban
    scenes x 10 samples at the preset's 1600x900, as `simgen make` makes them by default. Pairs
    alternate which goes first, on fresh dataroots; the overhead is 100 (t_ray / t_pool - 1), the
    median of the pairs. Also the size of a scene's part (every file it writes) per sample."""
    n, k, res = (2, 2, "800x450") if quick else (8, 10, "")
    pool_s, ray_s, part_mb = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(1 if quick else 3):
            runs = [("pool", []), ("ray", ["--ray"])]
            for name, extra in runs if r % 2 == 0 else runs[::-1]:
                out = Path(tmp) / f"{name}{r}"
                cmd = [sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--scenes", str(n),
                       "--samples-per-scene", str(k), "--workers", "2", "--preset", "urban", "--quiet", *extra]
                cmd += ["--resolution", res] if res else []
                t = time.perf_counter()
                subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
                (ray_s if extra else pool_s).append(time.perf_counter() - t)
                files = [p for p in out.rglob("*") if p.is_file() and "v1.0-sim" not in p.parts]
                part_mb.append(sum(p.stat().st_size for p in files) / 1e6 / (n * k))
                shutil.rmtree(out)
    pct = [100 * (b / a - 1) for a, b in zip(pool_s, ray_s)]
    return {"make_ray_overhead_pct": float(np.median(pct)), "make_ray_overhead_pct_runs": [round(v, 1) for v in pct],
            "make_ray_pairs_s": [[round(a, 1), round(b, 1)] for a, b in zip(pool_s, ray_s)],
            "make_ray_part_mb_per_sample": round(float(np.median(part_mb)), 2)}


if __name__ == "__main__":
    child_main({"worker_memory": worker_memory})
