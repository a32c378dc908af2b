"""The coordination layer: the problem's structure decides how a move is planned, above any planner.

A collision-free trajectory played backwards in time is collision-free, keeps the same speed
limits and hard stops, and starts where the original ended. So (``formulations/coordination.md``):

- ``reverse``: a move whose reverse is easier is planned in reverse and played forwards (an
  unfold, datum -> targets, is a fold from the targets, reversed);
- ``via_datum``: the whole move as two legs through the datum, each planned in its easy
  direction: start -> datum (a fold), then (target -> datum) reversed;
- ``via_fold``: the same through the folded configuration half-way in alpha (measured: the legs
  stall far more often than through the datum, where every arm turns the same way);
- ``auto`` (the default): by the scenario's structure: an unfold is reversed (where the reversed
  fold straggles, the mpc's fold is planned again with its schedule's paired timed paths, the
  shorter kept: ``schedule_pairs_retry``; on a dense field that second fold starts at once on the
  second core, let go if not needed), a fold planned directly; on instruments whose patrol regions overlap densely (reach > 0.8 pitch: MOONS,
  SDSS) the two-leg plan; elsewhere the direct plan, and where it leaves positioners short, the
  better of a **fix-up** (the direct plan until its last arrival, then only the positioners
  still short, and the neighbours they need, through the datum, everyone else holding) and the
  **two-leg** plan. It is never worse than the two-leg plan: a candidate slower than it, or
  leaving more short, is not returned. Whatever the first choice, if it leaves positioners
  short, or is complete only through the later fallback rounds inside a leg (``legs.Leg.rescued``)
  or through group moves (``legs.Leg.grouped``),
  the fallback planner plans the whole move (its own route and in-leg fallback), then the direct
  plan is the fallback;
- ``direct``: the planner alone.

Every leg is planned by the same planner (``mpc`` or ``dnf``, so that comparisons stay fair;
the fallback planner only where this one leaves positioners short, and the result names it),
completed by further attempts from where the previous one stopped (each attempt is the same
planner from a new start, which breaks the state of a deadlock), shortened by restarts from
where most of its positioners had arrived (``legs``), and the legs are joined at configurations
that are equal, the second leg through the datum starting while the last ones still fold where
that is clear (``retime``), into one continuous trajectory that the caller verifies whole.
The result's ``stats`` name the route, the legs (times, planner attempts, positioners moved) and
which positioners each strategy carried.
"""

from fiberplan.planners.coordination.layer import DENSE_REACH, coordinate
from fiberplan.planners.coordination.legs import leg_scenario
from fiberplan.planners.coordination.settings import ROUTES, RouteSettings

__all__ = ["DENSE_REACH", "ROUTES", "RouteSettings", "coordinate", "leg_scenario"]
