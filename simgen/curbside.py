"""Heavy vehicles at the curb and on the road: buses standing at their stops, unhitched trailers
parked in the parking strips, and trailers hitched to moving trucks.

A hitched trailer starts on its tractor's path, its box a coupling gap behind the tractor's, with
the tractor's heading; :mod:`simgen.motion` drags it along (``Plan.tractor``): on a straight path
it stays on the line that distance back, through a turn it follows as a kinematic trailer
(:mod:`simgen.paths`). Tractor and trailer never touch and move as one.
"""
from __future__ import annotations

import numpy as np

from .config import SceneConfig
from .layout import Grid
from .placement import ActorMaker, Placer, Plan, lane
from .world import Actor

# The drawbar: m between a tractor's box and its trailer's. The hitch is the middle of the
# tractor's rear face, so the tractor's rear corners swing about it on a circle of the tractor's
# half width: a drawbar longer than the widest truck's half width (1.3 x 2.46 m / 2 = 1.6 m, the
# size draw's upper clip) keeps them off the trailer's front at any articulation, and the
# trailer's front corners, on a circle of radius hypot(2.0, half its width) about the hitch,
# reach the tractor's side only past 100 degrees (101 at the widest sizes drawn). A 0.6 m
# coupling would touch at about 30 degrees; the turns bring 40 to 65.
HITCH_GAP = 2.0
CURB_CLEARANCE = 0.2   # m between the curb and a vehicle standing at it


def _curb_line(grid: Grid, rng: np.random.Generator, width: float):
    """The line a vehicle ``width`` wide stands on with its side ``CURB_CLEARANCE`` off the curb,
    driven the way its side's traffic goes: (origin, heading, length)."""
    origin, heading, length, _ = lane(grid, rng, lateral=grid.road_half_width - CURB_CLEARANCE - width / 2)
    return origin, heading, length


def place_bus_stops(cfg: SceneConfig, grid: Grid, placer: Placer, new: ActorMaker,
                    rng: np.random.Generator) -> None:
    """``bus_stops_per_km`` buses standing at stops: in the parking strip, facing the traffic's
    way (stopped, not parked: they are in service)."""
    _place_at_curb(cfg, grid, placer, new, rng, "bus", cfg.actors.bus_stops_per_km, parked=False)


def place_parked_trailers(cfg: SceneConfig, grid: Grid, placer: Placer, new: ActorMaker,
                          rng: np.random.Generator) -> None:
    """``parked_trailers_per_km`` unhitched trailers parked in the parking strips."""
    _place_at_curb(cfg, grid, placer, new, rng, "trailer", cfg.actors.parked_trailers_per_km, parked=True)


def _place_at_curb(cfg: SceneConfig, grid: Grid, placer: Placer, new: ActorMaker, rng: np.random.Generator,
                   cls: str, per_km: float, parked: bool) -> None:
    """``per_km`` static actors of ``cls`` along the parking strips, each tried at up to 20 places."""
    for _ in range(int(round(per_km * grid.road_km))):
        actor = new(cls, parked=parked, rider=False)
        for _try in range(20):
            origin, heading, length = _curb_line(grid, rng, actor.size[1])
            s = rng.uniform(20.0, length - 20.0)
            plan = Plan(actor, origin + s * np.array([np.cos(heading), np.sin(heading)]), heading, 0.0, 0.0, 0.0)
            if placer.add(plan, 0.3):
                break


def hitch(trailer: Actor, tractor: Plan) -> Plan:
    """The plan of ``trailer`` hitched behind ``tractor``: on the tractor's path, ``HITCH_GAP``
    behind its box, not driving itself (it follows the tractor)."""
    behind = tractor.actor.size[0] / 2 + HITCH_GAP + trailer.size[0] / 2
    trailer.towed_by = tractor.actor.id
    return Plan(trailer, tractor.origin, tractor.heading, tractor.s0 - behind, tractor.length, 0.0,
                priority=tractor.priority, tractor=tractor, turn=tractor.turn)


def place_train(placer: Placer, tractor: Plan, trailer: Plan | None, margin: float) -> bool:
    """Adds a tractor and its trailer (or a lone vehicle when ``trailer`` is None) if both are free."""
    if trailer is None:
        return placer.add(tractor, margin)
    if not (placer.free(tractor.box(), margin) and placer.free(trailer.box(), margin)):
        return False
    return placer.add(tractor, margin) and placer.add(trailer, 0.0)
