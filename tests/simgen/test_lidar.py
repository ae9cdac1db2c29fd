"""The simulated HDL-32E: beam pattern, exact ranges on known geometry, intensity, noise, limits.

Most tests scan a hand-built world: a closed axis-aligned room (floor top at z = 0, a front wall
at a known distance ahead of the ego) around a stationary ego, so every ray hits a known plane
and its range is the analytic ray-box exit distance.
"""
from __future__ import annotations

import numpy as np
import pytest

from simgen import geometry
from simgen.assets import Parts
from simgen.config import LidarConfig, load_preset
from simgen.layout import Grid
from simgen.lidar import ELEVATIONS_DEG, N_BEAMS, SWEEP_PERIOD, LidarScanner, RayTarget, ray_pattern
from simgen.rig import T_ego_from_lidar
from simgen.scene import sample_world
from simgen.traffic import EGO_SIZE, make_actor
from simgen.world import EGO_CENTRE_AHEAD_OF_ORIGIN, Actor, World
from simgen import assets

N_AZ = 1091                                   # round(360 / 0.33)
# Room planes: (axis, +1 for the max side / -1 for the min side) -> reflectivity.
ROOM_REFL = {(0, 1): 0.5, (0, -1): 0.4, (1, 1): 0.3, (1, -1): 0.35, (2, -1): 0.2, (2, 1): 0.6}
ROOM = ((-15.0, -12.0, 0.0), (10.0, 12.0, 30.0))   # interior (lo, hi); the front wall is at x = 10


# ---------------------------------------------------------------------------------------------
# Hand-built worlds

def room_mesh(lo, hi, refl=ROOM_REFL, thick=1.0):
    """Six boxes closing the interior [lo, hi]; face reflectivity per plane."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, L = (lo + hi) / 2, hi - lo + 2 * thick
    p = Parts()
    for axis in range(3):
        for side in (-1, 1):
            ext = L.copy()
            ext[axis] = thick
            centre = c.copy()
            centre[axis] = (hi if side > 0 else lo)[axis] + side * thick / 2
            p.box(ext, centre, (128, 128, 128), refl[(axis, side)])
    return p.build()


def ego_actor() -> Actor:
    """The ego as traffic.py builds it: a car mesh, not annotated."""
    return Actor(0, "car", EGO_SIZE, assets.car(*EGO_SIZE, (200, 200, 200)), np.zeros((0, 6)), annotate=False)


def hand_world(static_mesh, ego_speed=0.0, actors=(), actor_xy=()) -> World:
    """A world with the ego (ego frame = global frame at t = 0) and optional static actors."""
    times = SWEEP_PERIOD * np.arange(21)
    K = len(times)
    ego_xy = np.stack([EGO_CENTRE_AHEAD_OF_ORIGIN + ego_speed * times, np.zeros(K)], -1)
    xy = [ego_xy] + [np.broadcast_to(np.asarray(p, float), (K, 2)) for p in actor_xy]
    acts = [ego_actor(), *actors]
    z = np.zeros((len(acts), K))
    for i, a in enumerate(acts[1:], 1):
        z[i] = a.size[2] / 2
    speed = np.zeros((len(acts), K))
    speed[0] = ego_speed
    return World(extent=(100.0, 100.0), static_mesh=static_mesh, static_boxes=np.zeros((0, 7)),
                 actors=acts, times=times, xy=np.array(xy), z=z, yaw=np.zeros((len(acts), K)),
                 speed=speed, drivable=np.zeros((8, 8), np.uint8))


def room_exit(o, d, lo, hi):
    """Analytic range from interior point o along unit directions d (m, 3) to the box [lo, hi],
    the axis of the plane hit and its side (+1 max, -1 min)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))
    axis = np.argmin(t, axis=1)
    rows = np.arange(len(d))
    return t[rows, axis], axis, np.sign(d[rows, axis]).astype(int)


def to_ego(sweep):
    """Sensor-frame points and directions of a sweep -> ego frame (stationary ego at the origin)."""
    T = T_ego_from_lidar()
    return geometry.apply(T, sweep.points_lidar[:, :3].astype(np.float64)), sweep.dir_lidar @ T[:3, :3].T, T[:3, 3]


