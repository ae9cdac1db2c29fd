"""Procedural cars, trucks, buses, construction vehicles and trailers in the box frame, each with a front and a back.

The box frame has its origin at the box centre, x along the length (the front is +x), y to the
left and z up; every part lies inside the (l, w, h) box. What tells the front from the back, to
the cameras and to the lidar: a low hood and a raked windscreen against a steeper rear window or a
tall cargo box, axles placed as real overhangs place them, white headlights against red tail
lights of a different reflectivity, and retroreflective number plates at both ends.
"""
from __future__ import annotations

import numpy as np
import trimesh

from .parts import (GLASS, GLASS_REFL, HEADLIGHT, HEADLIGHT_REFL, PLATE_REAR, PLATE_REFL, TAILLIGHT, TAILLIGHT_REFL,
                    TIRE, Parts, lamps_and_plates, paint_reflectivity)


def _wheels(p: Parts, w, h, r, axle_x, tire_w=0.25):
    for x in axle_x:
        for side in (-1, 1):
            y = side * (w / 2 - tire_w / 2 - 0.01)
            p.cylinder((x, y - tire_w / 2, -h / 2 + r), (x, y + tire_w / 2, -h / 2 + r), r, TIRE, 0.05)


def car(l, w, h, color) -> trimesh.Trimesh:
    """A hatchback: a body whose hood slopes down to the nose, a glasshouse with a raked
    windscreen and a steep rear window, mirrors, lamps, plates and four wheels."""
    p = Parts()
    paint, refl = color, paint_reflectivity(color)
    bottom, top = -h / 2, h / 2
    r = min(0.34, 0.22 * h)
    hb = 0.485 * w                                   # body half-width; the mirrors reach the box
    sill, nose_top, cowl, belt = bottom + 0.5 * r, bottom + 0.42 * h, bottom + 0.54 * h, bottom + 0.57 * h
    x_cowl = l / 2 - 0.25 * l                        # where the hood meets the windscreen
    xn, xt = l / 2 - 0.02, -l / 2 + 0.02             # the body's ends; lamps and plates stand out
    body = [(xt, sill + 0.12), (xt + 0.1, sill), (xn - 0.2, sill), (xn, sill + 0.15),
            (xn, nose_top - 0.05), (xn - 0.1, nose_top), (x_cowl, cowl), (xt, belt)]
    taper = np.array([1.0, 1.0, 1.0, 0.88, 0.9, 0.92, 1.0, 1.0])   # a rounded nose, seen from above
    p.prism(body, hb * taper, paint, refl)
    roof = top - 0.04
    x_ws_top = x_cowl - (roof - cowl) / np.tan(np.radians(32))   # a windscreen raked 32 degrees
    x_rear_top = -l / 2 + (roof - belt) / np.tan(np.radians(65))  # a rear window at 65 degrees
    glass = [(x_cowl, cowl - 0.01), (x_ws_top, roof), (x_rear_top, roof), (xt + 0.02, belt - 0.01)]
    p.prism(glass, [0.95 * hb, 0.8 * hb, 0.8 * hb, 0.95 * hb], GLASS, GLASS_REFL)
    p.prism([(x_ws_top + 0.05, roof - 0.01), (x_ws_top, top), (x_rear_top + 0.02, top), (x_rear_top, roof - 0.01)],
            0.81 * hb, paint, refl)
    for side in (-1, 1):
        p.box((0.12, w / 2 - 0.9 * hb, 0.12), (x_cowl - 0.12, side * (w / 2 + 0.9 * hb) / 2, belt + 0.1), paint, refl)
    p.box((0.04, 1.5 * hb, 0.2), (xn - 0.01, 0.0, sill + 0.24), (30, 30, 30), 0.1)        # air intake
    p.box((0.04, 0.9 * hb, 0.1), (xn - 0.01, 0.0, nose_top - 0.13), (30, 30, 30), 0.1)     # grille
    lamps_and_plates(p, l / 2, -l / 2, hb - 0.3, z_head=nose_top - 0.13, z_tail=belt - 0.14,
                     z_plate_front=sill + 0.2, z_plate_rear=sill + 0.42, head=(0.4, 0.15), tail=(0.3, 0.22))
    _wheels(p, w, h, r, (l / 2 - 0.19 * l, -l / 2 + 0.23 * l))
    return p.build()


