"""Procedural people and the two-wheelers they ride, in the box frame, each with a front and a back.

The box frame has its origin at the box centre, x along the length (the way the person or the
cycle faces), y to the left and z up; every part lies inside the (l, w, h) box. A walker is caught
mid-stride: the left leg forward with its knee bent, the right leg trailing on its toes, the arms
swinging against the legs, the body leaning forward, feet pointing ahead, a face and a nose in
front and hair behind, so that no half-turn maps the figure onto itself.
"""
from __future__ import annotations

import numpy as np
import trimesh

from .parts import (HEADLIGHT, HEADLIGHT_REFL, PLATE_REAR, PLATE_REFL, TAILLIGHT, TAILLIGHT_REFL, TIRE,
                    Parts, paint_reflectivity)

SKIN = (200, 160, 130)
HAIR = (45, 35, 25)
SHOES = (35, 30, 30)
CLOTH_REFL, SKIN_REFL = 0.35, 0.3


def _limb(p: Parts, joints, radius, color, refl):
    """A chain of six-sided cylinders through ``joints`` (k, 3)."""
    joints = np.asarray(joints, float)
    for a, b in zip(joints[:-1], joints[1:]):
        p.cylinder(a, b, radius, color, refl, sections=6)


def _arm(p, shoulder, upper, fore, swing, bend, radius, shirt, skin):
    """An arm hanging from ``shoulder`` (3,), swung forward by ``swing`` (rad, negative = back) with
    the forearm bent a further ``bend`` forward; a hand at the end."""
    d_up = np.array([np.sin(swing), 0.0, -np.cos(swing)])
    d_fore = np.array([np.sin(swing + bend), 0.0, -np.cos(swing + bend)])
    elbow = shoulder + upper * d_up
    hand = elbow + fore * d_fore
    _limb(p, [shoulder, elbow, hand], radius, shirt, CLOTH_REFL)
    p.sphere(hand + 0.02 * d_fore, radius * 1.05, skin, SKIN_REFL, subdivisions=0)


def _head(p, centre, r, skin):
    """A head facing +x: the face in skin, hair over the back and the crown, a nose in front."""
    centre = np.asarray(centre, float)
    p.sphere(centre, r, skin, SKIN_REFL)
    p.sphere(centre + (-0.25 * r, 0, 0.12 * r), 0.93 * r, HAIR, 0.15)
    p.box((0.25 * r, 0.22 * r, 0.3 * r), centre + (0.95 * r, 0, -0.1 * r), skin, SKIN_REFL)


def _torso(p, hip, shoulder, depth, hip_hw, shoulder_hw, color):
    """A torso from ``hip`` (x, z) to ``shoulder`` (x, z), with a chest in front and a flat back."""
    (xh, zh), (xs, zs) = hip, shoulder
    chest = (xs + 0.6 * depth, zh + 0.75 * (zs - zh))
    p.prism([(xh - 0.5 * depth, zh), (xh + 0.45 * depth, zh), chest, (xs + 0.3 * depth, zs), (xs - 0.5 * depth, zs)],
            [hip_hw, hip_hw, shoulder_hw, shoulder_hw, shoulder_hw], color, CLOTH_REFL)


def _foot(p, ankle, bottom, y, lifted):
    """A shoe pointing +x from ``ankle`` x: flat, or (``lifted``) standing on its toes."""
    a = ankle
    heel = 0.1 if lifted else 0.0
    p.prism([(a - 0.06, bottom + heel), (a + 0.17, bottom), (a + 0.18, bottom + 0.05),
             (a + 0.02, bottom + 0.09 + heel), (a - 0.06, bottom + 0.07 + heel)], 0.045, SHOES, 0.15, y=y)


