"""Vehicles that turn at intersections, and hitched trailers that follow their trucks through the
turns: a synthetic tractor and trailer through a 90-degree turn, the route's closed form, and
generated urban worlds in which vehicles and trains turn without ever touching anything."""
from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest
import trimesh

from simgen import geometry, turns
from simgen.config import load_preset
from simgen.curbside import HITCH_GAP, hitch
from simgen.layout import MAP_PAD, MAP_RESOLUTION, Grid, drivable_mask
from simgen.motion import simulate
from simgen.paths import Routes, Turn, pull
from simgen.placement import Plan
from simgen.scene import LIDAR_PERIOD, sample_world
from simgen.turns import min_turn_radius, outline, path_clear, turn_ahead
from simgen.world import Actor

from test_shadows import look_at

TRUCK, TRAILER = (6.74, 2.46, 2.73), (12.01, 2.87, 3.82)     # the nuScenes mean sizes
SPEED = 8.0
# Left from the curb lane (5.25 m right of the centreline: radius hw + 5.25 = 14.75 m) and right
# from the lane by the centreline (1.75 m: hw - 1.75 = 7.75 m) of the urban preset (hw = 9.5 m).
TRAIN_TURNS = [(True, 5.25), (False, 1.75)]
URBAN_SEEDS, URBAN_SAMPLES = (0, 1, 2, 3), 20


def _actor(idx: int, cls: str, size) -> Actor:
    """An actor without a mesh: motion needs only its size."""
    return Actor(idx, cls, size, None, np.zeros((0, 6)))


def _train_through_turn(left: bool, lateral: float):
    """A truck and its trailer 60 m before the middle intersection of the urban grid, driving
    east at ``SPEED`` in the lane ``lateral`` right of the centreline, turning at it; simulated
    until the trailer has long straightened up. Returns (grid, plan, xy (2, K, 2), yaw (2, K))."""
    grid = Grid(load_preset("urban").layout)
    origin = np.array([MAP_PAD, grid.ys[1] - lateral])
    s0 = grid.xs[1] - MAP_PAD - 60.0
    turn, length = turn_ahead(grid, origin, 0.0, s0, lateral, left)
    plan = Plan(_actor(1, "truck", TRUCK), origin, 0.0, s0, length, SPEED, priority=1, turn=turn)
    trailer = hitch(_actor(2, "trailer", TRAILER), plan)
    routes, behind = Routes.of(origin[None], [0.0], [turn]), plan.s0 - trailer.s0
    assert path_clear(grid, routes, s0, turn, np.array(TRUCK), np.array(TRAILER), behind)   # a turn placement takes
    times = LIDAR_PERIOD * np.arange(400)                    # 20 s: 160 m of travel
    xy, yaw, _ = simulate([plan, trailer], np.zeros((0, 7)), times)
    return grid, plan, xy, yaw


def _boxes(xy: np.ndarray, yaw: np.ndarray, size) -> np.ndarray:
    """(K, 7) boxes of one actor's track xy (K, 2), yaw (K,)."""
    return np.concatenate([xy, np.zeros((len(xy), 1)), np.broadcast_to(size, (len(xy), 3)), yaw[:, None]], 1)