@pytest.fixture(scope="module")
def room_sweep():
    cfg = LidarConfig(range_noise_sigma=0.0, min_return=0.0)
    world = hand_world(room_mesh(*ROOM))
    sweep = LidarScanner(cfg, world).scan(0.5, np.random.default_rng(0))
    return cfg, world, sweep


@pytest.fixture(scope="module")
def tiny_world():
    return sample_world(load_preset("tiny"), np.random.default_rng(0), 2)


# ---------------------------------------------------------------------------------------------
# Beam pattern

# The HDL-32E's vertical angle per laser ID (degrees), as its user manual tabulates them, in
# firing order: the two halves of the fan interleaved, 4/3 deg apart, rounded to 0.01 deg.
HDL32E_VERTICAL_DEG = (-30.67, -9.33, -29.33, -8.00, -28.00, -6.67, -26.67, -5.33, -25.33, -4.00, -24.00, -2.67,
                       -22.67, -1.33, -21.33, 0.00, -20.00, 1.33, -18.67, 2.67, -17.33, 4.00, -16.00, 5.33,
                       -14.67, 6.67, -13.33, 8.00, -12.00, 9.33, -10.67, 10.67)


def test_beam_elevations_are_the_hdl32e_table():
    """Ring r is the r-th lowest laser: the elevations are the manual's, sorted, within 0.01 deg
    (its rounding, and the even spread of the simulator's 41.34 deg against the manual's 4/3 deg
    steps, which meet at both ends)."""
    assert len(ELEVATIONS_DEG) == len(HDL32E_VERTICAL_DEG)
    np.testing.assert_allclose(ELEVATIONS_DEG, np.sort(HDL32E_VERTICAL_DEG), atol=0.01)


def test_ray_pattern():
    frac, ring, d = ray_pattern(LidarConfig())
    assert len(frac) == len(ring) == len(d) == N_AZ * len(HDL32E_VERTICAL_DEG) == 34912
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(np.bincount(ring), np.full(N_BEAMS, N_AZ))
    el = np.degrees(np.arcsin(d[:, 2]))
    np.testing.assert_allclose(el, ELEVATIONS_DEG[ring], atol=1e-9)
    # firing fractions in (0, 1), non-decreasing, one column of 32 rays per azimuth step
    assert 0 < frac.min() and frac.max() < 1 and (np.diff(frac) >= 0).all()
    assert len(np.unique(frac)) == N_AZ
    az = np.arctan2(d[::N_BEAMS, 1], d[::N_BEAMS, 0])
    step = np.degrees(np.abs(geometry.wrap_angle(np.diff(az))))
    np.testing.assert_allclose(step, 360.0 / N_AZ, atol=1e-9)
    # the step follows azimuth_step_deg
    assert len(ray_pattern(LidarConfig(azimuth_step_deg=1.0))[0]) == 360 * N_BEAMS


# ---------------------------------------------------------------------------------------------
# Exact geometry

def test_every_ray_returns_on_the_known_planes(room_sweep):
    cfg, world, sweep = room_sweep
    n = N_AZ * N_BEAMS
    assert len(sweep.points_lidar) == n                       # a closed room: no ray is lost
    assert sweep.points_lidar.dtype == np.float32 and sweep.points_lidar.shape == (n, 5)
    p_ego, d_ego, o = to_ego(sweep)
    t_true, axis, side = room_exit(o, d_ego, *ROOM)
    np.testing.assert_allclose(np.linalg.norm(sweep.dir_lidar, axis=1), 1.0, atol=1e-12)
    # measured range == analytic ray-plane distance
    np.testing.assert_allclose(sweep.range, t_true, rtol=0, atol=1e-6)
    # every point lies on the plane its ray hits
    lo, hi = np.array(ROOM[0]), np.array(ROOM[1])
    plane = np.where(side > 0, hi[axis], lo[axis])
    np.testing.assert_allclose(p_ego[np.arange(n), axis], plane, rtol=0, atol=1e-4)
    wall = (axis == 0) & (side > 0)
    ground = (axis == 2) & (side < 0)
    assert wall.sum() > 4000 and ground.sum() > 4000
    assert np.abs(p_ego[wall, 0] - 10.0).max() < 1e-4
    assert np.abs(p_ego[ground, 2]).max() < 1e-4
    # points are range * direction from the sensor (stationary ego), in the sensor frame
    np.testing.assert_allclose(sweep.points_lidar[:, :3], sweep.range[:, None] * sweep.dir_lidar, atol=1e-4)
    # the per-point attributes
    np.testing.assert_allclose(sweep.rho, [ROOM_REFL[(a, s)] for a, s in zip(axis, side)], atol=1e-6)
    np.testing.assert_allclose(sweep.cos_inc, np.abs(d_ego[np.arange(n), axis]), atol=1e-9)
    assert (sweep.actor_id == 0).all()
    assert (sweep.time > 0.5 - SWEEP_PERIOD).all() and (sweep.time < 0.5).all()


