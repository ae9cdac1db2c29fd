"""The static city: a grid of roads with lanes, sidewalks, crosswalks, markings, buildings
and clutter, plus the drivable-area raster for the map.

Geometry: road centrelines at x = x_i (vertical roads, along y) and y = y_j (horizontal roads,
along x), ``block_pitch`` apart, spanning the whole world. A road has ``lanes_per_direction``
lanes each way (right-hand traffic) and a parking strip on each side; sidewalks (raised 0.15 m)
run along every block edge, and crosswalks continue them across the roads.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from . import lidarseg
from .assets import Parts
from .config import LayoutConfig

CURB_HEIGHT = 0.15
MAP_RESOLUTION = 0.1   # metres per map pixel
MARGIN = 32.0          # city edge to the first road centreline
# The city starts this far from the global origin, and the map extends this far beyond it on
# every side: consumers crop the map around the ego (the devkit crops 57 m for its 40 m views).
MAP_PAD = 100.0

ASPHALT = (62, 62, 64)
SIDEWALK = (168, 166, 160)
WHITE = (235, 235, 235)
YELLOW = (230, 190, 40)


@dataclass(frozen=True)
class Grid:
    """Road-grid geometry derived from a LayoutConfig."""
    cfg: LayoutConfig

    @property
    def road_half_width(self) -> float:
        return self.cfg.lanes_per_direction * self.cfg.lane_width + self.cfg.parking_width

    @property
    def xs(self) -> np.ndarray:
        """x of the vertical roads' centrelines."""
        return MAP_PAD + MARGIN + self.cfg.block_pitch * np.arange(self.cfg.blocks_x + 1)

    @property
    def ys(self) -> np.ndarray:
        """y of the horizontal roads' centrelines."""
        return MAP_PAD + MARGIN + self.cfg.block_pitch * np.arange(self.cfg.blocks_y + 1)

    @property
    def extent(self) -> tuple[float, float]:
        """Size of the city (m); it spans [MAP_PAD, MAP_PAD + size] on each axis."""
        return (2 * MARGIN + self.cfg.block_pitch * self.cfg.blocks_x,
                2 * MARGIN + self.cfg.block_pitch * self.cfg.blocks_y)

    def intervals(self, centres: np.ndarray, length: float) -> np.ndarray:
        """(k, 2) spans between roads along one axis (including the city margins)."""
        hw = self.road_half_width
        edges = np.concatenate([[MAP_PAD], np.repeat(centres, 2) + np.tile([-hw, hw], len(centres)),
                                [MAP_PAD + length]])
        return edges.reshape(-1, 2)

    @property
    def blocks(self) -> np.ndarray:
        """(b, 4) raised block rectangles (x0, x1, y0, y1), sidewalks included."""
        W, H = self.extent
        ix, iy = self.intervals(self.xs, W), self.intervals(self.ys, H)
        return np.array([(a, b, c, d) for a, b in ix for c, d in iy])

    @property
    def road_km(self) -> float:
        W, H = self.extent
        return (len(self.xs) * H + len(self.ys) * W) / 1000.0

    def ground_z(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) global points -> (...) ground height: the curb height on blocks, else 0."""
        b = self.blocks
        x, y = xy[..., 0, None], xy[..., 1, None]
        on = (x >= b[:, 0]) & (x <= b[:, 1]) & (y >= b[:, 2]) & (y <= b[:, 3])
        return np.where(on.any(-1), CURB_HEIGHT, 0.0)


def drivable_mask(grid: Grid) -> np.ndarray:
    """(H, W) uint8 map at MAP_RESOLUTION, 255 = road; row 0 is the world's top edge (max y)."""
    W, H = grid.extent
    nx, ny = int(round((W + 2 * MAP_PAD) / MAP_RESOLUTION)), int(round((H + 2 * MAP_PAD) / MAP_RESOLUTION))
    mask = np.zeros((ny, nx), np.uint8)
    hw = grid.road_half_width
    px = lambda v: int(round(v / MAP_RESOLUTION))  # noqa: E731
    c0, c1 = px(MAP_PAD), px(MAP_PAD + W)              # the city's columns
    r0, r1 = ny - px(MAP_PAD + H), ny - px(MAP_PAD)    # and rows (row = ny - y / resolution)
    for x in grid.xs:
        mask[r0:r1, px(x - hw):px(x + hw)] = 255
    for y in grid.ys:
        mask[ny - px(y + hw):ny - px(y - hw), c0:c1] = 255
    return mask


