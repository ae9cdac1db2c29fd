"""Procedural worlds: no collisions ever, plausible speeds, nuScenes-like density and sizes."""
from __future__ import annotations

import numpy as np
import pytest

from simgen import geometry
from simgen.config import load_preset
from simgen.scene import keyframe_times, sample_world
from simgen.world import CLASSES

N_SAMPLES = 10
CASES = [("tiny", 0), ("tiny", 1), ("urban", 0), ("urban", 1)]
# Mean (l, w, h) per class: the nuScenes anchor sizes of the detection literature (PointPillars, SECOND).
SIZE_MEAN = {
    "car": (4.61, 1.95, 1.72), "truck": (6.74, 2.46, 2.73), "bus": (11.19, 2.94, 3.47),
    "motorcycle": (2.10, 0.76, 1.44), "bicycle": (1.69, 0.60, 1.27), "pedestrian": (0.73, 0.66, 1.76),
    "traffic_cone": (0.40, 0.40, 1.06), "barrier": (0.49, 2.49, 0.98),
    "construction_vehicle": (6.38, 2.73, 3.13), "trailer": (12.01, 2.87, 3.82),
}
MAX_SPEED = {"pedestrian": 1.8, "bicycle": 7.0}
EGO_MAX_SPEED = 15.0


@pytest.fixture(scope="module")
def worlds():
    return {(p, s): sample_world(load_preset(p), np.random.default_rng(s), N_SAMPLES) for p, s in CASES}


def _overlapping_pairs(a, b, same=False):
    """All (i, j) where geometry.bev_overlap(a, b)[i, j] (margin 0). Only the pairs whose bounding circles
    meet (a necessary condition) go through the exact test, bev_overlap's pairwise kernel."""
    ra, rb = np.hypot(a[:, 3], a[:, 4]) / 2, np.hypot(b[:, 3], b[:, 4]) / 2
    d = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    cand = d <= ra[:, None] + rb[None, :] + 1e-9
    if same:
        cand = np.triu(cand, 1)
    i, j = np.nonzero(cand)
    hit = geometry.bev_overlap_pairwise(a[i], b[j], margin=0.0)
    return list(zip(i[hit], j[hit]))


@pytest.mark.parametrize("case", CASES, ids=[f"{p}-{s}" for p, s in CASES])
def test_no_footprints_ever_overlap(worlds, case):
    w = worlds[case]
    n, K = w.xy.shape[:2]
    assert w.times[0] == 0.0 and w.times[-1] == pytest.approx(keyframe_times(N_SAMPLES)[-1] + 0.5)
    moves = np.ptp(w.xy, axis=1).max(-1) > 0
    still = np.nonzero(~moves)[0]
    movers = np.nonzero(moves)[0]
    assert len(movers) > 10
    # Actors that never move: check once, among themselves and against the static clutter.
    b0 = w.boxes_at(0.0)
    bad = [(still[i], still[j]) for i, j in _overlapping_pairs(b0[still], b0[still], same=True)]
    bad += [(still[i], f"static{j}") for i, j in _overlapping_pairs(b0[still], w.static_boxes)]
    assert not bad, f"{case}: overlaps among static actors {bad[:5]}"
    # Moving actors against everything, at every simulated time and halfway between.
    times = np.union1d(w.times, (w.times[:-1] + w.times[1:]) / 2)
    for t in times:
        b = w.boxes_at(t)
        others = np.concatenate([b, w.static_boxes])
        pairs = [(movers[i], j) for i, j in _overlapping_pairs(b[movers], others) if movers[i] != j]
        assert not pairs, (f"{case} t={t:.3f}: overlapping footprints "
                           f"{[(int(i), w.actors[i].cls, int(j), w.actors[j].cls if j < n else 'static') for i, j in pairs[:5]]}")


@pytest.mark.parametrize("case", CASES, ids=[f"{p}-{s}" for p, s in CASES])
def test_tracks_and_speeds(worlds, case):
    w = worlds[case]
    n, K = w.xy.shape[:2]
    assert w.z.shape == (n, K) and w.speed.shape == (n, K) and w.yaw.shape == (n, K)
    cls = np.array([a.cls for a in w.actors])
    annotate = np.array([a.annotate for a in w.actors])
    # actor 0 is the ego: not annotated, at z = 0 (its ego_pose); everyone else is annotated
    assert not annotate[0] and annotate[1:].all()
    assert (w.z[0] == 0).all()
    assert len({a.id for a in w.actors}) == n and w.actors[0].id == 0
    assert set(cls[annotate]) <= set(CLASSES)
    # speeds
    assert np.isfinite(w.speed).all() and (w.speed >= -1e-9).all()
    for c, vmax in MAX_SPEED.items():
        assert w.speed[cls == c].max() <= vmax + 1e-9, (c, w.speed[cls == c].max())
    assert 0 < w.speed[0].max() <= EGO_MAX_SPEED + 1e-9
    assert w.speed.max() <= EGO_MAX_SPEED + 1e-9          # no actor is faster than 15 m/s (54 km/h)
    # motion is along the heading, never backwards, and no faster than the speed allows; sideways
    # only as far as the heading turns within the step (a chord of an arc runs along the mean heading)
    step = np.diff(w.xy, axis=1)                            # (n, K-1, 2)
    mid = (w.yaw[:, 1:] + w.yaw[:, :-1]) / 2
    u = np.stack([np.cos(mid), np.sin(mid)], -1)
    along = (step * u).sum(-1)
    side = step[..., 0] * u[..., 1] - step[..., 1] * u[..., 0]
    turned = np.abs(np.diff(w.yaw, axis=1))
    assert (along >= -1e-9).all() and (np.abs(side) <= np.linalg.norm(step, axis=-1) * np.sin(turned) + 1e-9).all()
    vmax_cls = np.array([MAX_SPEED.get(c, EGO_MAX_SPEED) for c in cls])
    assert (along / w.dt <= vmax_cls[:, None] + 1e-9).all()
    # parked vehicles and cycles, cones and barriers never move
    fixed = np.array([a.parked or a.cls in ("traffic_cone", "barrier") for a in w.actors])
    assert fixed.any() and np.ptp(w.xy[fixed], axis=1).max() == 0 and w.speed[fixed].max() == 0
    # every actor stays inside the map
    W, H = w.drivable.shape[1] * 0.1, w.drivable.shape[0] * 0.1
    assert w.xy[..., 0].min() > 0 and w.xy[..., 0].max() < W and w.xy[..., 1].min() > 0 and w.xy[..., 1].max() < H


