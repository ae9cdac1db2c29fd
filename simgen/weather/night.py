"""Night: the sun below the horizon; street lights and vehicles' lamps light the scene.

The sun gives nothing (the world keeps the sun it drew, so that it stays the day's world; the
night's cameras do not use it, nor cast its shadows). Every surface point gets the irradiance
(lux) of a dim ambient and of each nearby light, ``E = I(direction) cos(theta) / r^2`` (``theta``
between the surface normal and the light, ``r`` the distance), and sends back the luminance
``L = rho E / pi`` (cd/m^2, a Lambertian surface of linear reflectance ``rho``), plus what it
emits itself (lit lamp lenses). A face's 8-bit colour is read as an sRGB-encoded reflectance,
which gives the materials their measured albedos: asphalt (62) 0.048, a sidewalk (168) 0.39,
white road paint (235) 0.83. The lights cast no shadows: a shadow map per light would cost a
depth pass each, so light reaches what an object hides from it (the road behind a car ahead is
lit by the ego's low beam); a surface turned away from a light is never lit, which keeps lamps
from lighting building walls from behind.

- Ambient: 0.5 lux, neutral, on every surface alike: moonlight (0.05-0.3 lux at full moon) and a
  lit city's sky glow and inter-reflected street light, which the direct-only shading omits.
  The sky's luminance is 0.02 cd/m^2 (an urban night sky, 17-18 mag/arcsec^2), in the street
  lights' warm white. (Daylight for comparison: 10^4-10^5 lux.)
- Street lights (:func:`street_lights`): along both kerbs of every road, 30 m apart on each side
  and staggered, 9 m high, 1 m in from the kerb (a pole at the kerb with an outreach arm), 4000 K
  LED. A road luminaire spreads its light along the road and across it, little behind it: its
  intensity toward a direction at ``gamma`` from the nadir is ``I0 / cos^3 gamma``, which puts the
  same ``E = I0 / h^2`` on every point of a flat road it reaches, over the ground ellipse where
  that direction lands within 25 m along the road, the far kerb across it and the sidewalk's
  back edge behind it (:func:`street_intensity`); beyond the ellipse it falls linearly to 0 at
  1.5 times its size, and to nothing at or above the horizontal (full cut-off). ``I0`` = 330 cd
  (4 lux alone, 8 kcd at the ellipse's far ends) gives the roads 15 lux on average with a
  uniformity Emin / Emean of 0.8 (tests/simgen/test_night.py): EN 13201-2 class C3 (15 lux,
  U0 >= 0.4), urban main roads. The luminaire itself (a downward disc of 0.3 m radius, no geometry
  in the world: the lidar and the labels do not know it) is drawn with its luminance
  ``I / (pi r^2 cos gamma)`` where nothing nearer hides it.
- Vehicles' lamps (:func:`vehicle_lamps`): every vehicle and ridden cycle that is not parked has
  its low beams on, the ego too. A low beam (:func:`headlamp_intensity`) peaks at 12 000 cd 1
  degree below the horizon, falls to a quarter 12 degrees sideways and 5 degrees further down
  (with a wide skirt to the kerbs) and cuts off sharply above the horizon to 250 cd, which meets
  ECE Regulation 112's class B points on its 25 m screen (50R and 75R >= 12 lux, 50V >= 6 lux,
  25L and 25R >= 2 lux, B50L <= 0.4 lux; checked in the tests). A bicycle's lamp is a tenth of
  that. Lit lamp lenses emit: head lamps 10^4 cd/m^2
  white, tail lamps 60 cd/m^2 red (ECE Regulation 7: 4-12 cd over a 0.07-0.2 m^2 lens), both far
  above the night's full scale of 3.6 cd/m^2, so they are saturated blobs as in a real night
  image; a red lens passes 0.4 % and 0.25 % of its red to the green and blue channels.

Which lights a camera uses (bounded, so the shading costs lights x pixels): the street lights and
the vehicle lamps whose sphere of influence (40 m and 100 m) meets its view, the nearest
``MAX_STREET_LIGHTS`` (24) and ``MAX_VEHICLE_LAMPS`` (16) of them.

Frames: lights and surfaces in the global frame (x east, y north, z up, m); a lamp's beam frame is
its vehicle's box frame (x forward, y left, z up). Colours are linear RGB per unit luminance
(Y = 0.2126 R + 0.7152 G + 0.0722 B = 1). The per-pixel shading is simgen/weather/night_shading.py,
the camera's exposure and noise simgen/weather/night_sensor.py.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numba
import numpy as np

from ..layout import MAP_PAD, Grid
from ..parts import HEADLIGHT, TAILLIGHT
from ..world import World

AMBIENT_LUX = 0.5
SKY_LUMINANCE = 0.02                  # cd/m^2
NEUTRAL = np.array([1.0, 1.0, 1.0])
WARM_WHITE = np.array([1.440, 0.917, 0.527])    # 4000 K LED (blackbody 4000 K in linear sRGB, Y = 1)
COOL_WHITE = np.array([1.092, 0.978, 0.942])    # 6000 K LED head lamp

LAMP_SPACING = 30.0                   # m along each kerb; the two kerbs are staggered by half of it
LAMP_HEIGHT = 9.0                     # m above the road
LAMP_INSET = 1.0                      # m from the kerb line over the road
LAMP_I0 = 330.0                       # cd at the nadir
LAMP_ALONG = 25.0                     # m: the uniformly lit ellipse's reach along the road
LAMP_TAPER = 0.5                      # beyond the ellipse, 0 at (1 + LAMP_TAPER) times its size
LAMP_RADIUS = 0.3                     # m, the luminaire's emitting disc
STREET_REACH = 40.0                   # m: nothing farther is lit (its direction meets the road past the taper)

HEAD_I0 = 12_000.0                    # cd at the beam's peak
HEAD_PEAK = np.tan(np.radians(-1.0))  # tangent of the peak's elevation
HEAD_CUTOFF = np.tan(np.radians(0.5)) # above it, only the glare light
HEAD_WIDTH_V = np.tan(np.radians(5.0))    # the beam's half width at a quarter of its peak, below it
HEAD_WIDTH_H = np.tan(np.radians(12.0))   # and sideways
HEAD_SKIRT = 0.1                      # a wide sideways component (half width 45 degrees) lights the kerbs
HEAD_GLARE = 250.0                    # cd above the cut-off
HEAD_AHEAD = 0.05                     # m: the source sits this far ahead of the lens, which it must not light
HEAD_REACH = 100.0
CYCLE_LAMP_SCALE = 0.1

HEAD_EMISSION = 1.0e4 * NEUTRAL       # cd/m^2 per channel of a lit head lamp lens
TAIL_EMISSION = 60.0 * np.array([1.0, 0.004, 0.0025]) / 0.2126     # red lens, 60 cd/m^2 of luminance

MAX_STREET_LIGHTS = 24
MAX_VEHICLE_LAMPS = 16

STREET, HEAD = 0, 1                   # light kinds


@dataclass(frozen=True)
class Lights:
    """Light sources at one time, global frame: ``pos`` (n, 3) m; ``forward`` and ``left`` (n, 3)
    the horizontal axes of each light's frame (a head lamp's vehicle x and y; a street light's
    road direction and its direction across to the road's centre); ``kind`` (n,) STREET or HEAD;
    ``colour`` (n, 3) linear RGB times the lamp's intensity scale; ``reach`` (n,) m, the radius of
    its sphere of influence; ``footprint`` (n, 3) m, a street light's lit ellipse (along, across
    the road, behind; zeros for a head lamp); ``lit_ids`` (j,) the ids of the actors whose lamp
    lenses glow."""
    pos: np.ndarray
    forward: np.ndarray
    left: np.ndarray
    kind: np.ndarray
    colour: np.ndarray
    reach: np.ndarray
    footprint: np.ndarray
    lit_ids: np.ndarray

    ARRAYS = ("pos", "forward", "left", "kind", "colour", "reach", "footprint")

    def take(self, index: np.ndarray) -> Lights:
        return Lights(*(np.ascontiguousarray(getattr(self, a)[index]) for a in self.ARRAYS), self.lit_ids)

    def __add__(self, other: Lights) -> Lights:
        return Lights(*(np.concatenate([getattr(self, a), getattr(other, a)]) for a in self.ARRAYS), self.lit_ids)

    def nearest(self, seen: np.ndarray, eye: np.ndarray) -> Lights:
        """The lights a camera at ``eye`` (3,) uses: of those ``seen`` ((n,) bool, whose sphere of
        influence meets its view), the ``MAX_STREET_LIGHTS`` street lights and ``MAX_VEHICLE_LAMPS``
        head lamps nearest to it."""
        dist = np.linalg.norm(self.pos - eye, axis=1)
        keep = []
        for kind, cap in ((STREET, MAX_STREET_LIGHTS), (HEAD, MAX_VEHICLE_LAMPS)):
            idx = np.flatnonzero(seen & (self.kind == kind))
            keep.append(idx[np.argsort(dist[idx], kind="stable")[:cap]])
        return self.take(np.sort(np.concatenate(keep)))


@dataclass(frozen=True)
class NightScene:
    """A scene's light sources, a pure function of its world and layout (no random draws).

    street : the street luminaires (:func:`street_lights`).  lamp_actor : (k,) index into the world's
    actors of each head lamp, ``lamp_box`` (k, 3) its source in that actor's box frame (the ego's
    raised by half its height: its pose is on the ground), ``lamp_scale`` (k,) its intensity
    relative to a car's.  lit_ids : (j,) ids of the actors whose lamp lenses glow."""
    street: Lights
    lamp_actor: np.ndarray
    lamp_box: np.ndarray
    lamp_scale: np.ndarray
    lit_ids: np.ndarray

    def at(self, poses: np.ndarray) -> Lights:
        """The lights at one time, given every actor's (n, 4, 4) T_global_from_box then."""
        T = poses[self.lamp_actor]
        k = len(T)
        lamps = Lights(pos=np.einsum("kij,kj->ki", T[:, :3, :3], self.lamp_box) + T[:, :3, 3],
                       forward=T[:, :3, 0], left=T[:, :3, 1], kind=np.full(k, HEAD, np.int64),
                       colour=self.lamp_scale[:, None] * COOL_WHITE, reach=np.full(k, HEAD_REACH),
                       footprint=np.zeros((k, 3)), lit_ids=self.lit_ids)
        return dataclasses.replace(self.street, lit_ids=self.lit_ids) + lamps


