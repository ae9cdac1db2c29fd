"""What every placing section shares: the plan of an actor before simulation, the rejection
sampler that keeps footprints apart, the actor factory and the lanes and sidewalk lines to place on.

Every actor gets a path (origin, heading, and for some moving vehicles a turn at an intersection)
and a desired speed; static actors get speed 0.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import assets
from . import geometry
from .layout import MAP_PAD, Grid
from .paths import Turn
from .world import Actor

# Mean (l, w, h) per class from the nuScenes anchor configs; the spread is relative.
SIZE_MEAN = {
    "car": (4.61, 1.95, 1.72), "truck": (6.74, 2.46, 2.73), "bus": (11.19, 2.94, 3.47),
    "motorcycle": (2.10, 0.76, 1.44), "bicycle": (1.69, 0.60, 1.27),
    "pedestrian": (0.73, 0.66, 1.76), "traffic_cone": (0.40, 0.40, 1.06), "barrier": (0.49, 2.49, 0.98),
    "construction_vehicle": (6.38, 2.73, 3.13), "trailer": (12.01, 2.87, 3.82),
}
SIZE_SPREAD = {"car": 0.08, "truck": 0.15, "bus": 0.06, "motorcycle": 0.07, "bicycle": 0.06,
               "pedestrian": 0.08, "traffic_cone": 0.12, "barrier": 0.1, "construction_vehicle": 0.08,
               "trailer": 0.06}
EGO_SIZE = (4.08, 1.73, 1.56)   # the nuScenes ego, a Renault Zoe
SPEED = {"car": (6.0, 14.0), "truck": (5.0, 11.0), "bus": (5.0, 10.0), "motorcycle": (6.0, 14.0),
         "bicycle": (3.0, 7.0), "pedestrian": (0.5, 1.8), "construction_vehicle": (2.0, 6.0)}
PAINT = np.array([(200, 200, 205), (30, 30, 35), (150, 20, 25), (20, 50, 130), (120, 125, 130),
                  (235, 235, 230), (40, 90, 60), (200, 160, 40), (90, 60, 40), (60, 140, 190)], float)
CLOTHES = np.array([(40, 40, 60), (150, 30, 30), (30, 90, 150), (200, 200, 190), (60, 60, 60),
                    (180, 140, 60), (20, 110, 70), (110, 60, 120), (230, 120, 40), (90, 80, 70)], float)
SITE_YELLOW = np.array((235, 175, 20), float)
N_SURFACE = 256  # surface samples per actor for the visibility measure
@dataclass
class Plan:
    """An actor before simulation: its path, motion parameters and initial footprint.

    ``xy`` and ``box`` hold on the path's straight start, where every actor begins (a turn, if
    any, lies ahead of ``s0``)."""
    actor: Actor
    origin: np.ndarray          # (2,) path start, global
    heading: float              # path direction at the start (rad); also the actor's initial yaw
    s0: float                   # initial arc length along the path
    length: float               # path length (turn included)
    v_des: float                # desired speed (0 for static actors)
    z_ground: float = 0.0       # ground height under a static actor
    stop: tuple = ()            # (t_start, t_end) of a planned stop, or ()
    priority: int = 0           # lower goes first when two actors wait for each other
    tractor: "Plan | None" = None  # a hitched trailer's tractor: it keeps its distance behind it
    turn: Turn | None = None    # where the path turns onto a crossing road, or None (straight)

    def xy(self, s: float) -> np.ndarray:
        return self.origin + s * np.array([np.cos(self.heading), np.sin(self.heading)])

    def box(self) -> np.ndarray:
        l, w, h = self.actor.size
        return np.array([*self.xy(self.s0), 0.0, l, w, h, self.heading])


@dataclass
class Placer:
    """Rejection sampling against the footprints already placed."""
    static: np.ndarray
    boxes: list = field(default_factory=list)
    plans: list = field(default_factory=list)

    def free(self, box: np.ndarray, margin: float) -> bool:
        others = np.concatenate([self.static, np.array(self.boxes).reshape(-1, 7)])
        if len(others) == 0:
            return True
        near = np.hypot(*(others[:, :2] - box[:2]).T) < (np.hypot(*box[3:5]) + np.hypot(others[:, 3], others[:, 4])) / 2 + 2 * margin
        return not near.any() or not geometry.bev_overlap(box[None], others[near], margin).any()

    def add(self, plan: Plan, margin: float) -> bool:
        box = plan.box()
        if not self.free(box, margin):
            return False
        self.boxes.append(box)
        self.plans.append(plan)
        return True


def draw_size(cls: str, rng: np.random.Generator) -> tuple[float, float, float]:
    mean = np.array(SIZE_MEAN[cls])
    f = np.clip(1.0 + SIZE_SPREAD[cls] * rng.standard_normal(3), 0.75, 1.3)
    if cls == "pedestrian":   # keep a person's proportions: one scale for l and w
        f[1] = f[0]
    return tuple(float(v) for v in mean * f)


def make_actor(idx: int, cls: str, rng: np.random.Generator, parked=False, rider=True) -> Actor:
    """Builds the mesh and surface samples of one actor of class ``cls``."""
    size = draw_size(cls, rng)
    l, w, h = size
    paint = PAINT[rng.integers(len(PAINT))] * rng.uniform(0.85, 1.1)
    if cls == "construction_vehicle":        # site machines wear safety yellow, whatever was drawn
        paint = SITE_YELLOW * (0.8 + 0.3 * paint.mean() / 255)
    paint = tuple(np.clip(paint, 0, 255))
    clothes = (tuple(CLOTHES[rng.integers(len(CLOTHES))]), tuple(CLOTHES[rng.integers(len(CLOTHES))]))
    if cls == "motorcycle":
        # A parked motorcycle's box ends at its windshield; a ridden one's at the rider's head.
        h = rng.uniform(1.25, 1.4) if not rider else max(h, 1.5 + 0.05 * rng.standard_normal())
    elif cls == "bicycle":
        # The box holds the rider: nuScenes annotates a ridden cycle with its rider.
        h = max(h, 1.55 + 0.1 * rng.standard_normal()) if rider else rng.uniform(0.95, 1.1)
    size = (l, w, h)
    mesh = assets.actor_mesh(cls, size, paint, clothes, rider)
    surface = assets.surface_samples(mesh, N_SURFACE, seed=int(rng.integers(2**31)))
    return Actor(idx, cls, size, mesh, surface, parked=parked, rider=rider)


def lane(grid: Grid, rng: np.random.Generator, lateral: float | None = None):
    """A random lane: (origin (2,), heading, path length, lane lateral offset)."""
    cfg = grid.cfg
    W, H = grid.extent
    horizontal = rng.random() < 0.5
    centres = grid.ys if horizontal else grid.xs
    c = centres[rng.integers(len(centres))]
    forward = rng.random() < 0.5
    if lateral is None:
        lateral = (rng.integers(cfg.lanes_per_direction) + 0.5) * cfg.lane_width
    # Right-hand traffic: the lane lies to the right of the direction of travel.
    if horizontal:
        heading = 0.0 if forward else np.pi
        origin = np.array([MAP_PAD, c - lateral]) if forward else np.array([MAP_PAD + W, c + lateral])
        length = W
    else:
        heading = np.pi / 2 if forward else -np.pi / 2
        origin = np.array([c + lateral, MAP_PAD]) if forward else np.array([c - lateral, MAP_PAD + H])
        length = H
    return origin, heading, length, lateral


def sidewalk_line(grid: Grid, rng: np.random.Generator, lateral: float):
    """A line along a sidewalk at ``lateral`` from a road centreline (either side, either way)."""
    origin, heading, length, _ = lane(grid, rng, lateral=lateral)
    return origin, heading, length


@dataclass
class ActorMaker:
    """Makes the actors of a scene, numbered 1, 2, ... in the order they are made (the ego is 0)."""
    rng: np.random.Generator
    last_id: int = 0

    def __call__(self, cls: str, **kw) -> Actor:
        self.last_id += 1
        return make_actor(self.last_id, cls, self.rng, **kw)