def _on_drivable(mask: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 2) global points -> (...) bool: on a drivable pixel of ``mask`` (row 0 = max y)."""
    col = np.floor(points[..., 0] / MAP_RESOLUTION).astype(int)
    row = np.floor(mask.shape[0] - points[..., 1] / MAP_RESOLUTION).astype(int)
    return mask[row, col] == 255


@pytest.mark.parametrize("left, lateral", TRAIN_TURNS, ids=["left", "right"])
def test_trailer_follows_its_tractor_through_a_turn(left, lateral):
    grid, plan, xy, yaw = _train_through_turn(left, lateral)
    tractor, trailer = _boxes(xy[0], yaw[0], TRUCK), _boxes(xy[1], yaw[1], TRAILER)
    # The tractor turns a quarter, and never touches its trailer.
    assert yaw[0, -1] == pytest.approx(plan.turn.angle, abs=1e-12)
    assert not geometry.bev_overlap_pairwise(tractor, trailer, 0.0).any()
    # The trailer lags: while the tractor turns, it has turned less, by up to tens of degrees.
    articulation = (yaw[0] - yaw[1]) * np.sign(plan.turn.angle)
    assert articulation.min() > -1e-9 and np.degrees(articulation.max()) > 30
    # ... and comes back to the tractor's heading after. Once the hitch runs straight, tan(phi/2)
    # of the kinematic trailer decays as exp(-d / L) with the distance d: after 5 drawbars L it
    # is below 1% of its peak; the 0.05 s steps add far less than 1e-3 rad.
    drawbar = HITCH_GAP + TRAILER[0] / 2
    s_straight = plan.turn.end + TRUCK[0] / 2 + 5 * drawbar
    travelled = plan.s0 + SPEED * LIDAR_PERIOD * np.arange(xy.shape[1])     # nothing slows it down
    settled = travelled > s_straight
    assert settled.any()
    bound = 2 * np.arctan(np.tan(articulation.max() / 2) * np.exp(-5)) + 1e-3
    assert np.abs(articulation[settled]).max() < bound
    # Every swept box stays on the drivable area of the map.
    mask = drivable_mask(grid)
    assert _on_drivable(mask, outline(np.concatenate([tractor, trailer]))).all()


def test_a_turn_too_tight_for_a_train_is_refused():
    """Right from the curb lane the arc's radius is 4.25 m: too tight for a truck to steer, and a
    12 m trailer would jackknife; a car makes it."""
    grid = Grid(load_preset("urban").layout)
    origin, s0 = np.array([MAP_PAD, grid.ys[1] - 5.25]), grid.xs[1] - MAP_PAD - 60.0
    turn, _ = turn_ahead(grid, origin, 0.0, s0, 5.25, left=False)
    routes = Routes.of(origin[None], [0.0], [turn])
    behind = TRUCK[0] / 2 + HITCH_GAP + TRAILER[0] / 2
    assert turn.radius == pytest.approx(4.25)
    assert path_clear(grid, routes, s0, turn, np.array((4.61, 1.95, 1.72)))
    assert not path_clear(grid, routes, s0, turn, np.array(TRUCK))
    assert min_turn_radius(TRUCK[0]) < 7.75          # the same truck may turn right from the inner lane
    # With the steering limit lifted, the trailer alone still makes the turn impossible.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(turns, "MAX_STEER", np.radians(89.0))
        assert path_clear(grid, routes, s0, turn, np.array(TRUCK))
        assert not path_clear(grid, routes, s0, turn, np.array(TRUCK), np.array(TRAILER), behind)


def test_route_closed_form():
    """A left quarter turn of radius 10 at s = 5 from the origin heading east: exact points."""
    routes = Routes.of(np.zeros((1, 2)), [0.0], [Turn(5.0, 10.0, np.pi / 2)])
    s = np.array([[0.0, 5.0, 5.0 + 10 * np.pi / 4, 5.0 + 10 * np.pi / 2, 5.0 + 10 * np.pi / 2 + 3.0]])
    xy, yaw = routes.at(s)
    c = 10 / np.sqrt(2)
    expected = [(0, 0), (5, 0), (5 + c, 10 - c), (15, 10), (15, 13)]
    assert np.allclose(xy[0], expected, atol=1e-12)
    assert np.allclose(yaw[0], [0, 0, np.pi / 4, np.pi / 2, np.pi / 2], atol=1e-12)
    # A straight route is origin + s u, bit for bit, as paths were before turns existed.
    straight = Routes.of(np.array([[3.0, 4.0]]), [np.pi / 2], [None])
    s = np.array([7.3])
    u = np.array([np.cos(np.pi / 2), np.sin(np.pi / 2)])
    assert np.array_equal(straight.at(s)[0][0], np.array([3.0, 4.0]) + s[0] * u)


def test_kinematic_trailer_on_a_straight_path_stays_on_the_line():
    """Dragged along a line, the axle keeps its distance on that line: today's placement."""
    u = np.array([np.cos(0.7), np.sin(0.7)])
    axle = np.array([[-8.0 * u[0], -8.0 * u[1]]])
    for s in np.cumsum(np.full(200, 0.37)):
        axle = pull((s * u)[None], axle, np.array([8.0]))
    assert np.allclose(axle[0], (s - 8.0) * u, atol=1e-9)


@pytest.fixture(scope="module")
def urban_worlds():
    return [sample_world(load_preset("urban"), np.random.default_rng(s), URBAN_SAMPLES) for s in URBAN_SEEDS]


def test_urban_vehicles_and_trains_turn(urban_worlds):
    turned_vehicles = turned_trailers = 0
    for w in urban_worlds:
        turned = np.ptp(w.yaw, axis=1) > np.pi / 4
        cls = np.array([a.cls for a in w.actors])
        towed = np.array([a.towed_by >= 0 for a in w.actors])
        turned_vehicles += (turned & (cls != "trailer")).sum()
        turned_trailers += (turned & towed).sum()
        assert not turned[0]                                       # the ego goes straight
        assert set(cls[turned]) <= {"car", "truck", "bus", "motorcycle", "trailer"}
    assert turned_vehicles >= 10 and turned_trailers >= 1, (turned_vehicles, turned_trailers)


