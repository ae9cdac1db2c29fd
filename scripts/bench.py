#!/usr/bin/env python
"""The project's benchmarks. Prints one JSON object (``--json``) or a table.

Medians over repeats, because machines are shared and noisy. The parts live in
bench_simgen.py, bench_fog.py and bench_clfbev.py beside this file. Keys (simgen):
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
  eval_s_per_100_samples        clfbev.run.evaluate.evaluate_model (predict, write, the official
                                DetectionEval; tiny, 1 thread), per 100 samples; its two parts:
                                _predict_ (a prediction pass of its own) and _devkit_ (the rest)
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
    _range_iqr_by_severity      interquartile range (m) of the fog returns' distances [along
                                their rays, from the sensor at the sweep's end] (severity 1..5)
    _haze_returns               [fog returns, rays] at a visibility of 2,000 m
  mitsuba_s_per_image_800x450   one path-traced camera image (rgb pass) at mitsuba_spp
  weather_sample_ratio_*        (only with --only weather, about 10 min) `make` of one urban scene
                                (4 samples, 1600x900, one worker) under rain 50 mm/h, snowfall 2.5
                                mm/h, night, and all three, over the clear day's; median of 3
                                alternating pairs (_runs lists each pair's ratio)
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
import sys

from bench_clfbev import bench_clfbev, bench_eval
from bench_fog import bench_fog
from bench_simgen import (
    bench_demo,
    bench_lidar,
    bench_make,
    bench_mitsuba,
    bench_ray,
    bench_render,
    bench_scaling,
    bench_weather,
    bench_worker_memory,
)

# Parts run only when named in --only: they take long or run the whole demo.
NOT_BY_DEFAULT = ("demo", "scaling", "ray", "weather")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--quick", action="store_true", help="fewer repeats and smaller runs")
    ap.add_argument("--only", nargs="*", default=None,
                    help="subset: lidar render make memory clfbev eval fog mitsuba, or scaling (16-scene make "
                         "pairs, about 6 min) or demo (runs scripts/demo.sh, about 25 min): these two are not in "
                         "the default set, nor is ray (`make --ray` against the local pool, about 8 min) or weather "
                         "(a sample under rain, snow and night against the clear day, about 10 min)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    repeats = 5 if args.quick else 20
    parts = {"lidar": lambda: bench_lidar(repeats), "render": lambda: bench_render(repeats),
             "make": lambda: bench_make(args.quick), "memory": lambda: bench_worker_memory(args.quick),
             "clfbev": lambda: bench_clfbev(args.quick), "eval": lambda: bench_eval(args.quick),
             "fog": lambda: bench_fog(args.quick), "mitsuba": lambda: bench_mitsuba(args.quick),
             "demo": lambda: bench_demo(args.quick), "scaling": lambda: bench_scaling(args.quick),
             "ray": lambda: bench_ray(args.quick), "weather": lambda: bench_weather(args.quick)}
    result = {"machine": {"cpus": os.cpu_count()}}
    for name, run in parts.items():
        chosen = name not in NOT_BY_DEFAULT if args.only is None else name in args.only
        if chosen:
            result.update(run())
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for k, v in result.items():
            print(f"{k:32s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
