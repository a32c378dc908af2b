"""The route settings every planner under the coordination layer shares (``mpc``, ``dnf``)."""

from __future__ import annotations

from dataclasses import dataclass

from fiberplan.settings import setting

ROUTES = ("direct", "reverse", "via_datum", "via_fold", "auto")
"""Values of the ``route`` setting."""

REVERSE_LEG, UNFOLD_REVERSED_LEG = "reverse", "unfold-reversed"
REVERSED_LEGS = (REVERSE_LEG, UNFOLD_REVERSED_LEG)
"""Kinds of the leg scenarios planned backwards in time and played reversed (a planner that
keeps motor limits applies them reversed there)."""

TAIL_FORWARD = "tail-backwards"
"""Kind of a reversed leg's tail planned backwards (``legs.tail_backwards``): reversed twice, it
is played forwards."""


@dataclass(frozen=True)
class RouteSettings:
    """Fields of a planner's settings read by the coordination layer (a planner's settings
    dataclass derives from this one and adds ``route_fallback_planner``)."""

    route: str = setting("auto", "how the move is planned: the planner alone (direct), reversed, through the datum, or chosen by "
                         "the scenario's structure (auto)", choices=ROUTES, group="route")
    route_attempts: int = setting(4, "attempts per leg: each from where the previous one stopped, until every positioner arrives",
                                  low=1, high=50, group="route")
    route_restarts: bool = setting(True, "a complete leg is planned again from where most of its positioners had arrived; the "
                                   "shortest is kept", group="route")
    route_tails: bool = setting(True, "a complete leg whose last positioners straggle has its tail planned backwards, from its "
                                "goal out to where they stood, and played in reverse; kept where shorter", group="route")
    route_overlap: bool = setting(True, "the leg from the datum starts while the last ones still fold, where every new pair "
                                  "keeps the safety margin", group="route")
    route_prioritized_up_to: int = setting(19, "groups of at most this many positioners also try the prioritized planner's "
                                           "schedule (reference 003), alone or through a partial retraction of those it leaves "
                                           "short; kept where shorter (0: never)", unit="positioners", low=0, high=1_000_000,
                                           group="route")
    route_rescue_up_to: int = setting(200, "a complete plan that needed the fallback planner's rounds inside a leg (rescued) or group moves is also "
                                      "compared with the fallback planner's whole move and the direct plan on fields of at most this "
                                      "many positioners; above, it is kept as it is (a plan left short is always compared)",
                                      unit="positioners", low=0, high=1_000_000, group="route")
    route_retract_up_to: int = setting(19, "dense groups (reach above 0.8 pitch) of at most this many positioners also try the "
                                       "direct plan and, where it leaves positioners short or late, a partial retraction of those "
                                       "alone, everyone else going straight (two legs of the planner); kept where shorter (0: never)",
                                       unit="positioners", low=0, high=1_000_000, group="route")
    route_groups: bool = setting(True, "the positioners a leg's first attempt leaves short go home together with the neighbours "
                                 "in their way, by a search in their joint angles together while everyone around them holds "
                                 "(group moves); taken where every group finds a way", group="route")
    route_partial_folds: bool = setting(True, "on a dense field (reach above 0.8 pitch), the two legs are also planned through "
                                        "folded configurations part of the way from the datum's alpha to the one half-way between "
                                        "start and target, where their bounds promise a gain; kept where shorter", group="route")
    stretch: bool = setting(False, "after planning, each positioner's move is spread over more of the makespan, along its "
                            "own path or the straight joint move, where every neighbour pair keeps the safety margin at the "
                            "samples (less energy; the same starts and ends, the makespan never later; no motor rule broken "
                            "more often than by the plan)", group="route")
