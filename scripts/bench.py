#!/usr/bin/env python
"""The project's benchmarks. Prints one JSON object (``--json``) or a table.

Medians over repeats, because machines are shared and noisy. Keys (simgen):
  lidar_ms_per_sweep            one HDL-32E sweep of an urban world, all of LidarScanner.scan, with
                                the work split over all cores (as a single `make` worker runs it)
  lidar_ms_per_sweep_1_thread   the same on one thread (as each of `cores` workers runs it)
  lidar_embree_floor_ms         bare Embree intersects_first on the same scene (one posed mesh) and rays
  render_ms_per_image_1600x900  one camera: rgb + depth + id pass
  sample_s_1600x900             one worker, a whole sample (6 cameras, 10 sweeps, labels, writing)
  make_speedup_2_workers        `make` wall time with 1 worker / with 2 workers (4 scenes x 6 samples,
                                800x450; median of 3 alternating pairs, each pair's ratio listed)
  cpu_ceiling_2_procs           the machine's own 2-process speedup on a pure-Python loop, measured
                                after each of those pairs: what make_speedup_2_workers can reach
  make_speedup_2_workers_16_scenes
                                the same ratio on 16 scenes (2 pairs; only with --only scaling,
                                about 6 min), where a run's fixed costs weigh less
  worker_peak_rss_mb            peak RSS of a make worker over many scenes
  worker_rss_growth_mb          RSS after the last scene minus after the second (the first scene
                                warms caches up); about 0 when nothing leaks
Keys (clfbev, CPU, one torch thread per process unless said):
  train_tiny_samples_per_s      tiny `full`: forward + backward + AdamW step, one generated sample
  infer_tiny_ms                 tiny `full`: predict on one sample (median)
  train_tiny_peak_rss_mb        peak RSS of the process running the training steps
  paper_params_m, paper_gflops  the paper config's `full` model (FLOPs by torch.utils.flop_counter)
  attn_ms_exact_64x64 (+ _peak_mb), attn_ms_scalable_180x180 (+ _peak_mb): one MCM-sized
                                attention (B=1, 64 channels, 4 heads) in exact mode on 64x64 and in
                                the scalable modes (window 8, pooled stride 4) on 180x180
  eval_s_per_100_samples        clfbev predict + official DetectionEval (tiny, 1 thread), per 100
                                samples (with its two parts)
Keys (degradation and renderers):
  fog_overhead_pct              fog on one 1600x900 sample's 6 images and 10 sweeps (timed alone),
                                as a share of sample_s_1600x900 (measured in the same run)
  lidar_fog_*                   one urban sweep (world 0, t = 0.05 s) under fog severity 0..5, from
                                degrade.fog_returns' per-ray bookkeeping, bands by the clean range
                                (0-10, 10-30, 30-50, 50+ m; the kept ratio without 0-10):
    _points_by_severity, _returns_by_severity   points delivered, of which fog returns
    _returns_by_band            fog returns per band, per severity
    _silent_rays_by_severity    rays whose attenuated hard return reaches min_return (the lidar
                                equation) but which report nothing; 0 in strongest-return physics
    _equation_by_band           hard returns the lidar equation alone keeps (severity 1..5)
    _kept_ratio_by_band         hard returns delivered / _equation_by_band (severity 1..5)
    _won_share_by_band          share of the _equation_by_band rays the fog wins (1 - kept ratio)
    _intensity_0_by_severity    clean returns whose attenuated 8-bit intensity round(i exp(-2 alpha R))
                                is 0: an intensity-ratio fog (Hahner et al.'s real-data procedure)
                                turns exactly these into fog returns on this sweep (docs/fog.md)
  mitsuba_s_per_image_800x450   one path-traced camera image (rgb pass) at mitsuba_spp
  demo_total_s                  `bash scripts/demo.sh` from scratch (only with --only demo)
Keys (cluster backend, only with --only ray, about 8 min):
  make_ray_overhead_pct         `make --ray` (a local Ray instance, 2 CPUs) against the local pool of 2
                                workers, 8 urban scenes x 10 samples at 1600x900: 100 (t_ray / t_pool - 1),
                                median of 3 alternating pairs (each listed, and their seconds)
  make_ray_part_mb_per_sample   the bytes a scene sends back to the driver (all its files), per sample
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(times))


def bench_lidar(repeats: int) -> dict:
    import trimesh
    from simgen import geometry as geo
    from simgen.config import load_preset
    from simgen.lidar import LidarScanner, RayTarget
    from simgen.pipeline import MakeSettings, build_world
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
    from simgen import geometry as geo
    from simgen import rig
    from simgen.camera import Renderer
    from simgen.config import load_preset
    from simgen.pipeline import MakeSettings, build_world
    cfg = load_preset("urban")
    world = build_world(MakeSettings(cfg, 1, 0, 10, "v1.0-sim"), 0)
    r = Renderer(cfg.camera)
    r.set_world(world, key=0)
    cam = rig.cameras(cfg.camera.resolution)[0]
    b = world.boxes_at(1.0)
    poses = {a.id: geo.pose_2d(*b[i, :2], b[i, 6], b[i, 2]) for i, a in enumerate(world.actors) if a.annotate}
    T = world.ego_pose(1.0) @ cam.T_ego_from_cam
    r.render(cam, T, poses)
    ms = median_ms(lambda: r.render(cam, T, poses), repeats)
    r.close()
    return {"render_ms_per_image_1600x900": ms}


def run_make(out: Path, scenes: int, samples: int, workers: int, resolution: str, preset: str = "urban") -> float:
    cmd = [sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--scenes", str(scenes),
           "--samples-per-scene", str(samples), "--workers", str(workers), "--preset", preset, "--quiet"]
    if resolution:
        cmd += ["--resolution", resolution]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


SPIN = "x = 0\nfor i in range(20_000_000):\n    x += i\n"


def cpu_ceiling_2_procs() -> float:
    """The machine's own limit on a 2-process speedup, now: a pure-Python loop run alone
    (twice, one after the other) against two copies at once. Shared or virtual cores give less
    than 2 (measured 1.4-2.0 on a 2-vCPU VM)."""
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
    code = """