def test_ring_matches_elevation_in_sensor_frame(room_sweep):
    """The HDL-32E's lasers are fixed in the sensor: a point's ring is the elevation of its ray
    in the LIDAR_TOP frame, the frame the .pcd.bin is written in."""
    _, _, sweep = room_sweep
    ring = sweep.points_lidar[:, 4]
    assert (ring == np.round(ring)).all() and ring.min() == 0 and ring.max() == N_BEAMS - 1
    np.testing.assert_array_equal(np.bincount(ring.astype(int)), np.full(N_BEAMS, N_AZ))
    el = np.degrees(np.arcsin(sweep.dir_lidar[:, 2]))
    err = np.abs(el - ELEVATIONS_DEG[ring.astype(int)])
    assert err.max() < 0.01, f"ring vs sensor-frame elevation differ by up to {err.max():.3f} deg"
    # the same from the stored xyz (stationary ego: the sensor origin is the ray origin)
    xyz = sweep.points_lidar[:, :3].astype(np.float64)
    el_xyz = np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1)))
    assert np.abs(el_xyz - ELEVATIONS_DEG[ring.astype(int)]).max() < 0.01


def _check_intensity(cfg, sweep, lo, hi):
    inten = sweep.points_lidar[:, 3]
    assert (inten >= 0).all() and (inten <= 255).all() and (inten == np.round(inten)).all()
    _, d_ego, o = to_ego(sweep)
    n = len(d_ego)
    R, axis, side = room_exit(o, d_ego, lo, hi)
    cos = np.abs(d_ego[np.arange(n), axis])
    rho = np.array([ROOM_REFL[(a, s)] for a, s in zip(axis, side)])
    expect = np.round(255.0 * np.minimum(1.0, rho * cos / R ** 2 * cfg.intensity_ref_range ** 2))
    np.testing.assert_array_equal(inten, expect)
    return inten, R, axis, side, cos


def test_intensity_saturates_up_close():
    lo, hi = (-2.0, -2.5, 0.0), (3.5, 2.5, 3.0)
    cfg = LidarConfig(range_noise_sigma=0.0, min_return=0.0, min_range=0.0)
    sweep = LidarScanner(cfg, hand_world(room_mesh(lo, hi))).scan(0.5, np.random.default_rng(0))
    inten, *_ = _check_intensity(cfg, sweep, lo, hi)
    assert 0 < (inten == 255).sum() < len(inten)      # both regimes occur


def test_intensity_model(room_sweep):
    cfg, _, sweep = room_sweep
    inten, R, axis, side, cos = _check_intensity(cfg, sweep, *ROOM)
    # normal incidence on the front wall (rho 0.5, 9.056 m from the sensor):
    # round(255 * 0.5 * 1 / 9.056^2 * 36) = round(55.96) = 56
    wall = np.nonzero((axis == 0) & (side > 0))[0]
    k = wall[np.argmax(cos[wall])]
    assert cos[k] > 0.9995 and R[k] == pytest.approx(10.0 - 0.943713, abs=0.01)
    assert inten[k] == 56


def test_min_return_drops_weak_returns():
    world = hand_world(room_mesh(*ROOM))
    cfg = LidarConfig(range_noise_sigma=0.0, min_return=2e-3)
    sweep = LidarScanner(cfg, world).scan(0.5, np.random.default_rng(0))
    power = sweep.rho * sweep.cos_inc / sweep.range ** 2
    assert (power >= 2e-3).all()
    full = LidarScanner(LidarConfig(range_noise_sigma=0.0, min_return=0.0), world).scan(0.5, np.random.default_rng(0))
    p_full = full.rho * full.cos_inc / full.range ** 2
    assert len(sweep.range) == (p_full >= 2e-3).sum() < len(full.range)


