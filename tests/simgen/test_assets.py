"""Procedural actors: inside their boxes at every size, and with a front and a back that a half
turn about the vertical does not map onto each other, in shape (silhouettes, top heights) and in
lidar reflectivity (lamps, plates)."""
from __future__ import annotations

import numpy as np
import pytest

from simgen import assets, parts
from simgen.config import load_preset
from simgen.layout import Grid
from simgen.lidar import ELEVATIONS_DEG, RayTarget
from simgen.traffic import (SIZE_MEAN, STANDING_WAYS, TURN, WAIT_AT_CURB, Plan, _face_groups,
                            _standing_heading, make_actor)
from simgen.world import Actor

RES = 0.01                      # silhouette grid (m)
PAINT = (150, 20, 25)
RIDER = ((150, 30, 30), (40, 40, 60))
MESHES = {
    "car": (assets.car, SIZE_MEAN["car"], (PAINT,)),
    "truck": (assets.truck, SIZE_MEAN["truck"], (PAINT,)),
    "bus": (assets.bus, SIZE_MEAN["bus"], (PAINT,)),
    "pedestrian": (lambda *a: assets.pedestrian(*a).build(), SIZE_MEAN["pedestrian"], RIDER),
    "motorcycle": (assets.motorcycle, (2.10, 0.76, 1.5), (PAINT, RIDER)),
    "bicycle": (assets.bicycle, (1.69, 0.60, 1.55), (PAINT, RIDER)),
}


def _mesh(name):
    build, size, args = MESHES[name]
    return build(*size, *args), np.array(size)


def _cast_through_cells(mesh, size, axes) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Rays through the centres of a RES grid over the plane ``axes`` of the box ``size`` (3,),
    starting outside the box and pointing into it along the third axis; the grid is symmetric
    about 0, so a half turn is a flip of the array. Returns the hit distances, the triangles hit
    (-1 for none), both (n0 * n1,), and the grid's shape."""
    n = np.ceil(size[list(axes)] / RES).astype(int) + 2
    c0, c1 = ((np.arange(k) - (k - 1) / 2) * RES for k in n)
    A, B = np.meshgrid(c0, c1, indexing="ij")
    depth = 3 - sum(axes)                                              # the axis the rays run along
    origins = np.zeros((A.size, 3))
    origins[:, axes[0]], origins[:, axes[1]] = A.ravel(), B.ravel()
    origins[:, depth] = size[depth]
    dirs = np.zeros_like(origins)
    dirs[:, depth] = -1.0
    dist, tri, _ = RayTarget(mesh, mesh.metadata["reflectivity"]).first_hits(origins, dirs)
    return dist, tri, tuple(n)


def silhouette(mesh, size, axes) -> np.ndarray:
    """(n0, n1) bool: the cells of the plane ``axes`` whose centre the mesh's projection covers."""
    _, tri, shape = _cast_through_cells(mesh, size, axes)
    return (tri >= 0).reshape(shape)


def half_turn_iou(mesh, size, axes) -> float:
    """IoU of a silhouette and the silhouette of the mesh turned by 180 degrees about z:
    (x, y) -> (-x, -y) seen from above, x -> -x seen from the side."""
    s = silhouette(mesh, size, axes)
    turned = s[::-1, ::-1] if axes == (0, 1) else s[::-1, :]
    return float((s & turned).sum() / (s | turned).sum())


def top_heights(mesh, size) -> np.ndarray:
    """(n0, n1) height of the mesh's top surface above the box bottom per cell, 0 where nothing
    is (a ray cast straight down through every cell centre, from ``h`` above the box centre)."""
    dist, tri, shape = _cast_through_cells(mesh, size, (0, 1))
    return np.where(tri >= 0, 1.5 * size[2] - np.where(tri >= 0, dist, 0.0), 0.0).reshape(shape)


@pytest.mark.parametrize("cls", ["car", "truck", "bus", "motorcycle", "bicycle", "pedestrian",
                                 "traffic_cone", "barrier"])
def test_meshes_lie_inside_their_boxes_at_every_size(cls):
    """Sizes drawn as the worlds draw them, with and without riders, parked or not."""
    rng = np.random.default_rng(7)
    for k in range(24):
        a = make_actor(k, cls, rng, parked=bool(k % 2), rider=bool(k % 3))
        lo, hi = a.mesh.bounds
        half = np.array(a.size) / 2
        assert (lo >= -half - 1e-9).all() and (hi <= half + 1e-9).all(), (cls, a.size, a.mesh.bounds)
        # The mesh spans its box along x and z (a tight box), within a few centimetres; a parked
        # bicycle's box is drawn taller than its frame.
        tight = [0] if cls == "bicycle" else [0, 2]
        assert (hi[tight] - lo[tight] >= 2 * half[tight] - 0.1).all(), (cls, a.size, a.mesh.bounds)
        assert len(a.mesh.metadata["reflectivity"]) == len(a.mesh.faces) == len(a.mesh.visual.face_colors)


@pytest.mark.parametrize("name, axes, most", [
    ("pedestrian", (0, 1), 0.75), ("pedestrian", (0, 2), 0.75),
    ("motorcycle", (0, 1), 0.75), ("motorcycle", (0, 2), 0.75),
    ("bicycle", (0, 1), 0.75), ("bicycle", (0, 2), 0.75),
    ("car", (0, 2), 0.75), ("truck", (0, 2), 0.75),
    # A city bus is a box from both ends: its roof pod, overhangs and windscreen's rake are all
    # that tell them apart in outline.
    ("bus", (0, 2), 0.9),
])
def test_a_half_turn_changes_the_silhouette(name, axes, most):
    mesh, size = _mesh(name)
    assert half_turn_iou(mesh, size, axes) <= most