def pedestrian(l, w, h, shirt, trousers, skin=SKIN) -> Parts:
    """A walker mid-stride scaled to the box (returns Parts, so callers can add to it)."""
    p = Parts()
    bottom = -h / 2
    z_hip, z_knee, z_ankle, z_sh = bottom + 0.52 * h, bottom + 0.28 * h, bottom + 0.06 * h, bottom + 0.82 * h
    head_r = 0.065 * h
    limb_r, leg_y = 0.065 * min(h / 1.75, w / 0.66), 0.09 * w / 0.66
    x_hip, x_sh = -0.04 * l, 0.04 * l
    front_ankle, back_ankle = l / 2 - 0.19, -l / 2 + 0.07
    _limb(p, [(x_hip, leg_y, z_hip), (x_hip + 0.2 * l, leg_y, z_knee), (front_ankle, leg_y, z_ankle)],
          limb_r, trousers, 0.2)
    _limb(p, [(x_hip, -leg_y, z_hip), (x_hip - 0.22 * l, -leg_y, z_knee + 0.02),
              (back_ankle, -leg_y, z_ankle + 0.08)], limb_r, trousers, 0.2)
    _foot(p, front_ankle, bottom, leg_y, lifted=False)
    _foot(p, back_ankle, bottom, -leg_y, lifted=True)
    tw = min(0.62 * w, 0.45)
    _torso(p, (x_hip, z_hip - 0.02), (x_sh, z_sh), min(0.34 * l, 0.25), 0.38 * tw, tw / 2, shirt)
    arm_r = 0.8 * limb_r
    upper, fore = 0.17 * h, 0.14 * h
    # Arms swing against the legs: the right arm forward with a bent elbow, the left one back.
    _arm(p, np.array([x_sh, -(tw / 2 + arm_r), z_sh - 0.03]), upper, fore, 0.3, 0.5, arm_r, shirt, skin)
    _arm(p, np.array([x_sh, tw / 2 + arm_r, z_sh - 0.03]), upper, fore, -0.35, 0.15, arm_r, shirt, skin)
    _head(p, (x_sh + 0.04, 0.0, h / 2 - 1.05 * head_r - 0.005), head_r, skin)
    p.fit_within((l, w, h))       # limbs scale with the height, the box's depth and width need not
    return p


def seated_rider(p: Parts, seat, top, width, hands, shirt, skin=SKIN):
    """A rider's torso, arms and head from the ``seat`` (x, z) up to ``top``, leaning towards
    the ``hands`` (x, z) on the handlebar; the legs belong to the cycle."""
    (xs, zs), (xh, zh) = seat, hands
    body_h = top - zs
    head_r = min(0.11, 0.14 * body_h)
    z_sh = top - 2.3 * head_r
    x_sh = xs + 0.35 * (z_sh - zs)                     # leaning about 20 degrees forward
    tw = min(0.8 * width, 0.42, width - 0.17)        # shoulders and arms within ``width``
    _torso(p, (xs, zs), (x_sh, z_sh), 0.22, 0.38 * tw, tw / 2, shirt)
    for side in (-1, 1):
        shoulder = np.array([x_sh, side * (tw / 2 + 0.04), z_sh - 0.03])
        hand = np.array([xh, side * min(0.25, width / 2 - 0.05), zh])
        elbow = (shoulder + hand) / 2 + np.array([-0.02, 0.0, -0.06])
        _limb(p, [shoulder, elbow, hand], 0.045, shirt, CLOTH_REFL)
    _head(p, (x_sh + 0.06, 0.0, top - head_r - 0.01), head_r, skin)


def _wheel_ring(p: Parts, x, z, radius, color=(20, 20, 20)):
    ring = trimesh.creation.torus(major_radius=radius - 0.025, minor_radius=0.025,
                                  major_sections=16, minor_sections=6)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    ring.apply_translation((x, 0, z))
    p.add(ring, color, 0.1)


