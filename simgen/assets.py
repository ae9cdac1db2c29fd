"""Procedural meshes per class, built from coloured parts, in the box frame.

The box frame has its origin at the box centre, x along the length (heading: the front is +x), y
to the left and z up; every mesh lies inside its (l, w, h) box, so lidar points on it count as
inside the box. Each face carries a colour (for the cameras), a reflectivity 0..1 (for the lidar
intensity) and a lidarseg class index (``simgen.lidarseg``; only the static world's are read:
actors are labelled by their class). Vehicles live in :mod:`simgen.vehicles`, people and the
cycles they ride in :mod:`simgen.people`, the parts in :mod:`simgen.parts`; the street furniture,
which has no front, is here.
"""
from __future__ import annotations

import numpy as np
import trimesh

from .parts import SECTIONS, Parts, paint_reflectivity
from .people import bicycle, motorcycle, pedestrian
from .vehicles import bus, car, construction_vehicle, trailer, truck

__all__ = ["Parts", "paint_reflectivity", "car", "truck", "bus", "construction_vehicle", "trailer", "pedestrian",
           "bicycle", "motorcycle", "traffic_cone", "barrier", "actor_mesh", "surface_samples"]


def traffic_cone(l, w, h) -> trimesh.Trimesh:
    """An orange cone with a white band on a square base."""
    p = Parts()
    p.box((l * 0.98, w * 0.98, 0.04), (0, 0, -h / 2 + 0.02), (30, 30, 30), 0.1)
    cone = trimesh.creation.cone(radius=min(l, w) * 0.42, height=h - 0.05, sections=SECTIONS)
    cone.apply_translation((0, 0, -h / 2 + 0.04))
    p.add(cone, (255, 110, 10), 0.95)  # retroreflective sleeve
    return p.build()


def barrier(l, w, h) -> trimesh.Trimesh:
    """A jersey-style barrier: a wall across the box's width (w is the long side) with stripes."""
    p = Parts()
    p.box((l * 0.95, w * 0.98, h * 0.6), (0, 0, -h / 2 + 0.3 * h), (200, 200, 195), 0.5)
    p.box((l * 0.55, w * 0.98, h * 0.38), (0, 0, -h / 2 + 0.79 * h), (220, 30, 30), 0.8)
    return p.build()


def actor_mesh(cls: str, size, paint, clothes, rider: bool) -> trimesh.Trimesh:
    """The mesh of an actor of class ``cls`` in its (l, w, h) ``size`` box; ``paint`` colours
    vehicles and cycles, ``clothes`` (top, bottom) people and riders (``rider``: cycles only)."""
    l, w, h = size
    if cls == "car":
        return car(l, w, h, paint)
    if cls == "truck":
        return truck(l, w, h, paint)
    if cls == "bus":
        return bus(l, w, h, paint)
    if cls == "construction_vehicle":
        return construction_vehicle(l, w, h, paint)
    if cls == "trailer":
        return trailer(l, w, h, paint)
    if cls == "motorcycle":
        return motorcycle(l, w, h, paint, clothes if rider else None)
    if cls == "bicycle":
        return bicycle(l, w, h, paint, clothes if rider else None)
    if cls == "pedestrian":
        return pedestrian(l, w, h, *clothes).build()
    if cls == "traffic_cone":
        return traffic_cone(l, w, h)
    if cls == "barrier":
        return barrier(l, w, h)
    raise ValueError(f"no mesh for class {cls!r}")


def surface_samples(mesh: trimesh.Trimesh, count: int, seed: int) -> np.ndarray:
    """(count, 6) points and outward face normals on the mesh surface, area-weighted."""
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.concatenate([pts, mesh.face_normals[face]], axis=1)