def truck(l, w, h, color) -> trimesh.Trimesh:
    """A box truck: a cab lower and narrower than the cargo box behind it, on a chassis with a
    front axle under the cab and two rear axles."""
    p = Parts()
    paint, refl = color, paint_reflectivity(color)
    bottom, top = -h / 2, h / 2
    r = 0.45
    cab_l = min(2.2, 0.3 * l)
    cab_hw, cab_lo, cab_top = 0.45 * w, bottom + 0.4, bottom + 0.8 * h
    x_back = l / 2 - cab_l
    z_ws = bottom + 0.5 * h                                        # windscreen's lower edge
    xn = l / 2 - 0.02                                              # the cab's front; lamps stand out
    p.prism([(x_back, cab_lo), (xn, cab_lo), (xn, z_ws), (x_back, z_ws)], cab_hw, paint, refl)
    p.prism([(x_back, z_ws), (xn - 0.01, z_ws), (xn - 0.35, cab_top - 0.04), (x_back, cab_top - 0.04)],
            0.98 * cab_hw, GLASS, GLASS_REFL)
    p.prism([(x_back, z_ws), (x_back + 0.7, z_ws), (x_back + 0.7, cab_top), (x_back, cab_top)], cab_hw, paint, refl)
    p.prism([(x_back + 0.7, cab_top - 0.05), (l / 2 - 0.33, cab_top - 0.05), (l / 2 - 0.37, cab_top),
             (x_back + 0.7, cab_top)], cab_hw, paint, refl)
    floor = bottom + 2 * r + 0.15
    box_front = x_back - 0.12
    p.box((box_front + l / 2, w, top - floor), ((box_front - l / 2) / 2, 0, (floor + top) / 2), (225, 225, 215), 0.6)
    p.box((l - 0.3, 0.5 * w, 0.22), (-0.15, 0, floor - 0.11), (30, 30, 30), 0.1)           # chassis rails
    p.box((0.1, 0.9 * w, 0.15), (-l / 2 + 0.05, 0, bottom + 0.5), (40, 40, 40), 0.2)       # rear underrun bar
    p.box((0.04, 0.6 * w, 0.3), (xn - 0.01, 0, cab_lo + 0.45), (30, 30, 30), 0.1)         # grille
    lamps_and_plates(p, l / 2, -l / 2 + 0.1, cab_hw - 0.3, z_head=cab_lo + 0.2, z_tail=floor - 0.15,
                     z_plate_front=cab_lo + 0.1, z_plate_rear=floor - 0.35)
    _wheels(p, w, h, r, (l / 2 - 1.1, -l / 2 + 1.3, -l / 2 + 2.4), tire_w=0.35)
    return p.build()


def bus(l, w, h, color) -> trimesh.Trimesh:
    """A city bus: a driver's end with a tall raked windscreen and a destination sign, an engine end
    with a closed panel, a roof pod over the front half, a short front and long rear overhang."""
    p = Parts()
    paint, refl = color, paint_reflectivity(color)
    bottom, top = -h / 2, h / 2
    r = 0.5
    floor, roof = bottom + 0.7 * r, top - 0.3
    lo, mid = floor + 0.45 * (roof - floor), floor + 0.8 * (roof - floor)
    hw = w / 2
    # Lower body: the front's lower corner is chamfered (approach angle), the rear's less so.
    xn, xt = l / 2 - 0.02, -l / 2 + 0.02             # the lower body's ends; lamps and plates stand out
    p.prism([(xt, floor + 0.15), (xt + 0.2, floor), (xn - 0.5, floor), (xn, floor + 0.35),
             (xn, lo), (xt, lo)], hw, paint, refl)
    # Window band: a raked windscreen at the front, glass sides, a closed engine end at the back.
    p.prism([(-l / 2 + 1.2, lo), (l / 2, lo), (l / 2 - 0.25, mid), (-l / 2 + 1.2, mid)], 0.995 * hw, GLASS, GLASS_REFL)
    p.prism([(-l / 2, lo), (-l / 2 + 1.2, lo), (-l / 2 + 1.2, mid), (-l / 2, mid)], hw, paint, refl)
    p.prism([(-l / 2, mid), (l / 2 - 0.25, mid), (l / 2 - 0.4, roof), (-l / 2, roof)], hw, paint, refl)
    p.box((0.04, 0.7 * w, 0.25), (l / 2 - 0.33, 0, mid + 0.15), (255, 160, 30), 0.3)   # destination sign
    p.prism([(-0.1 * l, roof - 0.01), (0.4 * l, roof - 0.01), (0.38 * l, top), (-0.08 * l, top)],
            0.4 * w, (200, 200, 200), 0.5)                                              # air-conditioning pod
    p.box((0.04, 0.8 * w, 0.5), (xt + 0.01, 0, floor + 0.45), (50, 50, 50), 0.15)        # engine grille
    lamps_and_plates(p, l / 2, -l / 2, hw - 0.3, z_head=floor + 0.5, z_tail=lo - 0.25,
                     z_plate_front=floor + 0.25, z_plate_rear=lo - 0.6)
    _wheels(p, w, h, r, (l / 2 - 2.6, -l / 2 + 3.4), tire_w=0.35)
    return p.build()


