"""Per-point semantic labels in the nuScenes-lidarseg format.

nuScenes-lidarseg gives every point of a key-frame LIDAR_TOP sweep a class index (uint8, one
per point, in ``lidarseg/<version>/<sample_data token>_lidarseg.bin``), and its ``category``
table carries each class's ``index``. ``NAMES`` is that class list in index order; the devkit's
colormap (``nuscenes.utils.color_map.get_colormap``) has the same order, and the devkit's
statistics assume indices 0..31 without gaps, so ``category.json`` lists all 32 even though the
generator makes only some of them.

Actors are labelled by their class (a ridden bicycle's rider is part of the bicycle, as its box
is); the static world by the surface each face belongs to (``STATIC``).
"""
from __future__ import annotations

import numpy as np

from .world import CATEGORY, World

NAMES = (
    "noise", "animal", "human.pedestrian.adult", "human.pedestrian.child",
    "human.pedestrian.construction_worker", "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer", "human.pedestrian.stroller", "human.pedestrian.wheelchair",
    "movable_object.barrier", "movable_object.debris", "movable_object.pushable_pullable",
    "movable_object.trafficcone", "static_object.bicycle_rack", "vehicle.bicycle", "vehicle.bus.bendy",
    "vehicle.bus.rigid", "vehicle.car", "vehicle.construction", "vehicle.emergency.ambulance",
    "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer", "vehicle.truck",
    "flat.driveable_surface", "flat.other", "flat.sidewalk", "flat.terrain", "static.manmade",
    "static.other", "static.vegetation", "vehicle.ego",
)
INDEX = {name: i for i, name in enumerate(NAMES)}

NOISE = INDEX["noise"]                       # fog returns: no surface behind them
ROAD = INDEX["flat.driveable_surface"]       # asphalt, lane markings, crosswalks
SIDEWALK = INDEX["flat.sidewalk"]
TERRAIN = INDEX["flat.terrain"]              # lawns inside the blocks
PLAZA = INDEX["flat.other"]                  # paved lots inside the blocks
MANMADE = INDEX["static.manmade"]            # buildings, poles, bins
VEGETATION = INDEX["static.vegetation"]      # trees, hedges
CAR = INDEX["vehicle.car"]                   # the occluders' parked vans (not annotated)
STATIC = (ROAD, SIDEWALK, TERRAIN, PLAZA, MANMADE, VEGETATION, CAR)


def class_of_id(world: World) -> np.ndarray:
    """(1 + largest actor id,) uint8: each actor id's class (by the actor's category); index 0,
    the static world's id, holds 0 and is never read by :func:`classes`."""
    table = np.zeros(1 + max((a.id for a in world.actors), default=0), np.uint8)
    for a in world.actors:
        table[a.id] = INDEX[CATEGORY[a.cls]]
    return table


def classes(ids: np.ndarray, static_class: np.ndarray, id_class: np.ndarray) -> np.ndarray:
    """The class of each hit: its actor's class where it hit an actor (``ids`` > 0), else the
    class of the static surface it hit (``static_class``, same shape). The lidar's points and the
    cameras' pixels are labelled by this one function, so the two agree on every surface.

    ids : (...) int actor ids, 0 = static world.  id_class : :func:`class_of_id`.
    Returns (...) uint8.
    """
    return np.where(ids > 0, np.take(id_class, ids), static_class).astype(np.uint8)