def _along(p: Parts, horizontal: bool, c: float, u0: float, u1: float, off: float, width: float,
           color, refl, z: float = 0.01):
    """A marking quad along a road: from u0 to u1 along the road, at lateral offset ``off``."""
    length, mid = u1 - u0, (u0 + u1) / 2
    if horizontal:
        p.box((length, width, 0.01), (mid, c + off, z), color, refl, label=lidarseg.ROAD)
    else:
        p.box((width, length, 0.01), (c + off, mid, z), color, refl, label=lidarseg.ROAD)


def _road_markings(p: Parts, grid: Grid):
    """Centre double yellow, dashed lane lines, parking edge lines and zebra crosswalks."""
    cfg = grid.cfg
    W, H = grid.extent
    hw, sw = grid.road_half_width, cfg.sidewalk_width
    for horizontal, centres, cross, length in ((True, grid.ys, grid.xs, W), (False, grid.xs, grid.ys, H)):
        spans = grid.intervals(cross, length)
        for c in centres:
            for u0, u1 in spans:
                a, b = u0 + (sw if u0 > 0 else 0.0), u1 - (sw if u1 < length else 0.0)
                if b - a < 2.0:
                    continue
                for side in (-1, 1):
                    _along(p, horizontal, c, a, b, side * 0.15, 0.12, YELLOW, 0.55)
                    edge = side * cfg.lanes_per_direction * cfg.lane_width
                    _along(p, horizontal, c, a, b, edge, 0.12, WHITE, 0.6)
                    for k in range(1, cfg.lanes_per_direction):
                        for d0 in np.arange(a + 1.0, b - 3.0, 9.0):
                            _along(p, horizontal, c, d0, d0 + 3.0, side * k * cfg.lane_width, 0.12, WHITE, 0.6)
            # Zebra crosswalks where the sidewalks of the crossing roads continue over this road.
            for cc in cross:
                for side in (-1, 1):
                    band = (cc + side * (hw + sw / 2))
                    for off in np.arange(-hw + 0.6, hw - 0.3, 1.0):
                        if horizontal:
                            p.box((sw - 0.6, 0.5, 0.01), (band, c + off, 0.01), WHITE, 0.6, label=lidarseg.ROAD)
                        else:
                            p.box((0.5, sw - 0.6, 0.01), (c + off, band, 0.01), WHITE, 0.6, label=lidarseg.ROAD)


def _buildings(p: Parts, grid: Grid, rng: np.random.Generator) -> None:
    """Rows of buildings along each block's lot edges, varied in size and colour."""
    cfg = grid.cfg
    sw = cfg.sidewalk_width
    palette = np.array([(180, 160, 140), (150, 120, 100), (200, 195, 180), (120, 125, 135),
                        (170, 90, 70), (210, 200, 160), (100, 110, 120), (190, 180, 200)], float)
    for x0, x1, y0, y1 in grid.blocks:
        lx0, lx1, ly0, ly1 = x0 + sw, x1 - sw, y0 + sw, y1 - sw
        if lx1 - lx0 < 6 or ly1 - ly0 < 6:
            continue
        depth_max = min(22.0, (ly1 - ly0) / 2 - 1.0, (lx1 - lx0) / 2 - 1.0)
        if depth_max < 4:
            continue
        # Rows along the bottom and top edges, then the left and right edges between them.
        rows = [(lx0, lx1, ly0, +1, True), (lx0, lx1, ly1, -1, True),
                (ly0 + depth_max, ly1 - depth_max, lx0, +1, False),
                (ly0 + depth_max, ly1 - depth_max, lx1, -1, False)]
        for a, b, edge, inward, along_x in rows:
            u = a
            while u < b - 4.0:
                width = min(rng.uniform(10, 30), b - u)
                depth = rng.uniform(min(8.0, 0.6 * depth_max), depth_max)
                height = rng.uniform(*cfg.building_height)
                color = np.clip(palette[rng.integers(len(palette))] * rng.uniform(0.85, 1.15), 0, 255)
                mid_u, mid_v = u + width / 2, edge + inward * depth / 2
                center = (mid_u, mid_v) if along_x else (mid_v, mid_u)
                ext = (width, depth) if along_x else (depth, width)
                p.box((*ext, height), (*center, CURB_HEIGHT + height / 2), color, 0.35, label=lidarseg.MANMADE)
                # Dark window bands on the street facade.
                face = edge - inward * 0.03
                for zb in np.arange(CURB_HEIGHT + 3.0, height - 1.0, 3.2):
                    wc = (mid_u, face) if along_x else (face, mid_u)
                    wext = (width * 0.85, 0.08) if along_x else (0.08, width * 0.85)
                    p.box((*wext, 1.3), (*wc, zb), (50, 60, 75), 0.1, label=lidarseg.MANMADE)
                u += width + rng.uniform(*cfg.building_gap)