def test_range_noise_on_the_wall():
    sigma = 0.02
    cfg = LidarConfig(range_noise_sigma=sigma, min_return=0.0)
    sweep = LidarScanner(cfg, hand_world(room_mesh(*ROOM))).scan(0.5, np.random.default_rng(1))
    _, d_ego, o = to_ego(sweep)
    t_true, axis, side = room_exit(o, d_ego, *ROOM)
    wall = (axis == 0) & (side > 0)
    err = sweep.range[wall] - t_true[wall]
    assert wall.sum() > 4000
    assert abs(err.std() - sigma) < 0.003
    assert abs(err.mean()) < 0.003
    # the noise moves the point along its ray: the stored point sits at the measured range
    xyz = sweep.points_lidar[:, :3].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(xyz, axis=1), sweep.range, atol=1e-4)


def test_range_limits():
    """Points closer than min_range or farther than max_range are dropped, and only those."""
    lo, hi = (-90.0, -40.0, 0.0), (85.0, 40.0, 30.0)      # floor hits from 3.4 m, walls beyond 70 m
    world = hand_world(room_mesh(lo, hi))
    base = dict(range_noise_sigma=0.0, min_return=0.0)
    full = LidarScanner(LidarConfig(min_range=0.0, max_range=100.0, **base), world).scan(0.5, np.random.default_rng(0))
    cut = LidarScanner(LidarConfig(min_range=5.0, max_range=70.0, **base), world).scan(0.5, np.random.default_rng(0))
    assert full.range.min() < 5.0 and full.range.max() > 70.0
    assert cut.range.min() >= 5.0 and cut.range.max() <= 70.0
    keep = (full.range >= 5.0) & (full.range <= 70.0)
    assert len(cut.range) == keep.sum()
    np.testing.assert_allclose(np.sort(cut.range), np.sort(full.range[keep]), atol=1e-9)
    norms = np.linalg.norm(cut.points_lidar[:, :3].astype(np.float64), axis=1)
    assert norms.min() >= 5.0 - 1e-4 and norms.max() <= 70.0 + 1e-4
    # with noise, the limits hold on the measured range
    noisy = LidarScanner(LidarConfig(min_range=5.0, max_range=70.0, range_noise_sigma=0.3, min_return=0.0),
                         world).scan(0.5, np.random.default_rng(2))
    assert noisy.range.min() >= 5.0 and noisy.range.max() <= 70.0


def test_default_range_limits_on_a_real_world(tiny_world):
    cfg = LidarConfig()
    sweep = LidarScanner(cfg, tiny_world).scan(1.0, np.random.default_rng(0))
    assert len(sweep.range) > 10000
    assert sweep.range.min() >= cfg.min_range and sweep.range.max() <= cfg.max_range
    inten, ring = sweep.points_lidar[:, 3], sweep.points_lidar[:, 4]
    assert (inten >= 0).all() and (inten <= 255).all() and (inten == np.round(inten)).all()
    assert (ring == np.round(ring)).all() and set(np.unique(ring)) <= set(range(N_BEAMS))
    annotated = {a.id for a in tiny_world.actors if a.annotate}
    ids = set(np.unique(sweep.actor_id)) - {0}
    assert ids and ids <= annotated
    # no point inside the ego's footprint (any height)
    T_global_from_lidar = tiny_world.ego_pose(1.0) @ T_ego_from_lidar()
    p = geometry.apply(T_global_from_lidar, sweep.points_lidar[:, :3].astype(np.float64))
    ego = tiny_world.boxes_at(1.0)[0].copy()
    ego[5] = 1e3
    assert not geometry.points_in_box_mask(p, ego).any()


# ---------------------------------------------------------------------------------------------
# The ego is invisible to its own lidar

