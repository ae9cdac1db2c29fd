"""Procedural meshes per class, built from coloured parts, in the box frame.

The box frame has its origin at the box centre, x along the length (heading), y to the left and
z up; every mesh lies inside its (l, w, h) box, so lidar points on it count as inside the box.
Each face carries a colour (for the cameras), a reflectivity 0..1 (for the lidar intensity) and
a lidarseg class index (``simgen.lidarseg``; only the static world's are read: actors are
labelled by their class).
"""
from __future__ import annotations

import numpy as np
import trimesh

SECTIONS = 12  # cylinder/cone facets: enough to read as round, few enough to ray-cast fast


_TEMPLATES: dict = {}


def _template(kind: str, sections: int = SECTIONS, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Unit primitives (vertices, faces), made once by trimesh: building a trimesh object per
    part is what made worlds slow, so parts are plain arrays scaled from these."""
    key = (kind, sections, subdivisions)
    if key not in _TEMPLATES:
        if kind == "box":
            m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
        elif kind == "cylinder":      # radius 1, from z = -0.5 to 0.5
            m = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=sections)
        else:
            m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
        _TEMPLATES[key] = (np.array(m.vertices), np.array(m.faces))
    return _TEMPLATES[key]


def _rotation_z_to(direction: np.ndarray) -> np.ndarray:
    """A rotation taking +z to the unit vector along ``direction`` (columns x, y, z)."""
    z = direction / np.linalg.norm(direction)
    # x = normalise(helper x z), written out: np.cross is slow on single vectors.
    if abs(z[0]) < 0.9:      # helper (1, 0, 0)
        x = np.array([0.0, -z[2], z[1]])
    else:                    # helper (0, 1, 0)
        x = np.array([z[2], 0.0, -z[0]])
    x /= np.sqrt(x @ x)
    y = np.array([z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]])
    return np.stack([x, y, z], 1)


class Parts:
    """Accumulates coloured parts (plain vertex/face arrays) and concatenates them into one mesh."""

    def __init__(self):
        self.verts, self.faces, self.colors, self.refl, self.labels = [], [], [], [], []

    def add_arrays(self, verts: np.ndarray, faces: np.ndarray, color, reflectivity: float, label: int = 0):
        self.verts.append(np.asarray(verts, np.float64))
        self.faces.append(np.asarray(faces, np.int64))
        self.colors.append(np.broadcast_to(np.append(np.asarray(color, np.uint8)[:3], 255), (len(faces), 4)))
        self.refl.append(np.full(len(faces), reflectivity, np.float32))
        self.labels.append(np.full(len(faces), label, np.uint8))

    def add(self, mesh: trimesh.Trimesh, color, reflectivity: float, label: int = 0):
        self.add_arrays(mesh.vertices, mesh.faces, color, reflectivity, label)

    def box(self, extents, center, color, refl, yaw=0.0, label: int = 0):
        v, f = _template("box")
        v = v * np.asarray(extents, float)
        if yaw:
            c, s = np.cos(yaw), np.sin(yaw)
            v = v @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])
        self.add_arrays(v + np.asarray(center, float), f, color, refl, label)

    def cylinder(self, p0, p1, radius, color, refl, sections=SECTIONS, label: int = 0):
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        v, f = _template("cylinder", sections)
        v = v * np.array([radius, radius, np.linalg.norm(p1 - p0)])
        self.add_arrays(v @ _rotation_z_to(p1 - p0).T + (p0 + p1) / 2, f, color, refl, label)

    def sphere(self, center, radius, color, refl, subdivisions=1, label: int = 0):
        v, f = _template("sphere", subdivisions=subdivisions)
        self.add_arrays(v * radius + np.asarray(center, float), f, color, refl, label)

    def translate(self, offset):
        self.verts = [v + np.asarray(offset, float) for v in self.verts]

    def extend(self, other: "Parts"):
        self.verts += other.verts
        self.faces += other.faces
        self.colors += other.colors
        self.refl += other.refl
        self.labels += other.labels

    def build(self) -> trimesh.Trimesh:
        offsets = np.cumsum([0] + [len(v) for v in self.verts[:-1]])
        faces = np.concatenate([f + o for f, o in zip(self.faces, offsets)])
        mesh = trimesh.Trimesh(np.concatenate(self.verts), faces, process=False)
        mesh.visual.face_colors = np.concatenate(self.colors)
        mesh.metadata["reflectivity"] = np.concatenate(self.refl)
        mesh.metadata["lidarseg"] = np.concatenate(self.labels)
        return mesh


def paint_reflectivity(color) -> float:
    """Lidar reflectivity of car paint from its colour: bright paint returns more."""
    return float(0.15 + 0.6 * np.mean(color) / 255.0)


def _wheels(p: Parts, l, w, h, r, axle_x, tire_w=0.25):
    for x in axle_x:
        for side in (-1, 1):
            y = side * (w / 2 - tire_w / 2 - 0.01)
            p.cylinder((x, y - tire_w / 2, -h / 2 + r), (x, y + tire_w / 2, -h / 2 + r), r,
                       (25, 25, 25), 0.05)


def car(l, w, h, color) -> trimesh.Trimesh:
    """Body, cabin with dark glass, four wheels, head and tail lights."""
    p = Parts()
    r = min(0.34, 0.22 * h)
    body_lo, body_hi = -h / 2 + 0.55 * r, -h / 2 + 0.58 * h
    p.box((l * 0.98, w * 0.98, body_hi - body_lo), (0, 0, (body_lo + body_hi) / 2), color,
          paint_reflectivity(color))
    cab_l = 0.52 * l
    p.box((cab_l, w * 0.84, h / 2 - body_hi - 0.01), (-0.06 * l, 0, (body_hi + h / 2) / 2 - 0.005),
          (40, 50, 60), 0.08)
    p.box((cab_l * 0.7, w * 0.86, 0.06), (-0.06 * l, 0, h / 2 - 0.04), color, paint_reflectivity(color))
    for side in (-1, 1):
        p.box((0.05, 0.25, 0.12), (l / 2 * 0.98 - 0.02, side * (w / 2 - 0.3), body_hi - 0.15),
              (250, 250, 220), 0.9)
        p.box((0.05, 0.25, 0.12), (-l / 2 * 0.98 + 0.02, side * (w / 2 - 0.3), body_hi - 0.15),
              (200, 20, 20), 0.9)
    _wheels(p, l, w, h, r, (l / 2 - 0.85, -l / 2 + 0.85))
    return p.build()


def truck(l, w, h, color) -> trimesh.Trimesh:
    """A cab in front and a tall cargo box behind, on six wheels."""
    p = Parts()
    r = 0.45
    cab_l = min(2.2, 0.3 * l)
    floor = -h / 2 + 2 * r * 0.75
    p.box((cab_l, w * 0.96, 0.7 * (h / 2 - floor)), (l / 2 - cab_l / 2, 0, floor + 0.35 * (h / 2 - floor)),
          color, paint_reflectivity(color))
    p.box((0.05, w * 0.8, 0.3 * (h / 2 - floor) - 0.02), (l / 2 - 0.03, 0, floor + 0.83 * (h / 2 - floor)),
          (40, 50, 60), 0.08)
    p.box((cab_l - 0.1, w * 0.96, 0.3 * (h / 2 - floor) - 0.02),
          (l / 2 - cab_l / 2 - 0.05, 0, floor + 0.83 * (h / 2 - floor)), color, paint_reflectivity(color))
    box_l = l - cab_l - 0.2
    p.box((box_l, w, h / 2 - floor), (-l / 2 + box_l / 2, 0, (floor + h / 2) / 2), (225, 225, 215), 0.6)
    _wheels(p, l, w, h, r, (l / 2 - 1.0, -l / 2 + 1.2, -l / 2 + 2.4), tire_w=0.35)
    return p.build()


def bus(l, w, h, color) -> trimesh.Trimesh:
    """A long box with a window band, on four wheels."""
    p = Parts()
    r = 0.5
    floor = -h / 2 + 0.7 * r
    p.box((l, w, 0.45 * (h / 2 - floor)), (0, 0, floor + 0.225 * (h / 2 - floor)), color,
          paint_reflectivity(color))
    p.box((l * 0.995, w * 0.99, 0.35 * (h / 2 - floor)), (0, 0, floor + 0.625 * (h / 2 - floor)),
          (35, 45, 55), 0.08)
    p.box((l, w, 0.2 * (h / 2 - floor)), (0, 0, floor + 0.9 * (h / 2 - floor)), color,
          paint_reflectivity(color))
    _wheels(p, l, w, h, r, (l / 2 - 2.2, -l / 2 + 2.6), tire_w=0.35)
    return p.build()


def pedestrian(l, w, h, shirt, trousers, skin=(200, 160, 130), seated=False) -> Parts:
    """Legs, torso, arms and head scaled to height ``h`` (returns Parts, so riders can be seated)."""
    p = Parts()
    bottom = -h / 2
    head_r = 0.11 * h / 1.75
    leg_h = 0.0 if seated else 0.47 * h
    torso_h = 0.32 * h if not seated else 0.5 * (h - 2 * head_r)
    hip = bottom + leg_h
    tw = min(w * 0.62, 0.5)
    stride = 0.0 if seated else 0.18 * l   # one leg forward, one back, arms swinging opposite
    if not seated:
        for side in (-1, 1):
            p.box((0.16, 0.14, leg_h), (side * stride, side * tw * 0.25, bottom + leg_h / 2), trousers, 0.2)
    p.box((min(l * 0.45, 0.3), tw, torso_h), (0, 0, hip + torso_h / 2), shirt, 0.35)
    arm_h = 0.85 * torso_h
    for side in (-1, 1):
        p.box((0.1, 0.08, arm_h), (-side * stride * 0.8, side * (tw / 2 + 0.045), hip + torso_h - arm_h / 2),
              shirt, 0.35)
    p.sphere((0, 0, hip + torso_h + head_r + 0.01), head_r, skin, 0.3)
    return p


def _wheel_ring(p: Parts, x, z, radius, color=(20, 20, 20)):
    ring = trimesh.creation.torus(major_radius=radius - 0.025, minor_radius=0.025,
                                  major_sections=16, minor_sections=6)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    ring.apply_translation((x, 0, z))
    p.add(ring, color, 0.1)


def bicycle(l, w, h, color, rider_colors=None) -> trimesh.Trimesh:
    """Two wheels and a frame; with a seated rider when ``rider_colors`` is given."""
    p = Parts()
    r = min(0.34, l / 4.6)
    bottom = -h / 2
    ax = l / 2 - r - 0.02
    for x in (ax, -ax):
        _wheel_ring(p, x, bottom + r, r)
    seat = (-0.25 * l, 0, bottom + 2.2 * r)
    bar = (0.25 * l, 0, bottom + 2.4 * r)
    crank = (0.0, 0, bottom + r)
    for a, b in ((seat, crank), (bar, crank), (seat, bar), ((-ax, 0, bottom + r), crank),
                 ((-ax, 0, bottom + r), seat), ((ax, 0, bottom + r), bar)):
        p.cylinder(a, b, 0.025, color, 0.5, sections=6)
    p.box((0.06, min(w, 0.5), 0.04), (bar[0], 0, bar[2] + 0.06), (30, 30, 30), 0.2)
    if rider_colors is not None:
        top = h / 2
        body_h = top - seat[2]
        rider = pedestrian(0.3, min(w, 0.5), body_h, *rider_colors, seated=True)
        rider.translate((-0.1 * l, 0, seat[2] + body_h / 2))
        p.extend(rider)
        for side in (-1, 1):  # legs down to the pedals
            p.cylinder((-0.1 * l, side * 0.1, seat[2] + 0.02), (0.05 * l, side * 0.1, bottom + r + 0.1),
                       0.06, rider_colors[1], 0.2, sections=6)
    return p.build()


def motorcycle(l, w, h, color, rider_colors=None) -> trimesh.Trimesh:
    """Two thick wheels, an engine block, tank and seat; an optional seated rider."""
    p = Parts()
    r = 0.3
    bottom = -h / 2
    ax = l / 2 - r - 0.02
    for x in (ax, -ax):
        p.cylinder((x, -0.07, bottom + r), (x, 0.07, bottom + r), r, (20, 20, 20), 0.05)
    p.box((0.9, min(w, 0.4), 0.35), (0, 0, bottom + r + 0.15), (60, 60, 60), 0.4)
    p.box((0.7, min(w, 0.35), 0.2), (0.1, 0, bottom + r + 0.42), color, paint_reflectivity(color))
    seat_z = bottom + r + 0.55
    p.cylinder((0.3, 0, bottom + r + 0.45), (0.42, 0, bottom + 0.98), 0.03, (40, 40, 40), 0.4, sections=6)
    p.box((0.05, min(w * 0.95, 0.75), 0.04), (0.42, 0, bottom + 0.98), (40, 40, 40), 0.4)
    top = h / 2 - 0.02 if rider_colors is None else bottom + 1.25
    p.box((0.03, 0.4, top - (bottom + 0.95)), (0.5, 0, (top + bottom + 0.95) / 2), (150, 170, 190), 0.1)  # windshield
    if rider_colors is not None and h / 2 - seat_z > 0.4:
        body_h = h / 2 - seat_z
        rider = pedestrian(0.3, min(w, 0.6), body_h, *rider_colors, seated=True)
        rider.translate((-0.15, 0, seat_z + body_h / 2))
        p.extend(rider)
    return p.build()


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


def surface_samples(mesh: trimesh.Trimesh, count: int, seed: int) -> np.ndarray:
    """(count, 6) points and outward face normals on the mesh surface, area-weighted."""
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.concatenate([pts, mesh.face_normals[face]], axis=1)
