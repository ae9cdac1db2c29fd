"""The nuScenes attribute of a detection: from its speed where the speed tells, from the head's
still logit where it does not.

A nuScenes attribute is a state of the object. Three of them follow from the speed, with the
thresholds the simulator labels by (``simgen/labels.py``): a vehicle faster than 0.3 m/s is
``vehicle.moving``, a walker faster than 0.2 m/s ``pedestrian.moving``, and a two-wheeler that
moves has a rider. An object at rest is in one of two states that no speed tells apart:

==========  =========================  ==================================
classes     still state 0              still state 1
==========  =========================  ==================================
vehicles    ``vehicle.stopped``        ``vehicle.parked``
pedestrian  ``pedestrian.standing``    ``pedestrian.sitting_lying_down``
cycles      ``cycle.with_rider``       ``cycle.without_rider``
==========  =========================  ==================================

(a two-wheeler's rider is its state at any speed). The head learns which with one logit per
anchor, the still logit (``ModelConfig.loss.attribute``; :mod:`clfbev.supervision.targets`):
state 1 where it is >= 0. Without that head the most common state of the nuScenes and simulated
data stands in: parked, standing, without rider.
"""

from __future__ import annotations

VEHICLES = ("car", "truck", "bus", "trailer", "construction_vehicle")
CYCLES = ("bicycle", "motorcycle")
VEHICLE_MOVING_SPEED = 0.3     # m/s
PEDESTRIAN_MOVING_SPEED = 0.2  # m/s
CYCLE_MOVING_SPEED = 0.3       # m/s

# Per detection class: (the attribute when it moves, (still state 0, still state 1), the still
# state taken without a head).
_VEHICLE = ("vehicle.moving", ("vehicle.stopped", "vehicle.parked"), 1)
_PEDESTRIAN = ("pedestrian.moving", ("pedestrian.standing", "pedestrian.sitting_lying_down"), 0)
_CYCLE = ("cycle.with_rider", ("cycle.with_rider", "cycle.without_rider"), 1)
STATES = {**{c: _VEHICLE for c in VEHICLES}, "pedestrian": _PEDESTRIAN, **{c: _CYCLE for c in CYCLES}}


def moving_speed(name: str) -> float:
    """m/s above which a ``name`` object moves."""
    return PEDESTRIAN_MOVING_SPEED if name == "pedestrian" else CYCLE_MOVING_SPEED if name in CYCLES \
        else VEHICLE_MOVING_SPEED


def attribute_for(name: str, speed: float, still_logit: float | None = None) -> str:
    """The nuScenes attribute of a ``name`` box moving at ``speed`` m/s ('' for cones and
    barriers): the moving one above :func:`moving_speed`, else the still state of
    ``still_logit`` (state 1 where >= 0; None: the class's common state)."""
    if name not in STATES:
        return ""
    moving, still, common = STATES[name]
    if speed > moving_speed(name):
        return moving
    return still[common if still_logit is None else int(still_logit >= 0)]


def still_state(name: str, attribute: str) -> int:
    """The still state (0 or 1) a ``name`` object with the nuScenes ``attribute`` is in, -1 where
    it has none to learn (a moving vehicle or walker, a class without attributes, an attribute
    of another class)."""
    if name not in STATES:
        return -1
    _, still, _ = STATES[name]
    return still.index(attribute) if attribute in still else -1