def construction_vehicle(l, w, h, color) -> trimesh.Trimesh:
    """A tracked excavator: two crawler tracks, a house with the cab at its front left and a
    counterweight at its back, and a boom rising from the house's front with the arm and bucket
    lowered ahead of it (its front is the working end)."""
    p = Parts()
    paint, refl = color, paint_reflectivity(color)
    bottom, top = -h / 2, h / 2
    track_h, track_w = 0.8, min(0.6, 0.25 * w)
    x_track = (-l / 2 + 0.2, l / 2 - 1.2)                           # the crawlers; the bucket reaches beyond
    for side in (-1, 1):
        p.prism([(x_track[0], bottom + 0.35), (x_track[0] + 0.35, bottom), (x_track[1] - 0.35, bottom),
                 (x_track[1], bottom + 0.35), (x_track[1] - 0.15, bottom + track_h), (x_track[0] + 0.15, bottom + track_h)],
                track_w / 2, TIRE, 0.05, y=side * (w / 2 - track_w / 2))
    house_lo, house_top = bottom + track_h + 0.1, bottom + 0.62 * h
    x_house = (-l / 2 + 0.04, 0.12 * l)
    p.box((x_house[1] - x_house[0], 0.95 * w, house_top - house_lo), (sum(x_house) / 2, 0, (house_lo + house_top) / 2),
          paint, refl)
    p.box((0.4, 0.9 * w, 0.5), (x_house[0] + 0.2, 0, house_top + 0.25), (60, 60, 60), 0.3)       # counterweight
    cab_y = w / 2 - 0.45
    p.prism([(x_house[1] - 1.6, house_top), (x_house[1] - 0.02, house_top), (x_house[1] - 0.2, top - 0.02),
             (x_house[1] - 1.6, top - 0.02)], 0.42, GLASS, GLASS_REFL, y=cab_y)                       # the cab
    p.box((1.4, 0.86, 0.06), (x_house[1] - 0.88, cab_y, top - 0.03), paint, refl)                     # cab roof
    x_boom, x_tip = x_house[1] - 0.6, l / 2 - 1.4
    p.prism([(x_boom, house_lo + 0.3), (x_boom + 0.5, house_lo + 0.3), (x_tip + 0.3, top - 0.45), (x_tip - 0.2, top - 0.1)],
            0.22, paint, refl, y=-0.15)                                                               # boom
    p.prism([(x_tip - 0.2, top - 0.1), (x_tip + 0.3, top - 0.45), (l / 2 - 0.45, bottom + 0.75), (l / 2 - 0.8, bottom + 0.8)],
            0.18, paint, refl, y=-0.15)                                                               # arm
    p.prism([(l / 2 - 1.05, bottom + 0.75), (l / 2 - 0.35, bottom + 0.95), (l / 2 - 0.02, bottom + 0.35),
             (l / 2 - 0.4, bottom + 0.02)], 0.5, (70, 70, 70), 0.3, y=-0.15)                          # bucket
    lamps_and_plates(p, x_house[1] + 0.04, -l / 2, 0.4 * w, z_head=house_top - 0.25, z_tail=house_lo + 0.3,
                     z_plate_front=house_lo + 0.15, z_plate_rear=house_lo + 0.6, head=(0.2, 0.12), tail=(0.2, 0.12))
    return p.build()


def trailer(l, w, h, color) -> trimesh.Trimesh:
    """A semi-trailer: a tall box on a floor that the tractor's fifth wheel carries at the front
    (kingpin end, with landing legs and a rounded front top), three axles at the back with red
    tail lights, a yellow plate and an underrun bar. The front (+x) is the hitch end."""
    p = Parts()
    paint, refl = color, paint_reflectivity(color)
    bottom, top = -h / 2, h / 2
    r = 0.5
    floor = bottom + 1.25
    xn, xt = l / 2 - 0.04, -l / 2 + 0.04                             # the box's ends; the lamps stand out
    p.prism([(xt, floor), (xn, floor), (xn, top - 0.2), (xn - 0.2, top), (xt, top)], 0.99 * w / 2, paint, refl)
    p.box((xn - xt, 0.98 * w, 0.06), ((xn + xt) / 2, 0, floor + 0.4), (200, 30, 30), 0.9)        # a reflective stripe
    p.box((l - 0.4, 0.5 * w, 0.25), (-0.2, 0, floor - 0.125), (30, 30, 30), 0.1)                 # chassis rails
    for side in (-1, 1):                                             # landing legs behind the kingpin
        p.box((0.15, 0.15, floor - bottom - 0.02), (l / 2 - 2.2, side * 0.35 * w, (bottom + 0.02 + floor) / 2), (70, 70, 70), 0.3)
    p.box((0.1, 0.9 * w, 0.15), (-l / 2 + 0.05, 0, bottom + 0.55), (40, 40, 40), 0.2)            # rear underrun bar
    hw = w / 2 - 0.3
    for side in (-1.0, 1.0):
        p.box((0.04, 0.3, 0.15), (-l / 2 + 0.02, side * hw, floor - 0.35), TAILLIGHT, TAILLIGHT_REFL)
        p.box((0.04, 0.12, 0.08), (l / 2 - 0.02, side * hw, top - 0.35), HEADLIGHT, HEADLIGHT_REFL)  # front markers
    p.box((0.04, 0.52, 0.11), (-l / 2 + 0.02, 0.0, floor - 0.6), PLATE_REAR, PLATE_REFL)
    _wheels(p, w, h, r, (-l / 2 + 1.5, -l / 2 + 2.8, -l / 2 + 4.1), tire_w=0.35)
    return p.build()