@pytest.mark.parametrize("seed", [0, 1])
def test_urban_density_near_the_ego(worlds, seed):
    w = worlds[("urban", seed)]
    annotate = np.array([a.annotate for a in w.actors])
    counts = []
    for t in keyframe_times(N_SAMPLES):
        b = w.boxes_at(t)
        ego_xy = w.ego_pose(t)[:2, 3]
        counts.append(int((annotate & (np.hypot(*(b[:, :2] - ego_xy).T) <= 50.0)).sum()))
    assert np.mean(counts) >= 20, counts


def test_all_annotated_classes_appear(worlds):
    for case, w in worlds.items():
        present = {a.cls for a in w.actors if a.annotate}
        assert {"car", "pedestrian", "bicycle"} <= present, (case, present)
        assert not w.actors[0].annotate


def _sizes(worlds):
    sizes: dict[str, list] = {}
    riders: dict[str, list] = {}
    for w in worlds.values():
        for a in w.actors:
            if a.annotate:
                sizes.setdefault(a.cls, []).append(a.size)
                riders.setdefault(a.cls, []).append(a.rider)
    return {c: np.array(v) for c, v in sizes.items()}, {c: np.array(v) for c, v in riders.items()}


def test_sizes_near_class_means(worlds):
    """Per class, the median l, w and h are within 10 % of the nuScenes means (pooled over the
    four worlds). Cycle heights are bimodal by construction (a ridden cycle's box holds its
    rider, a parked one's does not), so there the mean height is compared instead: the nuScenes
    class mean mixes both states too."""
    sizes, riders = _sizes(worlds)
    assert {"car", "pedestrian", "bicycle"} <= set(sizes)
    bad = []
    for c, s in sizes.items():
        assert (s > 0).all()
        ratio = np.median(s, axis=0) / np.array(SIZE_MEAN[c])
        if c in ("bicycle", "motorcycle"):
            ratio[2] = s[:, 2].mean() / SIZE_MEAN[c][2]
        if (np.abs(ratio - 1) > 0.10).any():
            bad.append((c, len(s), np.round(ratio, 3).tolist()))
    assert not bad, f"class sizes off the nuScenes means (class, count, l/w/h ratio): {bad}"


def test_ridden_cycles_are_taller_than_parked_ones(worlds):
    sizes, riders = _sizes(worlds)
    for c in ("bicycle", "motorcycle"):
        h, r = sizes[c][:, 2], riders[c]
        assert r.any() and (~r).any(), c
        assert h[r].min() > h[~r].max() - 0.3, c
        assert np.median(h[r]) > np.median(h[~r]) + 0.1, c
    assert np.median(sizes["bicycle"][riders["bicycle"], 2]) > 1.4     # a seated adult on a bicycle


def test_boxes_hold_their_meshes(worlds):
    for w in worlds.values():
        for a in w.actors:
            lo, hi = a.mesh.bounds
            half = np.array(a.size) / 2
            assert (lo >= -half - 1e-6).all() and (hi <= half + 1e-6).all(), (a.cls, a.size, a.mesh.bounds)
            assert len(a.mesh.metadata["reflectivity"]) == len(a.mesh.faces)


def test_every_static_face_has_a_lidarseg_class(worlds):
    """The static world's faces all carry one of the static classes (none is left at noise)."""
    from simgen import lidarseg
    for world in worlds.values():
        labels = world.static_mesh.metadata["lidarseg"]
        assert labels.shape == (len(world.static_mesh.faces),)
        assert set(np.unique(labels).tolist()) <= set(lidarseg.STATIC) and (labels != lidarseg.NOISE).all()
        # Each surface kind is there (lawns or plazas, whichever this world drew).
        assert {lidarseg.ROAD, lidarseg.SIDEWALK, lidarseg.MANMADE, lidarseg.VEGETATION} <= set(np.unique(labels).tolist())
