"""Names of the registered planners and where each lives (no imports: anyone may read it).

``fiberplan.planners`` loads a planner from here when it is first used; the instrument file
reader checks ``[planner_defaults.<name>]`` tables against these names.
"""

from __future__ import annotations

PLANNERS: dict[str, tuple[str, str, str]] = {
    # name: (module, planning function, settings dataclass)
    "straight": ("fiberplan.planners.straight", "plan_straight", "StraightSettings"),
    "mpc": ("fiberplan.planners.mpc", "plan_mpc", "MpcSettings"),
    "dnf": ("fiberplan.planners.dnf", "plan_dnf", "DnfSettings"),
    "central": ("fiberplan.planners.central", "plan_central", "CentralSettings"),
    "prioritized": ("fiberplan.planners.prioritized", "plan_prioritized", "PrioritizedSettings"),
}


def planner_names() -> list[str]:
    """Names of the registered planners."""
    return sorted(PLANNERS)