def test_urban_boxes_never_overlap(urban_worlds):
    for w in urban_worlds:
        movers = np.nonzero(np.ptp(w.xy, axis=1).max(-1) > 0)[0]
        for t in np.union1d(w.times, (w.times[:-1] + w.times[1:]) / 2):
            b = w.boxes_at(float(t))
            others = np.concatenate([b, w.static_boxes])
            i, j = geometry.near_pairs(b[movers], others)
            i = movers[i]
            keep = i != j
            hit = geometry.bev_overlap_pairwise(b[i[keep]], others[j[keep]], 0.0)
            assert not hit.any(), (t, list(zip(i[keep][hit], j[keep][hit]))[:5])


def test_urban_headings_are_continuous(urban_worlds):
    """No heading jumps more than its motion allows: on an arc of radius R a step of chord c
    turns by 2 asin(c / 2R), and R is at least the tightest turn's, hw - the outer lane's
    offset; a trailer turns by at most asin of its hitch's step over its drawbar."""
    for w in urban_worlds:
        grid = Grid(load_preset("urban").layout)
        r_min = grid.road_half_width - (grid.cfg.lanes_per_direction - 0.5) * grid.cfg.lane_width
        index = {a.id: i for i, a in enumerate(w.actors)}
        d_yaw = np.abs(np.diff(w.yaw, axis=1))
        chord = np.linalg.norm(np.diff(w.xy, axis=1), axis=-1)
        for i, a in enumerate(w.actors):
            if a.towed_by < 0:
                assert (d_yaw[i] <= 2 * np.arcsin(np.minimum(chord[i] / (2 * r_min), 1)) + 1e-9).all(), a.id
                continue
            j = index[a.towed_by]
            hitch = w.xy[j] - w.sizes[j, 0] / 2 * np.stack([np.cos(w.yaw[j]), np.sin(w.yaw[j])], -1)
            drawbar = np.linalg.norm(hitch - w.xy[i], axis=-1)
            step = np.linalg.norm(np.diff(hitch, axis=0), axis=-1)
            assert (d_yaw[i] <= np.arcsin(np.minimum(step / (drawbar[:-1] - step), 1)) + 1e-9).all(), a.id


def _render_actor(yaw_track, yaw_now: float) -> np.ndarray:
    """(H, W, 3) rgb of a 4 x 2 x 1.5 m box actor whose heading over the world's two samples is
    ``yaw_track``, posed at ``yaw_now``, on a grey plane under the sun, seen from above its corner."""
    from simgen.camera import Renderer
    from simgen.config import CameraConfig
    plane = trimesh.creation.box(extents=(60.0, 60.0, 0.02))
    plane.apply_translation((0.0, 0.0, -0.01))
    plane.visual.face_colors = (150, 150, 150, 255)
    post = trimesh.creation.box(extents=(0.5, 0.5, 2.0))           # something static that casts a shadow
    post.apply_translation((20.0, 20.0, 1.0))
    post.visual.face_colors = (150, 150, 150, 255)
    mesh = trimesh.creation.box(extents=(4.0, 2.0, 1.5))
    mesh.visual.face_colors = (200, 60, 40, 255)
    ego = Actor(0, "car", (4.0, 2.0, 1.5), mesh, np.zeros((0, 6)), annotate=False)
    car = Actor(1, "car", (4.0, 2.0, 1.5), mesh, np.zeros((0, 6)))
    world = types.SimpleNamespace(
        static_mesh=trimesh.util.concatenate([plane, post]), actors=[ego, car],
        meta={"sun_azimuth": 2.3, "sun_elevation": 0.7}, speed=np.ones((2, 2)), yaw=np.array([[0.0, 0.0], yaw_track]),
        boxes_at=lambda t: np.array([[-20.0, 0, 0.75, 4, 2, 1.5, 0], [0, 0, 0.75, 4, 2, 1.5, yaw_track[0]]]))
    cfg = dataclasses.replace(CameraConfig(), resolution=(160, 120), shadows=True)
    r = Renderer(cfg)
    try:
        r.set_world(world, key=("turn-test", tuple(yaw_track)))
        cam = types.SimpleNamespace(K=np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]]), resolution=(160, 120))
        T_global_from_cam = look_at(np.array([-6.0, -7.0, 5.0]), (0.0, 0.0, 0.5))
        return r.render(cam, T_global_from_cam, {1: geometry.pose_2d(0.0, 0.0, yaw_now, 0.75)})[0]
    finally:
        r.close()


def test_a_turned_actor_is_shaded_for_its_heading_at_render_time():
    """An actor that has turned a quarter looks as one that always had its new heading, not as
    one lit for its old heading."""
    turned = _render_actor([0.0, np.pi / 2], np.pi / 2)
    always = _render_actor([np.pi / 2, np.pi / 2], np.pi / 2)
    stale = _render_actor([0.0, 0.0], np.pi / 2)          # lit for heading 0, drawn at pi / 2
    assert np.abs(turned.astype(int) - always).max() <= 1
    assert np.abs(stale.astype(int) - always).max() > 10