def _clutter(p: Parts, grid: Grid, rng: np.random.Generator) -> np.ndarray:
    """Poles, trees and bins along the curb side of every sidewalk. Returns (s, 7) footprints."""
    cfg = grid.cfg
    hw = grid.road_half_width
    W, H = grid.extent
    boxes = []
    for horizontal, centres, cross, length in ((True, grid.ys, grid.xs, W), (False, grid.xs, grid.ys, H)):
        spans = grid.intervals(cross, length)
        for c in centres:
            for side in (-1, 1):
                lat = c + side * (hw + 0.6)
                for u0, u1 in spans:
                    for u in np.arange(u0 + 3.0, u1 - 3.0, cfg.clutter_spacing):
                        u = u + rng.uniform(-2.0, 2.0)
                        x, y = (u, lat) if horizontal else (lat, u)
                        kind = rng.choice(3, p=[0.5, 0.38, 0.12])
                        z0 = CURB_HEIGHT
                        if kind == 0:    # a street light
                            hgt = rng.uniform(5.0, 8.0)
                            p.cylinder((x, y, z0), (x, y, z0 + hgt), 0.1, (90, 95, 100), 0.45, label=lidarseg.MANMADE)
                            boxes.append((x, y, z0 + hgt / 2, 0.3, 0.3, hgt, 0.0))
                        elif kind == 1:  # a tree: trunk and canopy
                            hgt = rng.uniform(2.2, 3.2)
                            r = rng.uniform(1.2, 2.2)
                            p.cylinder((x, y, z0), (x, y, z0 + hgt), 0.16, (95, 70, 50), 0.3, label=lidarseg.VEGETATION)
                            green = (rng.integers(40, 80), rng.integers(100, 150), rng.integers(40, 70))
                            p.sphere((x, y, z0 + hgt + r * 0.8), r, green, 0.4, label=lidarseg.VEGETATION)
                            boxes.append((x, y, z0 + hgt / 2, 0.4, 0.4, hgt, 0.0))
                        else:            # a bin
                            p.box((0.5, 0.5, 0.9), (x, y, z0 + 0.45), (40, 90, 50), 0.3, label=lidarseg.MANMADE)
                            boxes.append((x, y, z0 + 0.45, 0.6, 0.6, 0.9, 0.0))
    return np.array(boxes, dtype=np.float64).reshape(-1, 7)


def build_static(grid: Grid, rng: np.random.Generator) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The static world mesh (global frame) and the (s, 7) footprints of its clutter."""
    W, H = grid.extent
    p = Parts()
    # The road surface, its top at z = 0.
    p.box((W, H, 0.02), (MAP_PAD + W / 2, MAP_PAD + H / 2, -0.01), ASPHALT, 0.12, label=lidarseg.ROAD)
    sw = grid.cfg.sidewalk_width
    lawn = rng.random() < 0.5
    for x0, x1, y0, y1 in grid.blocks:
        p.box((x1 - x0, y1 - y0, CURB_HEIGHT), ((x0 + x1) / 2, (y0 + y1) / 2, CURB_HEIGHT / 2), SIDEWALK, 0.3,
              label=lidarseg.SIDEWALK)
        if x1 - x0 > 2 * sw + 1 and y1 - y0 > 2 * sw + 1:
            color = (78, 112, 62) if lawn else (140, 135, 125)
            # 5 mm short of the lot edge on every side: the buildings' street faces stand on that
            # edge, and a slab side in the same plane z-fights with them (a flickering pixel row).
            p.box((x1 - x0 - 2 * sw - 0.01, y1 - y0 - 2 * sw - 0.01, 0.01),
                  ((x0 + x1) / 2, (y0 + y1) / 2, CURB_HEIGHT + 0.005), color, 0.25,
                  label=lidarseg.TERRAIN if lawn else lidarseg.PLAZA)
    _road_markings(p, grid)
    _buildings(p, grid, rng)
    clutter = _clutter(p, grid, rng)
    return p.build(), clutter
