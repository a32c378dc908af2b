"""The ``mpc`` planner: decentralised model-predictive control, one OSQP QP per positioner in conflict.

One concept per module (``formulations/mpc.md`` names them):

==============  ============================================================================
``loop``        :func:`plan_mpc`, the receding-horizon loop
``settings``    :class:`MpcSettings`: every setting with its unit, range, group and doc
``conflicts``   which pairs are in conflict; the linearised collision rows of the QPs
``qp``          the per-positioner QP: its fixed sparsity pattern, one OSQP workspace each
``executors``   where the QPs are solved: in this process, or in persistent workers
``priority``    who yields to whom
``deadlock``    detection and the escalation ladder (:class:`~.deadlock.Level`)
``waiting``     waiting places of the waiting rules
``routes``      routes a positioner follows instead of its straight move
``grid``        one positioner's joint grid, shared by detours and timed paths
``detour``      detours and pair resolutions for deadlocked positioners
``schedule``    the start schedule (:class:`~.schedule.StartScheduler`)
``stats``       the run's counters
==============  ============================================================================

The safety layer is shared with the other planners: :mod:`fiberplan.planners.safety`.
"""

from fiberplan.planners.mpc.loop import plan_mpc
from fiberplan.planners.mpc.settings import QP_SOLVERS, MpcSettings

__all__ = ["QP_SOLVERS", "MpcSettings", "plan_mpc"]