def bicycle(l, w, h, color, rider_colors=None) -> trimesh.Trimesh:
    """Two wheels, a frame, a white reflector in front and a red one behind; with a seated rider
    when ``rider_colors`` is given."""
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
    p.box((0.03, 0.08, 0.06), (bar[0] + 0.05, 0, bar[2] - 0.05), HEADLIGHT, HEADLIGHT_REFL)
    p.box((0.03, 0.08, 0.06), (seat[0] - 0.12, 0, seat[2] - 0.12), TAILLIGHT, TAILLIGHT_REFL)
    if rider_colors is not None:
        shirt, trousers = rider_colors
        hip = (-0.1 * l, seat[2] + 0.05)
        seated_rider(p, hip, h / 2, min(w, 0.5), (bar[0], bar[2] + 0.08), shirt)
        for side in (-1, 1):  # legs down to the pedals, one up, one down
            knee = (0.12 * l, side * 0.11, seat[2] + 0.05 - (0.05 if side > 0 else 0.2))
            foot = (0.05 * l * side, side * 0.11, bottom + r + (0.2 if side > 0 else -0.15))
            _limb(p, [(hip[0], side * 0.1, hip[1]), knee, foot], 0.06, trousers, 0.2)
    return p.build()


def motorcycle(l, w, h, color, rider_colors=None) -> trimesh.Trimesh:
    """Two thick wheels, a raked fork, an engine block, tank and seat, a fairing with a headlight
    and a windshield in front, a tail light and plate behind; an optional seated rider."""
    p = Parts()
    r = 0.3
    bottom = -h / 2
    ax = l / 2 - r - 0.02
    for x in (ax, -ax):
        p.cylinder((x, -0.07, bottom + r), (x, 0.07, bottom + r), r, TIRE, 0.05)
    p.box((0.9, min(w, 0.4), 0.35), (-0.05, 0, bottom + r + 0.15), (60, 60, 60), 0.4)
    p.box((0.7, min(w, 0.35), 0.2), (0.1, 0, bottom + r + 0.42), color, paint_reflectivity(color))
    seat_z = bottom + r + 0.55
    p.prism([(-0.25, seat_z - 0.08), (-l / 2 + 0.25, seat_z), (-l / 2 + 0.2, seat_z + 0.06), (-0.25, seat_z + 0.02)],
            0.14, (30, 30, 30), 0.2)                                                  # seat and tail
    for side in (-1, 1):                                                              # the raked fork
        p.cylinder((ax, side * 0.09, bottom + r), (0.42, side * 0.09, bottom + 0.98), 0.03, (150, 150, 150), 0.5,
                   sections=6)
    p.box((0.05, min(w * 0.95, 0.75), 0.04), (0.42, 0, bottom + 0.98), (40, 40, 40), 0.4)
    p.prism([(0.3, bottom + r + 0.2), (0.45, bottom + r + 0.3), (0.5, bottom + 0.95), (0.32, bottom + 0.95)],
            0.17, color, paint_reflectivity(color))                                   # front fairing
    p.box((0.05, 0.16, 0.14), (0.5, 0, bottom + 0.86), HEADLIGHT, HEADLIGHT_REFL)
    p.box((0.04, 0.14, 0.06), (-l / 2 + 0.22, 0, seat_z - 0.02), TAILLIGHT, TAILLIGHT_REFL)
    p.box((0.03, 0.2, 0.12), (-l / 2 + 0.25, 0, seat_z - 0.13), PLATE_REAR, PLATE_REFL)
    top = h / 2 - 0.02 if rider_colors is None else bottom + 1.25
    p.prism([(0.48, bottom + 0.95), (0.53, bottom + 0.95), (0.46, top), (0.42, top)], 0.2,
            (150, 170, 190), 0.1)                                                      # windshield
    if rider_colors is not None and h / 2 - seat_z > 0.4:
        shirt, trousers = rider_colors
        seated_rider(p, (-0.15, seat_z), h / 2, min(w, 0.6), (0.4, bottom + 1.0), shirt)
        for side in (-1, 1):
            _limb(p, [(-0.15, side * 0.12, seat_z + 0.05), (0.2, side * 0.2, seat_z + 0.02),
                      (0.05, side * 0.2, bottom + r + 0.05)], 0.06, trousers, 0.2)
    return p.build()