@pytest.mark.parametrize("ego_speed", [0.0, 10.0])
def test_no_returns_from_the_ego(ego_speed):
    world = hand_world(room_mesh((-40.0, -20.0, 0.0), (40.0, 20.0, 25.0)), ego_speed=ego_speed)
    cfg = LidarConfig(range_noise_sigma=0.0, min_return=0.0, min_range=0.0)
    for t in (0.3, 0.5):
        sweep = LidarScanner(cfg, world).scan(t, np.random.default_rng(0))
        assert len(sweep.range) == N_AZ * N_BEAMS
        assert (sweep.actor_id == 0).all()
        T = world.ego_pose(t) @ T_ego_from_lidar()
        p = geometry.apply(T, sweep.points_lidar[:, :3].astype(np.float64))
        ego = world.boxes_at(t)[0].copy()
        ego[5] = 1e3                                   # the whole column above the footprint
        assert not geometry.points_in_box_mask(p, ego).any()
        assert p[:, 2].min() > -1e-4                    # nothing below the floor either


def test_annotated_actor_next_to_the_ego_is_seen():
    """Sanity check of the ego test: a car placed where the ego is gets hit; the ego does not."""
    car = make_actor(1, "car", np.random.default_rng(0))
    world = hand_world(room_mesh((-40.0, -20.0, 0.0), (40.0, 20.0, 25.0)), actors=[car], actor_xy=[(1.3, 4.0)])
    sweep = LidarScanner(LidarConfig(range_noise_sigma=0.0, min_return=0.0), world).scan(0.5, np.random.default_rng(0))
    hit = sweep.actor_id == 1
    assert hit.sum() > 100
    assert set(np.unique(sweep.actor_id)) == {0, 1}
    p = geometry.apply(T_ego_from_lidar(), sweep.points_lidar[:, :3].astype(np.float64))
    box = world.boxes_at(0.5)[1]
    inside = geometry.points_in_box_mask(p, box + np.r_[0, 0, 0, 0.02, 0.02, 0.02, 0])
    assert inside[hit].all()                           # the car's points lie in its box
    assert np.abs(p[inside & ~hit, 2]).max() < 1e-4     # the rest in the box is floor under it


# ---------------------------------------------------------------------------------------------
# Ray engines

