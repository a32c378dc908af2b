"""Run statistics of the ``mpc`` planner: what the QPs, the safety layer and the deadlock rules did."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fiberplan.planners.mpc.executors import QpBatchResult
from fiberplan.planners.mpc.qp import STATUS_ERROR, STATUS_INACCURATE, STATUS_NON_FINITE, STATUS_SOLVED, USABLE


@dataclass
class RunStats:
    """Counters of one run, filled by the loop; :meth:`qp_dict` gives the QP part of ``PlanResult.stats``."""

    qp_solves: int = 0
    qp_screened: int = 0
    qp_solved: int = 0
    qp_inaccurate: int = 0
    qp_failures: int = 0
    qp_non_finite: int = 0
    qp_errors: int = 0
    first_qp_error: str = ""
    workspaces: int = 0
    safety_holds: int = 0
    safety_iterations_max: int = 0
    non_finite_steps: int = 0
    solve_times: list[np.ndarray] = field(default_factory=list)
    iter_counts: list[np.ndarray] = field(default_factory=list)
    qp_per_step: list[int] = field(default_factory=list)

    def record_qps(self, result: QpBatchResult) -> None:
        """Count one step's batch of QP solves."""
        status = result.status
        self.qp_solves += len(status)
        self.qp_solved += int(np.sum(status == STATUS_SOLVED))
        self.qp_inaccurate += int(np.sum(status == STATUS_INACCURATE))
        self.qp_failures += int(np.sum(~np.isin(status, USABLE)))
        self.qp_non_finite += int(np.sum(status == STATUS_NON_FINITE))
        self.qp_errors += int(np.sum(status == STATUS_ERROR))
        self.first_qp_error = self.first_qp_error or result.first_error
        self.workspaces += result.new_workspaces
        self.solve_times.append(result.solve_s)
        self.iter_counts.append(result.iterations)

    def qp_dict(self, n: int, n_steps: int) -> dict[str, float | int]:
        """The QP and safety-layer statistics of the run."""
        times = np.concatenate(self.solve_times) if self.solve_times else np.zeros(0)
        iters = np.concatenate(self.iter_counts) if self.iter_counts else np.zeros(0)
        return {
            "n_steps": n_steps,
            "qp_solves": self.qp_solves,
            "qp_screened": self.qp_screened,
            "qp_solved": self.qp_solved,
            "qp_inaccurate": self.qp_inaccurate,
            "qp_failures": self.qp_failures,
            "qp_non_finite": self.qp_non_finite,
            "qp_errors": self.qp_errors,
            "non_finite_steps_held": self.non_finite_steps,
            "qp_workspaces": self.workspaces,
            "qp_fraction": self.qp_solves / max(1, n * n_steps),
            # Per QP: OSQP's update + solve (the vectors are assembled for the whole batch before).
            "qp_solve_ms_median": float(np.median(times) * 1e3) if len(times) else 0.0,
            "qp_solve_ms_p95": float(np.percentile(times, 95) * 1e3) if len(times) else 0.0,
            "qp_iterations_median": float(np.median(iters)) if len(iters) else 0.0,
            "qp_max_per_step": int(max(self.qp_per_step, default=0)),
            "safety_holds": self.safety_holds,
            "safety_iterations_max": self.safety_iterations_max,
        }

    def warnings(self) -> list[str]:
        """The QP faults of the run, in words."""
        if not (self.qp_non_finite or self.qp_errors or self.non_finite_steps):
            return []
        first = f" (first error: {self.first_qp_error})" if self.first_qp_error else ""
        return [f"mpc: {self.qp_non_finite} QP solve(s) returned a non-finite solution and {self.qp_errors} raised{first}; "
                "each such positioner held for that step"]
