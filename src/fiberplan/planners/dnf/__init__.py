"""The ``dnf`` planner: decentralized navigation functions (references 000 and 002).

``loop`` holds :func:`plan_dnf`, ``settings`` :class:`DnfSettings`, ``potential`` the potential
and its gradients (with reference 000's convergence condition and reference 002's ellipse
distance), ``escape`` the deadlock bookkeeping. The safety layer is shared:
:mod:`fiberplan.planners.safety`. The method: ``formulations/dnf.md``.
"""

from fiberplan.planners.dnf.loop import plan_dnf
from fiberplan.planners.dnf.potential import (
    ConvergenceCheck,
    convergence_bound,
    convergence_condition,
    ellipse_arm_distance,
    repulsion_potential,
    repulsion_slope,
)
from fiberplan.planners.dnf.settings import DnfSettings

__all__ = [
    "ConvergenceCheck",
    "DnfSettings",
    "convergence_bound",
    "convergence_condition",
    "ellipse_arm_distance",
    "plan_dnf",
    "repulsion_potential",
    "repulsion_slope",
]