@pytest.mark.parametrize("name, most", [("car", 0.75), ("truck", 0.8), ("bus", 0.95)])
def test_a_half_turn_changes_the_top_heights(name, most):
    """Vehicles fill their footprint, so seen from above the front and back differ in height:
    hood against roof, cab against cargo box. Compared as sum(min) / sum(max) of the heights."""
    mesh, size = _mesh(name)
    H = top_heights(mesh, size)
    turned = H[::-1, ::-1]
    assert np.minimum(H, turned).sum() / np.maximum(H, turned).sum() <= most


def _scan(mesh, sensor_xy, z=1.84 - 0.86):
    """A spinning 32-beam scan from ``sensor_xy`` (box frame, ``z`` above the box centre): the
    hit points (m, 3) and the reflectivity of the faces hit (m,)."""
    az = np.radians(np.arange(0.0, 360.0, 0.1))
    AZ, EL = np.meshgrid(az, np.radians(ELEVATIONS_DEG), indexing="ij")
    d = np.stack([np.cos(EL) * np.cos(AZ), np.cos(EL) * np.sin(AZ), np.sin(EL)], -1).reshape(-1, 3)
    o = np.tile([*sensor_xy, z], (len(d), 1))
    refl = mesh.metadata["reflectivity"]
    dist, tri, _ = RayTarget(mesh, refl).first_hits(o, d)
    hit = tri >= 0
    return o[hit] + d[hit] * dist[hit, None], refl[tri[hit]]


def test_a_cars_front_half_and_back_half_reflect_differently():
    """Seen from the side, the halves' mean reflectivity differs by at least 15%; head-on, only
    the front shows headlights and only the back tail lights, and both show a plate."""
    mesh, _ = _mesh("car")
    pts, rho = _scan(mesh, (0.0, -8.0))
    front, back = rho[pts[:, 0] > 0].mean(), rho[pts[:, 0] < 0].mean()
    assert abs(front - back) >= 0.15 * max(front, back)
    for ahead, lamp, other in ((1.0, parts.HEADLIGHT_REFL, parts.TAILLIGHT_REFL),
                               (-1.0, parts.TAILLIGHT_REFL, parts.HEADLIGHT_REFL)):
        rho = np.concatenate([_scan(mesh, (ahead * r, 0.0))[1] for r in (8.0, 10.0, 12.0)])
        assert np.isin(np.float32([lamp, parts.PLATE_REFL]), rho).all()
        assert not np.isin(np.float32(other), rho)


@pytest.fixture(scope="module")
def grid():
    return Grid(load_preset("tiny").layout)


def test_standing_pedestrians_face_the_road_they_wait_to_cross(grid):
    """Just before a crossing road, facing it; just after one (it is behind), facing back to it."""
    hw = grid.road_half_width
    origin, heading = np.array([0.0, grid.ys[0] - hw - 3.0]), 0.0       # a sidewalk line going +x
    for way in (0.0, 0.37, 0.99):
        ahead = _standing_heading(grid, origin, heading, grid.xs[0] - hw - WAIT_AT_CURB + 0.5, way)
        behind = _standing_heading(grid, origin, heading, grid.xs[0] + hw + 1.0, way)
        assert abs(ahead - heading) <= TURN + 1e-12
        assert abs(np.cos(behind - heading - np.pi) - 1.0) <= 1 - np.cos(TURN) + 1e-12


def test_standing_pedestrians_elsewhere_face_along_the_sidewalk_or_across_it(grid):
    """Away from corners, each way takes its share of the variate, turned by at most TURN; the
    road the line runs along is on its left."""
    hw = grid.road_half_width
    origin, heading = np.array([0.0, grid.ys[0] - hw - 3.0]), 0.0
    s = (grid.xs[0] + grid.xs[1]) / 2                                  # mid-block
    way = np.linspace(0.0, 1.0, 2001)[:-1]
    yaw = np.array([_standing_heading(grid, origin, heading, s, q) for q in way])
    bases = np.array([0.0, np.pi, np.pi / 2, -np.pi / 2])
    off = np.angle(np.exp(1j * (yaw[:, None] - bases[None])))          # (q, 4) wrapped
    nearest = np.abs(off).argmin(1)
    assert (np.abs(off[np.arange(len(way)), nearest]) <= TURN + 1e-9).all()
    np.testing.assert_allclose(np.bincount(nearest, minlength=4) / len(way), STANDING_WAYS, atol=1e-3)


def test_standing_pedestrians_close_together_face_each_other():
    """Two people 2 m apart turn to each other; a third far away and a walker keep their way."""
    def plan(xy, v, heading=0.3):
        actor = Actor(0, "pedestrian", SIZE_MEAN["pedestrian"], None, np.zeros((0, 6)))
        return Plan(actor, np.array(xy, float), heading, 0.0, 10.0 * (v > 0), v)
    a, b, far, walker = plan((0, 0), 0.0), plan((1.2, 1.6), 0.0), plan((30, 0), 0.0), plan((0.5, 0.5), 1.2)
    _face_groups([a, b, far, walker])
    assert a.heading == pytest.approx(np.arctan2(1.6, 1.2))
    assert b.heading == pytest.approx(np.arctan2(-1.6, -1.2))
    assert far.heading == walker.heading == 0.3