def street_lights(grid: Grid) -> Lights:
    """The street luminaires, a pure function of the layout (global frame, m).

    Along every road (centreline ``c``, half width ``hw``) over the whole city, which starts at
    ``MAP_PAD``: over the kerb at ``c - hw`` at ``u = MAP_PAD + (k + 1/2) S`` and over the kerb at
    ``c + hw`` at ``u = MAP_PAD + (k + 1) S``, each ``LAMP_INSET`` in from its kerb and
    ``LAMP_HEIGHT`` up. Each lights the ellipse reaching ``LAMP_ALONG`` along the road, to the far
    kerb across it and to the sidewalk's back edge behind it."""
    W, H = grid.extent
    hw, inset = grid.road_half_width, grid.road_half_width - LAMP_INSET
    pos, forward, left = [], [], []
    for along_x, centres, length in ((True, grid.ys, W), (False, grid.xs, H)):
        axis = np.array([1.0, 0.0, 0.0]) if along_x else np.array([0.0, 1.0, 0.0])
        across = np.array([0.0, 1.0, 0.0]) if along_x else np.array([1.0, 0.0, 0.0])
        for side, first in ((-1.0, 0.5), (1.0, 1.0)):
            u = MAP_PAD + LAMP_SPACING * np.arange(first, length / LAMP_SPACING)
            uu, vv = (a.ravel() for a in np.meshgrid(u, centres + side * inset))
            xy = np.stack([uu, vv], -1) if along_x else np.stack([vv, uu], -1)
            pos.append(np.c_[xy, np.full(len(xy), LAMP_HEIGHT)])
            forward.append(np.tile(axis, (len(xy), 1)))
            left.append(np.tile(-side * across, (len(xy), 1)))
    m = sum(len(p) for p in pos)
    footprint = np.tile([LAMP_ALONG, 2 * hw - LAMP_INSET, LAMP_INSET + grid.cfg.sidewalk_width], (m, 1))
    return Lights(np.concatenate(pos), np.concatenate(forward), np.concatenate(left), np.full(m, STREET, np.int64),
                  np.tile(WARM_WHITE, (m, 1)), np.full(m, STREET_REACH), footprint, np.zeros(0, np.int64))