def _road_rays(world, n, seed):
    """n random rays leaving from 1.84 m above random points on the roads of a tiny world."""
    rng = np.random.default_rng(seed)
    g = Grid(load_preset("tiny").layout)
    lane = g.cfg.lanes_per_direction * g.cfg.lane_width
    along = rng.uniform(g.xs[0], g.xs[-1], n)
    across = rng.choice(g.ys, n) + rng.uniform(-lane, lane, n)
    horizontal = rng.random(n) < 0.5
    xy = np.where(horizontal[:, None], np.c_[along, across], np.c_[across, along])
    o = np.c_[xy, np.full(n, 1.84)]
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def _brute_force_first_hit(mesh, o, d, chunk=64):
    """Möller-Trumbore against every triangle: (m,) distance to the nearest hit, inf for a miss."""
    tri = np.asarray(mesh.triangles)
    v0, e1, e2 = tri[:, 0].T, (tri[:, 1] - tri[:, 0]).T, (tri[:, 2] - tri[:, 0]).T   # (3, F) each
    out = np.full(len(o), np.inf)
    for a in range(0, len(o), chunk):
        dx, dy, dz = (d[a:a + chunk, k, None] for k in range(3))                      # (c, 1)
        sx, sy, sz = (o[a:a + chunk, k, None] - v0[k] for k in range(3))              # (c, F)
        px, py, pz = dy * e2[2] - dz * e2[1], dz * e2[0] - dx * e2[2], dx * e2[1] - dy * e2[0]
        det = px * e1[0] + py * e1[1] + pz * e1[2]
        qx, qy, qz = sy * e1[2] - sz * e1[1], sz * e1[0] - sx * e1[2], sx * e1[1] - sy * e1[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            u = (sx * px + sy * py + sz * pz) * inv
            v = (dx * qx + dy * qy + dz * qz) * inv
            t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        out[a:a + chunk] = np.where(ok, t, np.inf).min(1)
    return out


def test_embree_matches_brute_force(tiny_world):
    mesh = tiny_world.static_mesh
    o, d = _road_rays(tiny_world, 1500, seed=1)
    target = RayTarget(mesh, mesh.metadata["reflectivity"], engine="embree")
    dist, tri, cos = target.first_hits(o, d)
    ref = _brute_force_first_hit(mesh, o, d)
    np.testing.assert_array_equal(np.isfinite(dist), np.isfinite(ref))
    np.testing.assert_array_equal(np.isfinite(dist), tri >= 0)
    both = np.isfinite(dist)
    assert 0.3 < both.mean() < 0.95
    np.testing.assert_allclose(dist[both], ref[both], rtol=0, atol=1e-5)
    np.testing.assert_allclose(target.reflectivity[tri[both]], mesh.metadata["reflectivity"][tri[both]])
    n = mesh.face_normals[tri[both]]
    np.testing.assert_allclose(cos[both], np.abs(np.einsum("md,md->m", n, d[both])), rtol=0, atol=1e-12)
    assert np.all(cos[~both] == 0)


def test_plane_hits_on_a_grazing_ray_does_not_raise():
    """A ray along its triangle's plane (cos 0) gets a non-finite distance, as numpy would give,
    not a ZeroDivisionError from the compiled kernel; tfar turns a far hit into a miss."""
    from simgen import lidar_kernels
    normals, plane = np.array([[0.0, 0.0, 1.0]]), np.array([0.0])
    tri = np.array([0, 0, -1])
    origins = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    dirs = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    dist, cos = lidar_kernels.plane_hits(tri.copy(), origins, dirs, normals, plane, np.zeros(0))
    assert dist[0] == 5.0 and cos[0] == 1.0
    assert not np.isfinite(dist[1]) and cos[1] == 0.0
    assert dist[2] == np.inf and cos[2] == 0.0
    far = tri.copy()
    dist, cos = lidar_kernels.plane_hits(far, origins, dirs, normals, plane, np.array([4.0, 9.0, 9.0]))
    assert far[0] == -1 and dist[0] == np.inf and cos[0] == 0.0


def test_threaded_sweep_gives_the_same_bytes():
    """A sweep cast in chunks over threads equals the sweep cast in one piece, field by field."""
    from simgen.lidar import MIN_RAYS_PER_THREAD
    cfg = load_preset("tiny")
    world = sample_world(cfg, np.random.default_rng(3), 4)
    one, three = LidarScanner(cfg.lidar, world, threads=1), LidarScanner(cfg.lidar, world, threads=3)
    assert len(one.frac) >= 3 * MIN_RAYS_PER_THREAD                    # the sweep is really split
    for t in (0.5, 1.25):
        a, b = one.scan(t, np.random.default_rng(1)), three.scan(t, np.random.default_rng(1))
        for f in ("points_lidar", "time", "actor_id", "rho", "cos_inc", "range", "dir_lidar"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
        assert np.isin(a.actor_id, [world.actors[i].id for i in one.moving_idx]).sum() > 20


def test_embree_matches_trimesh_triangle_engine(tiny_world):
    """The pure-Python fallback (used when embreex is missing) must give the same first hits."""
    mesh = tiny_world.static_mesh
    o, d = _road_rays(tiny_world, 2000, seed=2)
    refl = mesh.metadata["reflectivity"]
    d_e, t_e, _ = RayTarget(mesh, refl, engine="embree").first_hits(o, d)
    d_t, t_t, _ = RayTarget(mesh, refl, engine="triangle").first_hits(o, d)
    np.testing.assert_array_equal(t_e >= 0, t_t >= 0)
    both = (t_e >= 0) & (t_t >= 0)
    assert both.mean() > 0.3
    np.testing.assert_allclose(d_e[both], d_t[both], rtol=0, atol=1e-5)


def test_cut_down_scan_equals_casting_every_ray_at_every_mover():
    """Casting only the rays near each moving actor loses no return: same bytes as casting all."""
    cfg = load_preset("tiny")
    world = sample_world(cfg, np.random.default_rng(3), 4)
    fast = LidarScanner(cfg.lidar, world)
    full = LidarScanner(cfg.lidar, world)
    n = len(full.frac)
    full._candidate_rays = lambda boxes, *args: (np.tile(np.arange(n), len(boxes)), np.repeat(np.arange(len(boxes)), n))
    hits_on_movers = 0
    for t in (0.5, 1.25, 2.0):
        a, b = fast.scan(t, np.random.default_rng(1)), full.scan(t, np.random.default_rng(1))
        assert np.array_equal(a.points_lidar, b.points_lidar) and np.array_equal(a.actor_id, b.actor_id)
        hits_on_movers += np.isin(a.actor_id, [world.actors[i].id for i in fast.moving_idx]).sum()
    assert hits_on_movers > 100