import os, resource, sys, json
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
from pathlib import Path
from simgen.config import load_preset
from simgen.pipeline import MakeSettings, generate_scene
s = MakeSettings(load_preset("urban"), int(sys.argv[2]), 0, 2, "v1.0-sim")
rss = []
for i in range(s.n_scenes):
    generate_scene(s, Path(sys.argv[1]), i)
    rss.append(int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20)
print(json.dumps({"rss": rss, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""
    n = 3 if quick else 8
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run([sys.executable, "-c", code, tmp, str(n)], check=True, cwd=ROOT,
                              capture_output=True, text=True)
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"worker_peak_rss_mb": r["peak"], "worker_rss_growth_mb": r["rss"][-1] - r["rss"][1],
            "worker_rss_per_scene_mb": [round(v) for v in r["rss"]]}


CLFBEV_TRAIN = """
import json, resource, sys, time, tempfile, subprocess
import numpy as np, torch
torch.set_num_threads(1)
from clfbev.config import tiny
from clfbev.data import NuScenesDetection, collate
from clfbev.model import CLFusionBEV
cfg = tiny()
ds = NuScenesDetection(sys.argv[1], "v1.0-sim", "sim-train", cfg.data_config())
batch = collate([ds[0]])
torch.manual_seed(0)
model = CLFusionBEV(cfg, "full")
opt = torch.optim.AdamW(model.parameters(), lr=2e-4, weight_decay=1e-2)
times = []
for _ in range(int(sys.argv[2])):
    t = time.perf_counter()
    opt.zero_grad()
    model.loss(batch)["loss"].backward()
    opt.step()
    times.append(time.perf_counter() - t)
model.eval()
with torch.no_grad():
    model.predict(batch)
    inf = []
    for _ in range(int(sys.argv[2])):
        t = time.perf_counter(); model.predict(batch); inf.append(time.perf_counter() - t)
print(json.dumps({"train_tiny_samples_per_s": 1.0 / float(np.median(times[1:])),
                  "infer_tiny_ms": 1000 * float(np.median(inf)),
                  "train_tiny_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""

CLFBEV_ATTN = """
import json, resource, sys, time
import numpy as np, torch
torch.set_num_threads(1)
from clfbev.attention import BEVAttention
mode, side = sys.argv[1], int(sys.argv[2])
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
attn = BEVAttention(4, mode=mode, window=8, pool_stride=4)
q = torch.randn(1, side, side, 64)
with torch.no_grad():
    attn(q, q, q)
    ts = []
    for _ in range(3):
        t = time.perf_counter(); attn(q, q, q); ts.append(time.perf_counter() - t)
print(json.dumps({"ms": 1000 * float(np.median(ts)),
                  "peak_mb": (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024}))
"""


def _py(code: str, *args) -> dict:
    proc = subprocess.run([sys.executable, "-c", code, *map(str, args)], check=True, cwd=ROOT,
                          capture_output=True, text=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def bench_clfbev(quick: bool) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "simgen.cli", "make", "--preset", "tiny", "--scenes", "2",
                        "--samples-per-scene", "2", "--out", tmp, "--quiet"], check=True, cwd=ROOT,
                       stdout=subprocess.DEVNULL)
        out = _py(CLFBEV_TRAIN, tmp, 4 if quick else 10)
        if not quick:
            out["paper_gflops"] = _py(PAPER_FLOPS, tmp)["gflops"]
    exact = _py(CLFBEV_ATTN, "exact", 64)
    window = _py(CLFBEV_ATTN, "window", 180)
    pooled = _py(CLFBEV_ATTN, "pooled", 180)
    out.update({"attn_ms_exact_64x64": exact["ms"], "attn_peak_mb_exact_64x64": exact["peak_mb"],
                "attn_ms_scalable_180x180": window["ms"], "attn_peak_mb_scalable_180x180": window["peak_mb"],
                "attn_ms_pooled_180x180": pooled["ms"], "attn_peak_mb_pooled_180x180": pooled["peak_mb"]})
    from clfbev.config import paper
    from clfbev.model import CLFusionBEV, count_parameters
    out["paper_params_m"] = count_parameters(CLFusionBEV(paper(), "full")) / 1e6
    return out


PAPER_FLOPS = """
import json, torch
from torch.utils.flop_counter import FlopCounterMode
torch.set_num_threads(2)
import sys
from clfbev.config import paper
from clfbev.data import NuScenesDetection, collate
from clfbev.model import CLFusionBEV
cfg = paper()
model = CLFusionBEV(cfg, "full").eval()
batch = collate([NuScenesDetection(sys.argv[1], "v1.0-sim", "sim-train", cfg.data_config())[0]])
with torch.no_grad(), FlopCounterMode(display=False) as fc:
    model(batch)
print(json.dumps({"gflops": fc.get_total_flops() / 1e9}))
"""


def bench_eval(quick: bool) -> dict:
    """clfbev eval: predict + the official DetectionEval, per 100 samples (tiny config, 1 thread)."""
    with tempfile.TemporaryDirectory() as tmp:
        n = 6 if quick else 12
        subprocess.run([sys.executable, "-m", "simgen.cli", "make", "--preset", "tiny", "--scenes", "2",
                        "--samples-per-scene", str(n // 2), "--val-fraction", "0.5", "--out", f"{tmp}/d", "--quiet",
                        "--workers", "1"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        return _py(EVAL_TIMING, f"{tmp}/d", f"{tmp}/e")


EVAL_TIMING = """
import json, sys, time, torch
torch.set_num_threads(1)
from clfbev.config import tiny
from clfbev.data import NuScenesDetection
from clfbev.evaluate import evaluate, predict_split, write_results
from clfbev.model import CLFusionBEV
torch.manual_seed(0)
cfg = tiny()
model = CLFusionBEV(cfg, "full").eval()
ds = NuScenesDetection(sys.argv[1], "v1.0-sim", "sim-val", cfg.data_config())
t0 = time.perf_counter()
results = predict_split(model, ds)
t1 = time.perf_counter()
evaluate(ds.nusc, write_results(sys.argv[2] + "/r.json", results), "sim-val", sys.argv[2], cfg.class_names)
t2 = time.perf_counter()
n = len(ds)
print(json.dumps({"eval_s_per_100_samples": (t2 - t0) / n * 100, "eval_predict_s_per_100_samples": (t1 - t0) / n * 100,
                  "eval_devkit_s_per_100_samples": (t2 - t1) / n * 100}))
"""


def bench_fog(quick: bool) -> dict:
    """Fog's share of a 1600x900 sample: the degradation functions on one sample's data (6 camera
    images with their depth, 10 sweeps), timed alone, over the same sample made without fog."""
    from simgen import rig
    from simgen.config import load_preset, with_degradation
    from simgen.lidar import LidarScanner
    from simgen.mitsuba_camera import actor_poses_at
    from simgen.pipeline import MakeSettings, _renderer, build_world, degrade_image, degrade_sweep
    cfg = with_degradation(load_preset("urban"), fog=5)
    s = MakeSettings(cfg, 1, 0, 1, "v1.0-sim")
    world = build_world(s, 0)
    r = _renderer(cfg, None)
    r.set_world(world, key="bench-fog")
    cams = rig.cameras(cfg.camera.resolution)
    poses = actor_poses_at(world, 0.5)
    frames = []
    for cam in cams:
        rgb, depth, _ = r.render(cam, world.ego_pose(0.5) @ cam.T_ego_from_cam, poses)
        frames.append((cam, rgb, depth))
    scanner = LidarScanner(cfg.lidar, world)
    sweeps = [scanner.scan(0.05 * (k + 1), np.random.default_rng(k)) for k in range(10)]

    def fog_one_sample():
        for i, (cam, rgb, depth) in enumerate(frames):
            degrade_image(rgb, depth, cam, cfg, s, 0, i)
        for sw in sweeps:
            degrade_sweep(sw, cfg, np.zeros(0, int), np.random.default_rng(0))

    ms = median_ms(fog_one_sample, 3 if quick else 7)
    sample_s = bench_render_sample_s(quick)
    return {"fog_ms_per_sample_1600x900": ms, "fog_overhead_pct": 100 * ms / 1000 / sample_s,
            **lidar_fog_figures(sweeps[0], cfg.lidar)}


FOG_BANDS = ((0.0, 10.0), (10.0, 30.0), (30.0, 50.0), (50.0, np.inf))


def lidar_fog_figures(sw, lidar) -> dict:
    """What fog does to one clean sweep, severity 0..5 (see the lidar_fog_* keys)."""
    from simgen import degrade as D
    rho_cos = sw.rho * sw.cos_inc
    band = np.digitize(sw.range, [b[1] for b in FOG_BANDS[:-1]])          # (n,) band index by clean range
    per_band = lambda mask: [int((mask & (band == b)).sum()) for b in range(len(FOG_BANDS))]  # noqa: E731
    out = {k: [] for k in ("points", "returns", "returns_by_band", "silent", "equation", "kept", "won",
                           "intensity_0")}
    for sev, alpha in enumerate(D.FOG_ALPHA):
        pts, is_fog = D.fog_lidar(sw.points_lidar, rho_cos, sw.range, sw.dir_lidar, alpha, lidar.min_return,
                                  lidar.intensity_ref_range, np.random.default_rng(0))
        out["points"].append(len(pts))
        out["returns"].append(int(is_fog.sum()))
        if alpha == 0:
            out["returns_by_band"].append([0] * len(FOG_BANDS))
            out["silent"].append(0)
            continue
        f = D.fog_returns(rho_cos, sw.range, alpha, lidar.min_return)
        assert int(f.kept.sum()) == len(pts) and int((f.kept & f.fog_wins).sum()) == int(is_fog.sum())
        expected = f.p_hard >= lidar.min_return                            # the lidar equation alone
        hard = f.kept & ~f.fog_wins
        out["returns_by_band"].append(per_band(f.kept & f.fog_wins))
        out["silent"].append(int((expected & ~f.kept).sum()))
        eq, kept, won = per_band(expected)[1:], per_band(hard)[1:], per_band(expected & f.fog_wins)[1:]
        out["equation"].append(eq)
        out["kept"].append([round(k / e, 4) if e else None for k, e in zip(kept, eq)])
        out["won"].append([round(w / e, 4) if e else None for w, e in zip(won, eq)])
        # Ranged by the points themselves, as a procedure that sees only the point cloud does.
        r0 = np.linalg.norm(sw.points_lidar[:, :3], axis=1)
        i_att = np.round(sw.points_lidar[:, 3] * np.exp(-2 * alpha * r0))
        out["intensity_0"].append(int(((i_att == 0) & (sw.points_lidar[:, 3] > 0)).sum()))
    return {"lidar_fog_points_by_severity": out["points"], "lidar_fog_returns_by_severity": out["returns"],
            "lidar_fog_returns_by_band": out["returns_by_band"], "lidar_fog_silent_rays_by_severity": out["silent"],
            "lidar_fog_equation_by_band": out["equation"], "lidar_fog_kept_ratio_by_band": out["kept"],
            "lidar_fog_won_share_by_band": out["won"], "lidar_fog_intensity_0_by_severity": out["intensity_0"]}


def bench_render_sample_s(quick: bool) -> float:
    """Seconds per 1600x900 sample (one worker), as sample_s_1600x900."""
    with tempfile.TemporaryDirectory() as tmp:
        samples = 2 if quick else 4
        secs = run_make(Path(tmp) / "d", 1, samples, 1, "1600x900")
        return secs / samples


def bench_mitsuba(quick: bool) -> dict:
    """One 800x450 camera image path-traced by Mitsuba (rgb pass only) at MITSUBA_SPP."""
    from simgen import rig
    from simgen.config import load_preset, with_resolution
    from simgen.mitsuba_camera import MitsubaRenderer, actor_poses_at
    from simgen.pipeline import MakeSettings, build_world
    cfg = with_resolution(load_preset("urban"), 800, 450)
    world = build_world(MakeSettings(cfg, 1, 0, 1, "v1.0-sim"), 0)
    cam = rig.cameras(cfg.camera.resolution)[0]
    T = world.ego_pose(0.5) @ cam.T_ego_from_cam
    poses = actor_poses_at(world, 0.5)
    r = MitsubaRenderer(cfg.camera, spp=MITSUBA_SPP)
    try:
        ms = median_ms(lambda: r.render(world, cam, T, poses, with_ids=False), 2 if quick else 3)
    finally:
        r.close()
    return {"mitsuba_s_per_image_800x450": ms / 1000, "mitsuba_spp": MITSUBA_SPP, "mitsuba_variant": r.variant}


MITSUBA_SPP = 16


def bench_demo(quick: bool) -> dict:
    """`bash scripts/demo.sh` from scratch (its data and run folders removed first)."""
    import shutil
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
    import shutil
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--quick", action="store_true", help="fewer repeats and smaller runs")
    ap.add_argument("--only", nargs="*", default=None,
                    help="subset: lidar render make memory clfbev eval fog mitsuba, or scaling (16-scene make "
                         "pairs, about 6 min) or demo (runs scripts/demo.sh, about 25 min): these two are not in "
                         "the default set, nor is ray (`make --ray` against the local pool, about 8 min)")
    args = ap.parse_args()
    repeats = 5 if args.quick else 20
    parts = {"lidar": lambda: bench_lidar(repeats), "render": lambda: bench_render(repeats),
             "make": lambda: bench_make(args.quick), "memory": lambda: bench_worker_memory(args.quick),
             "clfbev": lambda: bench_clfbev(args.quick), "eval": lambda: bench_eval(args.quick),
             "fog": lambda: bench_fog(args.quick), "mitsuba": lambda: bench_mitsuba(args.quick),
             "demo": lambda: bench_demo(args.quick), "scaling": lambda: bench_scaling(args.quick),
             "ray": lambda: bench_ray(args.quick)}
    result = {"machine": {"cpus": os.cpu_count()}}
    for name, fn in parts.items():
        if (args.only is None and name not in ("demo", "scaling", "ray")) or (args.only is not None and name in args.only):
            result.update(fn())
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for k, v in result.items():
            print(f"{k:32s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