def lights_on(world: World) -> np.ndarray:
    """(n,) bool: the actors whose lamps are on: the ego, and every vehicle or cycle that is not
    parked (a cycle only with its rider). Pedestrians, cones and barriers have no lamps."""
    return np.array([i == 0 or (not a.parked and a.cls not in ("pedestrian", "traffic_cone", "barrier")
                                and (a.cls not in ("bicycle", "motorcycle") or a.rider))
                     for i, a in enumerate(world.actors)], bool)


def vehicle_lamps(world: World) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The head lamps of the actors with their lights on: (k,) actor index, (k, 3) source position
    in the box frame, (k,) intensity scale. A lamp is the forward-facing faces of the actor's
    head-lamp-coloured parts on one side (y < 0 or y > 0; one lamp on a cycle), its source at
    their area-weighted centre, ``HEAD_AHEAD`` in front of the lens. A trailer's are marker
    lights, not head lamps."""
    index, box, scale = [], [], []
    on = lights_on(world)
    for i, a in enumerate(world.actors):          # a loop over actors, each vectorised over its faces
        if not on[i] or a.cls == "trailer":
            continue
        colours = np.asarray(a.mesh.visual.face_colors)[:, :3]
        front = np.all(colours == HEADLIGHT, axis=1) & (np.asarray(a.mesh.face_normals)[:, 0] > 0.9)
        centres, area = np.asarray(a.mesh.triangles_center)[front], np.asarray(a.mesh.area_faces)[front]
        cycle = a.cls in ("bicycle", "motorcycle")
        groups = [np.ones(len(centres), bool)] if cycle else [centres[:, 1] < 0, centres[:, 1] > 0]
        for g in groups:
            if not g.any():
                continue
            p = (centres[g] * area[g, None]).sum(0) / area[g].sum() + [HEAD_AHEAD, 0.0, 0.0]
            if i == 0:
                p[2] += world.sizes[0, 2] / 2 - world.z[0, 0]
            index.append(i)
            box.append(p)
            scale.append(CYCLE_LAMP_SCALE if a.cls == "bicycle" else 1.0)
    return np.array(index, np.int64), np.array(box, np.float64).reshape(-1, 3), np.array(scale, np.float64)


def night_scene(world: World, grid: Grid) -> NightScene:
    """The light sources of a scene: its layout's street lights, its vehicles' lamps."""
    index, box, scale = vehicle_lamps(world)
    ids = np.array([a.id for a in world.actors], np.int64)[lights_on(world)]
    return NightScene(street_lights(grid), index, box, scale, ids)


@dataclass(frozen=True)
class FaceTables:
    """Per face of a renderer's face table (index 0 = the sky): ``albedo`` (F, 3) float32 linear
    reflectance, ``normal`` (F, 3) float32 unit normal, global frame (a moving actor's faces are
    re-posed before each render), ``emit`` (F, 3) float32 emitted luminance, cd/m^2."""
    albedo: np.ndarray
    normal: np.ndarray
    emit: np.ndarray


def emission(colours: np.ndarray, owner: np.ndarray, lit_ids: np.ndarray) -> np.ndarray:
    """(F, 3) float32 emitted luminance (cd/m^2) per face: the head and tail lamp lenses, by their
    colours (F, 3) uint8, of the actors in ``lit_ids`` (``owner`` (F,) the actor id per face)."""
    lit = np.isin(owner, lit_ids) & (owner > 0)
    out = np.zeros(colours.shape, np.float32)
    out[lit & np.all(colours == HEADLIGHT, axis=1)] = HEAD_EMISSION
    out[lit & np.all(colours == TAILLIGHT, axis=1)] = TAIL_EMISSION
    return out


@numba.njit(cache=True, nogil=True)
def street_intensity(x, y, z, along, street, house):
    """Luminous intensity (cd) of a street luminaire toward the direction (x, y, z) of its frame
    (x along the road, y across to the road's centre, z up; unit length): ``I0 / cos^3 gamma``
    (``cos gamma = -z``) where that direction meets the road, ``LAMP_HEIGHT`` below, inside the
    ellipse of semi-axes ``along`` and ``street`` (y > 0) or ``house`` (y < 0) metres, falling
    linearly to 0 at ``1 + LAMP_TAPER`` times it; 0 at or above the horizontal."""
    if z >= 0.0:
        return 0.0
    reach = LAMP_HEIGHT / -z               # metres along the direction to the road plane
    b = street if y > 0.0 else house
    q = np.sqrt((reach * x / along) ** 2 + (reach * y / b) ** 2)
    share = min(1.0, max(0.0, 1.0 - (q - 1.0) / LAMP_TAPER))
    return LAMP_I0 / (-z) ** 3 * share


@numba.njit(cache=True, nogil=True)
def headlamp_intensity(x, y, z):
    """Luminous intensity (cd) of a low beam toward the direction (x, y, z) of its beam frame (x
    forward, y left, z up; any length): 0 behind the lamp. Sideways and downward it falls as
    ``1 / (1 + (t / w)^2)^2`` of the tangent ``t`` of the angle off its peak (a quarter of the peak
    at ``t = w``: arithmetic only, the shading evaluates it for every pixel and lamp); upward it
    drops linearly from the peak to the glare level at the cut-off."""
    if x <= 0.0:
        return 0.0
    t_h = y / x
    t_v = z / np.sqrt(x * x + y * y)
    a = 1.0 + (t_h / HEAD_WIDTH_H) ** 2
    horizontal = (1.0 / (a * a) + HEAD_SKIRT / (1.0 + t_h * t_h)) / (1.0 + HEAD_SKIRT)
    if t_v <= HEAD_PEAK:
        b = 1.0 + ((t_v - HEAD_PEAK) / HEAD_WIDTH_V) ** 2
        vertical = 1.0 / (b * b)
    elif t_v < HEAD_CUTOFF:
        vertical = 1.0 + (t_v - HEAD_PEAK) / (HEAD_CUTOFF - HEAD_PEAK) * (HEAD_GLARE / HEAD_I0 - 1.0)
    else:
        vertical = HEAD_GLARE / HEAD_I0
    return HEAD_I0 * horizontal * vertical
