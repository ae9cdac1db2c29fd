"""`simgen make | presets | check | show`.

Bad input (an unknown preset key, a negative count, a zero resolution, an unwritable --out, a
damaged file, an unreachable cluster: :mod:`simgen.errors`) gets one line naming the problem on
stderr and exit code 2, before anything is written. Any other exception keeps its traceback.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from .errors import EXIT_BAD_INPUT, ConfigError, InputError


def _positive_int(name):
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer, got {text!r}") from None
        if v < 1:
            raise argparse.ArgumentTypeError(f"{name} must be >= 1, got {v}")
        return v
    return parse


def _resolution(text):
    m = re.fullmatch(r"(\d+)x(\d+)", text)
    if not m:
        raise argparse.ArgumentTypeError(f"--resolution must look like 1600x900, got {text!r}")
    w, h = int(m.group(1)), int(m.group(2))
    if w < 16 or h < 16 or w > 4096 or h > 4096:
        raise argparse.ArgumentTypeError(f"--resolution {text}: each side must be in [16, 4096]")
    return w, h


def _fraction(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--val-fraction must be a number, got {text!r}") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"--val-fraction must be in [0, 1], got {v}")
    return v


def check_writable(out: Path) -> None:
    """Refuse an --out that cannot be created or written, without creating anything."""
    p = out.resolve()
    while not p.exists():
        p = p.parent
    if not p.is_dir():
        raise ConfigError(f"--out {out}: {p} is not a directory")
    if not os.access(p, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {out}: {p} is not writable")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="simgen",
        description="Procedural urban scenes rendered into a nuScenes-format dataset: six cameras "
                    "(pyrender), a 32-beam HDL-32E lidar (Embree), exact labels (boxes, and a "
                    "nuScenes-lidarseg class per key-frame lidar point), and the 13 tables that "
                    "nuscenes-devkit loads and evaluates.")
    sub = ap.add_subparsers(dest="command", required=True)

    mk = sub.add_parser("make", help="generate a dataset (resumes an interrupted run in the same --out)",
                        description="Generate N scenes into DIR/<version>/ (tables), DIR/samples, DIR/sweeps "
                                    "and DIR/maps (and DIR/dense with --dense-labels). Rerunning the same command after an interruption finishes "
                                    "the missing scenes; the result is byte-identical to an uninterrupted run.")
    mk.add_argument("--scenes", type=_positive_int("--scenes"), required=True, help="number of scenes")
    mk.add_argument("--out", type=Path, required=True, help="dataroot to write")
    mk.add_argument("--preset", default="urban", help="preset name (see `simgen presets`) or a YAML file [urban]")
    mk.add_argument("--seed", type=int, default=0, help="global seed; scene i uses (seed, i) [0]")
    mk.add_argument("--workers", type=_positive_int("--workers"), default=os.cpu_count() or 1,
                    help="worker processes, or the CPUs of the local Ray instance of --ray [number of cores]")
    mk.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                    help="run the scenes as Ray tasks (the same bytes): on a local Ray instance, or with "
                         "ADDRESS (auto, or HOST:PORT of the head node) on an existing cluster; needs the "
                         "optional extra: pip install -e .[ray]")
    mk.add_argument("--samples-per-scene", type=_positive_int("--samples-per-scene"), default=10,
                    help="key frames (2 Hz) per scene [10]")
    mk.add_argument("--resolution", type=_resolution, default=None,
                    help="camera resolution WxH; intrinsics are scaled from 1600x900 [preset's]")
    mk.add_argument("--version", default="v1.0-sim", help="version folder name [v1.0-sim]")
    mk.add_argument("--val-fraction", type=_fraction, default=0.2, help="share of scenes in sim-val [0.2]; 1 makes a set for evaluation only")
    mk.add_argument("--gl", choices=("egl", "osmesa"), default=None,
                    help="OpenGL platform [egl, or $PYOPENGL_PLATFORM]; osmesa is the slow fallback")
    mk.add_argument("--quiet", action="store_true", help="no progress bar")
    mk.add_argument("--renderer", choices=("pyrender", "mitsuba"), default=None,
                    help="camera renderer [preset's: pyrender]; mitsuba path-traces (seconds per image)")
    mk.add_argument("--spp", type=int, default=None, help="Mitsuba samples per pixel [preset's: 16]")
    mk.add_argument("--dense-labels", action="store_true",
                    help="also write, beside each camera image samples/CAM_X/NAME.jpg, its z-depth "
                         "dense/CAM_X/NAME_depth.png (uint16, metres x 256, 0 = no surface) and its "
                         "nuScenes-lidarseg class per pixel dense/CAM_X/NAME_seg.png (uint8, 0 = sky)")
    dg = mk.add_argument_group("degradation (overrides the preset's 'degrade' section; labels stay clean, "
                               "so a degraded run pairs with the clean run of the same seed)")
    dg.add_argument("--fog", type=int, default=None, metavar="0-5",
                    help="fog severity; lidar alpha 0.005/0.01/0.02/0.03/0.06 per m, same extinction on the cameras")
    dg.add_argument("--fog-visibility", type=float, default=None, metavar="METRES",
                    help="fog by meteorological optical range instead (alpha = ln(20) / MOR)")
    dg.add_argument("--lens-occlusion", type=int, default=None, metavar="0-5", help="dirt blobs on every camera lens")
    dg.add_argument("--beam-drop", type=int, default=None, metavar="N", help="drop N of the 32 lidar rings")
    dg.add_argument("--lidar-fov", type=float, default=None, metavar="DEGREES",
                    help="keep only this sector around the ego's forward axis")
    dg.add_argument("--occlusion", default=None, choices=("none", "light", "heavy"),
                    help="extra static occluders (vans, hedges, trees, poles) along the ego's route")
    dg.add_argument("--drop-sensor", default=None, metavar="CHANNEL[,CHANNEL]",
                    help="failed sensors: a black image / an empty point cloud (the records and files exist)")

    wx = mk.add_argument_group("weather (overrides the preset's 'weather' section; the world, poses and labels "
                               "stay the clear day's, so a set pairs with the clean run of the same seed)")
    wx.add_argument("--rain", type=float, default=None, metavar="MM_PER_H",
                    help="rain rate, 0-200 mm/h (0 = none): Marshall-Palmer drops on both sensors, a wet road")
    wx.add_argument("--snow", type=float, default=None, metavar="MM_PER_H",
                    help="snowfall rate, 0-20 mm/h of melted water (0 = none): Gunn-Marshall flakes along each "
                         "lidar beam and in front of the cameras")
    wx.add_argument("--night", action="store_true", default=None,
                    help="night: street and vehicle lights, a camera's photon and read noise (the lidar is unchanged)")

    sub.add_parser("presets", help="list the presets, one line each")

    ck = sub.add_parser("check", help="validate a dataroot: tables, files and token integrity")
    ck.add_argument("dataroot", type=Path)
    ck.add_argument("--version", default="v1.0-sim")

    sh = sub.add_parser("show", help="contact sheet: six cameras with projected GT boxes, plus a lidar BEV")
    sh.add_argument("dataroot", type=Path)
    sh.add_argument("--sample", type=int, default=0, help="sample index in table order [0]")
    sh.add_argument("--version", default="v1.0-sim")
    sh.add_argument("--out", type=Path, required=True, help="PNG to write")
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)   # argparse itself exits with code 2 on malformed arguments
    try:
        return _run(args)
    except InputError as e:
        print(f"simgen: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("simgen: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130


def _run(args) -> int:
    if args.command == "presets":
        from .config import list_presets, load_preset
        for name in list_presets():
            print(f"{name:14s} {load_preset(name).description}")
        return 0
    if args.command == "make":
        return _make(args)
    if args.command == "check":
        from .check import check_dataroot
        return check_dataroot(args.dataroot, args.version)
    if args.command == "show":
        from .show import contact_sheet
        contact_sheet(args.dataroot, args.version, args.sample, args.out)
        print(f"wrote {args.out}")
        return 0
    return 1


def _make(args) -> int:
    from .config import load_preset, with_degradation, with_renderer, with_resolution, with_weather
    from .make import make
    from .settings import MakeSettings
    cfg = load_preset(args.preset)
    if args.resolution:
        cfg = with_resolution(cfg, *args.resolution)
    cfg = with_renderer(cfg, args.renderer, args.spp)
    cfg = with_degradation(cfg, fog=args.fog, fog_visibility=args.fog_visibility, lens_occlusion=args.lens_occlusion,
                           beam_drop=args.beam_drop, lidar_fov=args.lidar_fov, drop_sensors=args.drop_sensor,
                           occlusion=args.occlusion)
    cfg = with_weather(cfg, rain=args.rain, snow=args.snow, night=args.night)
    if not re.fullmatch(r"[A-Za-z0-9._-]+", args.version):
        raise ConfigError(f"--version {args.version!r}: use letters, digits, '.', '_' and '-' only")
    if args.ray is not None:
        from .ray_backend import parse_address
        parse_address(args.ray)
    check_writable(args.out)
    settings = MakeSettings(cfg, args.scenes, args.seed, args.samples_per_scene, args.version,
                            args.val_fraction, args.gl, args.dense_labels)
    summary = make(settings, args.out, args.workers, progress=not args.quiet, ray=args.ray)
    print(f"simgen: {summary['scenes']} scenes, {summary['samples']} samples, "
          f"{summary['tables']['sample_annotation']} annotations in {args.out}/{args.version} "
          f"({summary['seconds']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
