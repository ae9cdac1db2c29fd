"""What rain and snowfall do to one clean urban sweep, and what they cost (docs/weather.md).

    python scripts/bench_weather.py [--repeats N] [--sample]

For rain of 10, 25 and 50 mm/h and snowfall of 0.5, 1 and 2.5 mm/h (water equivalent) on the
urban preset's world 0, the sweep ending at t = 0.05 s (the sweep scripts/bench_fog.py uses):
per band of the clean return's range the share of the clean returns still reported as
themselves, the wet road's share of its returns kept, the number of clutter returns (particle
echoes, labelled noise) and the quantiles of their distance from the sensor; the time of the
weather per sweep against the sweep's own ray casting. ``--sample`` also times ``simgen make``
of one urban scene of 2 samples at 1600x900 clear, in rain (25 mm/h) and in snow (2.5 mm/h).
Prints markdown tables.
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from bench_common import median_ms, run_make

BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 35.0), (35.0, 50.0), (50.0, np.inf))
WEATHERS = (("rain", 10.0), ("rain", 25.0), ("rain", 50.0), ("snow", 0.5), ("snow", 1.0), ("snow", 2.5))
QUANTILES = (5, 25, 50, 75, 95)


def clean_sweep():
    """The urban settings, world-0 scanner and the clean sweep ending at t = 0.05 s."""
    from simgen.config import load_preset
    from simgen.lidar import LidarScanner
    from simgen.pipeline import build_world
    from simgen.settings import MakeSettings
    cfg = load_preset("urban")
    s = MakeSettings(cfg, 1, 0, 1, "v1.0-sim")
    scanner = LidarScanner(cfg.lidar, build_world(s, 0))
    return cfg, s, scanner, scanner.scan(0.05, np.random.default_rng(0), missed_rays=True)


def weather_points(cfg, s, sw, kind: str, rate: float) -> np.ndarray:
    """The sweep's points under the weather, with the label and ray columns (lidar_sweep's)."""
    from simgen.settings import weather_streams
    from simgen.weather import lidar_sweep, rain_lidar, snow_lidar
    pts = lidar_sweep.with_ray_column(np.concatenate([sw.points_lidar, sw.label[:, None].astype(np.float32)], axis=1))
    rays = lidar_sweep.sweep_rays(pts, sw, cfg.lidar.min_return, 0.0)
    w = weather_streams(s, 0)
    if kind == "rain":
        return rain_lidar.rain_sweep(pts, rays, rate, cfg.lidar, w.rain_lidar)[0]
    return snow_lidar.snow_sweep(pts, rays, rate, cfg.lidar, w.snow_lidar)[0]


def figures(cfg, s, sw, kind: str, rate: float) -> dict:
    """Kept shares per band, the road's kept share, clutter count and distance quantiles (m)."""
    from simgen import lidarseg
    from simgen.weather.lidar_sweep import LABEL_COLUMN, RAY_COLUMN
    out = weather_points(cfg, s, sw, kind, rate)
    ray = out[:, RAY_COLUMN].astype(np.int64)
    clutter = out[:, LABEL_COLUMN] == lidarseg.NOISE
    kept = np.zeros(len(sw.range), bool)
    kept[ray[~clutter]] = True                                 # reported as itself
    band = np.digitize(sw.range, [b[1] for b in BANDS[:-1]])
    road = sw.label == lidarseg.ROAD
    dist = np.linalg.norm(out[clutter, :3], axis=1)
    return {"kept_by_band": [float(kept[band == b].mean()) for b in range(len(BANDS))],
            "clean_by_band": [int((band == b).sum()) for b in range(len(BANDS))],
            "road_kept": float(kept[road].mean()), "clutter": int(clutter.sum()),
            "clutter_from_missed_rays": int((clutter & (ray >= len(sw.range))).sum()),
            "clutter_quantiles_m": [float(q) for q in np.percentile(dist, QUANTILES)] if len(dist) else []}


def timings(cfg, s, scanner, sw, repeats: int) -> dict:
    """Median ms: the sweep's ray casting, and degrade_sweep under each weather."""
    from simgen.config import with_weather
    from simgen.sensor_effects import degrade_sweep
    from simgen.settings import weather_streams
    out = {"scan": median_ms(lambda: scanner.scan(0.05, np.random.default_rng(0)), repeats)}
    for kind, rate in WEATHERS:
        c = with_weather(cfg, **{kind: rate})
        degrade_sweep(sw, c, np.zeros(0, int), np.random.default_rng(0), weather_streams(s, 0))   # tables, once
        out[f"{kind} {rate:g}"] = median_ms(
            lambda: degrade_sweep(sw, c, np.zeros(0, int), np.random.default_rng(0), weather_streams(s, 0)), repeats)
    return out


def sample_seconds() -> dict:
    """Seconds per sample of ``simgen make`` (one urban scene, 2 samples, 1600x900, one worker)."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, flags in (("clear", ()), ("rain 25", ("--rain", "25")), ("snow 2.5", ("--snow", "2.5"))):
            out[name] = run_make(Path(tmp) / name.replace(" ", "_"), 1, 2, 1, "1600x900", flags=flags) / 2
    return out


def table(rows: dict, clean: list[int]) -> str:
    names = [f"{lo:g}-{hi:g} m" if np.isfinite(hi) else f"{lo:g}+ m" for lo, hi in BANDS]
    lines = ["| weather | " + " | ".join(f"kept {n} ({c:,})" for n, c in zip(names, clean))
             + " | road kept | clutter (of them in missed rays) | clutter distance q5/q25/q50/q75/q95 (m) |",
             "|---" * (len(BANDS) + 4) + "|"]
    for key, f in rows.items():
        q = "/".join(f"{x:.1f}" for x in f["clutter_quantiles_m"]) or "-"
        lines.append(f"| {key} | " + " | ".join(f"{k:.3f}" for k in f["kept_by_band"])
                     + f" | {f['road_kept']:.3f} | {f['clutter']:,} ({f['clutter_from_missed_rays']:,}) | {q} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--sample", action="store_true", help="also time simgen make at 1600x900 (minutes)")
    args = ap.parse_args()
    cfg, s, scanner, sw = clean_sweep()
    rows = {f"{kind} {rate:g} mm/h": figures(cfg, s, sw, kind, rate) for kind, rate in WEATHERS}
    print(f"Urban world 0, sweep ending at 0.05 s: {len(sw.range):,} returns, {len(sw.miss_range):,} rays without one "
          f"({int(np.isinf(sw.miss_range).sum()):,} into the open).\n")
    print(table(rows, next(iter(rows.values()))["clean_by_band"]))
    t = timings(cfg, s, scanner, sw, args.repeats)
    print("\n| per sweep | ms | / ray casting |\n|---|---|---|")
    for key, ms in t.items():
        print(f"| {key} | {ms:.2f} | {ms / t['scan']:.2f} |")
    if args.sample:
        secs = sample_seconds()
        print("\n| simgen make, urban, 1600x900 | s per sample | / clear |\n|---|---|---|")
        for key, sec in secs.items():
            print(f"| {key} | {sec:.2f} | {sec / secs['clear']:.2f} |")


if __name__ == "__main__":
    main()
