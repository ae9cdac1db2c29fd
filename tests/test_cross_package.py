"""The facts simgen and clfbev each keep a copy of, pinned to each other.

The two packages never import each other (tests/test_layout.py), so a rule both need is written
twice: once where the generator labels its data, once where the detector reads or scores it.
These tests feed both copies the same inputs and require the same answers.

- The attributes: simgen labels an object moving above a class's threshold, and at rest by
  its state (parked or stopped, with or without a rider: ``simgen.labels.attribute``); clfbev
  derives the attribute of a detection from its predicted speed with the same thresholds and
  from its still logit with the same names for the states at rest
  (``clfbev.attributes.attribute_for``).
- The sector filter: simgen's ``fov`` degradation (``simgen.degrade.keep_sector``) and clfbev's
  ``fov`` corruption (``clfbev.corruptions.corrupt_points``) keep the same points.
- The detection classes: every class simgen makes is written under a category that the
  devkit maps back to that class, and is one of clfbev's ``DETECTION_CLASSES``, which are the
  devkit's ten.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from clfbev.corruptions import Corruption, corrupt_points
from clfbev.attributes import attribute_for
from clfbev.settings import DETECTION_CLASSES
from simgen import degrade, labels, world

THRESHOLDS = sorted({*labels.MOVING_SPEED.values(), labels.DEFAULT_MOVING_SPEED})


def speed_grid() -> list[float]:
    """Speeds (m/s) around and at every threshold either package uses, and well away from them."""
    around = [v for t in THRESHOLDS for v in (np.nextafter(t, 0.0), t, np.nextafter(t, np.inf), t - 1e-6, t + 1e-6)]
    return sorted({0.0, 1e-9, 0.1, 0.25, 0.5, 1.0, 5.0, 30.0, *map(float, around)})


def simgen_actor(cls: str, parked: bool = False, rider: bool = True) -> SimpleNamespace:
    """What ``labels.attribute`` reads of an actor."""
    return SimpleNamespace(cls=cls, parked=parked, rider=rider)


# The still logit of each still state (clfbev.attributes): state 0 below 0, state 1 at or above.
STATE_0, STATE_1 = -5.0, 5.0


@pytest.mark.parametrize("speed", speed_grid())
def test_a_pedestrian_gets_the_same_attribute(speed):
    simgen = labels.attribute(simgen_actor("pedestrian"), speed)
    assert simgen == attribute_for("pedestrian", speed) == attribute_for("pedestrian", speed, STATE_0)


@pytest.mark.parametrize("cls", world.VEHICLES)
@pytest.mark.parametrize("speed", speed_grid())
def test_a_driving_vehicle_gets_the_same_attribute_in_still_state_0(cls, speed):
    """Above the same threshold `vehicle.moving` in both; below it simgen writes
    `vehicle.stopped` (the car is in traffic), which is clfbev's still state 0. Without a still
    head clfbev says `vehicle.parked`, the common state."""
    simgen = labels.attribute(simgen_actor(cls), speed)
    assert simgen == attribute_for(cls, speed, STATE_0)
    assert attribute_for(cls, speed) == ("vehicle.moving" if simgen == "vehicle.moving" else "vehicle.parked")


@pytest.mark.parametrize("cls", world.VEHICLES)
def test_a_parked_vehicle_is_parked_in_both(cls):
    assert labels.attribute(simgen_actor(cls, parked=True), 0.0) == attribute_for(cls, 0.0, STATE_1) == \
        attribute_for(cls, 0.0) == "vehicle.parked"


@pytest.mark.parametrize("cls", world.CYCLES)
@pytest.mark.parametrize("speed", speed_grid())
def test_a_ridden_cycle_is_with_rider_in_both_at_any_speed(cls, speed):
    """simgen names a cycle's attribute by its rider; clfbev gives a moving cycle its rider (above
    simgen's moving threshold) and a still one still state 0 (with rider) or 1 (without)."""
    assert labels.attribute(simgen_actor(cls), speed) == attribute_for(cls, speed, STATE_0) == "cycle.with_rider"


