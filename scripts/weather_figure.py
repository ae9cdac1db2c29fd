"""The weather figure of docs/weather.md: one urban sample made under each condition with the same
seed (so the world, the poses and the labels are the same), one row per condition: the front and
the back camera as written, and the key frame's lidar BEV in its lidarseg colours (the weather's
clutter returns are the "noise" class, drawn white here).

    .venv/bin/python scripts/weather_figure.py --out docs/images/weather.jpg

Each condition is a `simgen make` of one scene and one sample into a temporary folder; the
figure reads them back through nuscenes-devkit like `simgen show`.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

CONDITIONS = {  # name -> simgen make flags
    "clear day": [],
    "rain 25 mm/h": ["--rain", "25"],
    "snowfall 1 mm/h": ["--snow", "1"],
    "night": ["--night"],
    "fog 3": ["--fog", "3"],
}


def make(out: Path, flags: list[str], seed: int, resolution: str) -> None:
    """One urban scene, one sample, under ``flags``."""
    cmd = [sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--scenes", "1", "--samples-per-scene", "1",
           "--seed", str(seed), "--resolution", resolution, "--workers", "1", "--quiet", *flags]
    subprocess.run(cmd, check=True)


def row(root: Path, name: str, tile_width: int) -> np.ndarray:
    """[CAM_FRONT | CAM_BACK | BEV] of the set's first sample, captioned with ``name``."""
    from simgen.show import draw_bev, load_nusc
    nusc = load_nusc(root, "v1.0-sim")
    sample = nusc.sample[0]
    tiles = []
    for channel in ("CAM_FRONT", "CAM_BACK"):
        img = cv2.imread(str(root / nusc.get("sample_data", sample["data"][channel])["filename"]))
        h = int(round(img.shape[0] * tile_width / img.shape[1]))
        tiles.append(cv2.resize(img, (tile_width, h), interpolation=cv2.INTER_AREA))
    bev = draw_bev(nusc, sample["data"]["LIDAR_TOP"], tiles[0].shape[0], half_range=40.0)
    out = np.concatenate([*tiles, bev], 1)
    cv2.putText(out, name, (10, out.shape[0] - 14), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (0, 0, 0), 5, cv2.LINE_AA)
    cv2.putText(out, name, (10, out.shape[0] - 14), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (255, 255, 255), 2, cv2.LINE_AA)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("docs/images/weather.jpg"), help="image to write (.jpg or .png)")
    ap.add_argument("--seed", type=int, default=3, help="the world's seed [3]")
    ap.add_argument("--resolution", default="1600x900", help="camera resolution WxH [1600x900]")
    ap.add_argument("--tile-width", type=int, default=560, help="width of each camera tile in pixels [560]")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for i, (name, flags) in enumerate(CONDITIONS.items()):
            root = Path(tmp) / f"c{i}"
            make(root, flags, args.seed, args.resolution)
            rows.append(row(root, name, args.tile_width))
    sheet = np.concatenate(rows, 0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(args.out.suffix, sheet, [cv2.IMWRITE_JPEG_QUALITY, 88])
    if not ok:
        raise SystemExit(f"--out {args.out}: cannot encode this image type")
    tmp_out = args.out.with_name(args.out.name + ".part")
    tmp_out.write_bytes(buf.tobytes())
    tmp_out.replace(args.out)
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
