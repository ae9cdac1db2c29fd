"""Coloured mesh parts: the primitives every procedural asset is built from.

Parts are plain vertex/face arrays scaled from unit templates (building a trimesh object per part
is what made worlds slow). Each face carries a colour (for the cameras), a reflectivity 0..1 (for
the lidar intensity) and a lidarseg class index. Faces wind counter-clockwise seen from outside.
"""
from __future__ import annotations

import functools

import numpy as np
import trimesh

SECTIONS = 12  # cylinder/cone facets: enough to read as round, few enough to ray-cast fast

# Lidar reflectivity (0..1) of the materials vehicles share. Number plates are retroreflective
# sheeting, the brightest thing on a vehicle; a headlight's white lens and mirror housing return
# more than a tail light's red lens; glass returns little.
PLATE_REFL = 1.0
HEADLIGHT_REFL = 0.85
TAILLIGHT_REFL = 0.4
GLASS_REFL = 0.08
GLASS = (40, 50, 60)
TIRE = (25, 25, 25)
HEADLIGHT = (250, 250, 235)
TAILLIGHT = (200, 20, 20)
PLATE_FRONT = (235, 235, 230)   # white front plate, yellow rear plate (as in Singapore)
PLATE_REAR = (235, 200, 40)

_TEMPLATES: dict = {}


def _template(kind: str, sections: int = SECTIONS, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Unit primitives (vertices, faces), made once by trimesh."""
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


@functools.lru_cache(maxsize=None)
def _prism_faces(k: int) -> np.ndarray:
    """Faces of a prism over a k-gon: ring 0 (vertices 0..k-1, +y side) and ring 1 (k..2k-1)."""
    i = np.arange(k)
    j = (i + 1) % k
    fan = np.arange(1, k - 1)
    cap_plus = np.stack([np.zeros(k - 2, int), fan + 1, fan], 1)
    cap_minus = np.stack([np.full(k - 2, k), k + fan, k + fan + 1], 1)
    sides = np.concatenate([np.stack([i, j, k + j], 1), np.stack([i, k + j, k + i], 1)])
    faces = np.concatenate([cap_plus, cap_minus, sides])
    faces.flags.writeable = False         # shared by every prism over a k-gon
    return faces


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
        self.add_arrays(v * np.asarray(radius, float) + np.asarray(center, float), f, color, refl, label)

    def prism(self, profile_xz, half_width, color, refl, y=0.0, label: int = 0):
        """A side profile extruded across y: ``profile_xz`` (k, 2) a convex polygon in (x, z),
        either winding; ``half_width`` a scalar or (k,) per vertex (a tapered solid); ``y`` the
        centre of the extrusion."""
        pts = np.asarray(profile_xz, float)
        area2 = np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1])
        hw = np.broadcast_to(np.asarray(half_width, float), len(pts))
        if area2 < 0:        # clockwise in (x, z) is counter-clockwise seen from +y
            pts, hw = pts[::-1], hw[::-1]
        ring = lambda sgn: np.stack([pts[:, 0], y + sgn * hw, pts[:, 1]], 1)  # noqa: E731
        self.add_arrays(np.concatenate([ring(1.0), ring(-1.0)]), _prism_faces(len(pts)), color, refl, label)

    def translate(self, offset):
        self.verts = [v + np.asarray(offset, float) for v in self.verts]

    def fit_within(self, extents):
        """Shrinks the parts towards the origin, axis by axis, until they lie inside the box of
        ``extents`` (l, w, h) centred there; parts already inside are left as they are."""
        reach = np.abs(np.concatenate(self.verts)).max(axis=0)
        scale = np.minimum(1.0, np.asarray(extents, float) / 2 / np.maximum(reach, 1e-9))
        self.verts = [v * scale for v in self.verts]

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


def lamps_and_plates(p: Parts, x_front: float, x_rear: float, half_track: float, z_head: float,
                     z_tail: float, z_plate_front: float, z_plate_rear: float, head=(0.3, 0.13), tail=(0.3, 0.13),
                     plate=(0.52, 0.11)):
    """White headlights and a white plate on the front face (at ``x_front``), red tail lights and a
    yellow plate on the rear face (``x_rear``); lamps at ``y = +-half_track``, ``head`` and ``tail``
    their (width, height). Each part is 4 cm deep and lies inside the faces' x range."""
    for side in (-1.0, 1.0):
        p.box((0.04, *head), (x_front - 0.02, side * half_track, z_head), HEADLIGHT, HEADLIGHT_REFL)
        p.box((0.04, *tail), (x_rear + 0.02, side * half_track, z_tail), TAILLIGHT, TAILLIGHT_REFL)
    p.box((0.04, *plate), (x_front - 0.02, 0.0, z_plate_front), PLATE_FRONT, PLATE_REFL)
    p.box((0.04, *plate), (x_rear + 0.02, 0.0, z_plate_rear), PLATE_REAR, PLATE_REFL)