@pytest.mark.parametrize("cls", world.CYCLES)
def test_a_parked_cycle_is_without_rider_in_both(cls):
    parked = simgen_actor(cls, parked=True, rider=False)
    assert labels.attribute(parked, 0.0) == attribute_for(cls, 0.0, STATE_1) == attribute_for(cls, 0.0) == \
        "cycle.without_rider"
    fastest_still = labels.MOVING_SPEED.get(cls, labels.DEFAULT_MOVING_SPEED)
    assert attribute_for(cls, float(np.nextafter(fastest_still, np.inf)), STATE_1) == "cycle.with_rider"


@pytest.mark.parametrize("cls", ["traffic_cone", "barrier"])
def test_static_objects_have_no_attribute_in_both(cls):
    for speed in speed_grid():
        assert labels.attribute(simgen_actor(cls), speed) is None and attribute_for(cls, speed) == ""


# ---------------------------------------------------------------- the sector filter

FOVS = [1.0, 30.0, 70.0, 90.0, 120.0, 180.0, 270.0, 359.0, 359.999, 360.0]


def points_at_azimuths(azimuths: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 5) lidar points (x, y, z, intensity, ring) at the given azimuths (rad), ranges 1-60 m."""
    r = rng.uniform(1.0, 60.0, len(azimuths))
    return np.stack([r * np.cos(azimuths), r * np.sin(azimuths), rng.uniform(-2, 2, len(azimuths)),
                     rng.uniform(0, 255, len(azimuths)), rng.integers(0, 32, len(azimuths))], axis=1)


def sector_grid(forward_az: float, fov_deg: float) -> np.ndarray:
    """Azimuths (rad) on a fine grid all around, and at, just inside and just outside both edges
    of the sector and the point straight behind."""
    half = np.deg2rad(fov_deg) / 2
    edges = np.array([-half, half, -np.pi, np.pi, 0.0])
    near = np.concatenate([edges, np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf), edges + 1e-9, edges - 1e-9])
    return forward_az + np.concatenate([np.linspace(-np.pi, np.pi, 7201), near])


@pytest.mark.parametrize("fov_deg", FOVS)
@pytest.mark.parametrize("forward_az", [0.0, np.pi / 2, np.pi, -np.pi / 2, 0.3, -2.9, 3.0])
def test_the_sector_filters_keep_the_same_points(forward_az, fov_deg):
    rng = np.random.default_rng(int(fov_deg * 1000) + int(forward_az * 100))
    points = points_at_azimuths(sector_grid(forward_az, fov_deg), rng)
    forward_lidar = np.array([np.cos(forward_az), np.sin(forward_az), 0.0])
    kept_simgen = degrade.keep_sector(points, forward_lidar, fov_deg)
    kept_clfbev = corrupt_points(points, points[:, 4], forward_lidar, [Corruption("fov", fov_deg)], "token")
    assert np.array_equal(kept_simgen, kept_clfbev)
    if fov_deg < 360:      # not vacuous: the edge decides for some points
        assert 0 < len(kept_simgen) < len(points)


# ---------------------------------------------------------------- the detection classes

def test_the_detection_classes_are_the_devkits():
    from nuscenes.eval.detection.constants import DETECTION_NAMES
    assert sorted(DETECTION_CLASSES) == sorted(DETECTION_NAMES) and len(DETECTION_CLASSES) == len(DETECTION_NAMES)


@pytest.mark.parametrize("cls", world.CLASSES)
def test_every_simgen_class_reads_back_as_itself(cls):
    """simgen writes class c under the category world.CATEGORY[c]; the devkit (which clfbev loads
    the annotations with) maps that category back to c, one of clfbev's detection classes."""
    from nuscenes.eval.detection.utils import category_to_detection_name
    assert category_to_detection_name(world.CATEGORY[cls]) == cls
    assert cls in DETECTION_CLASSES
