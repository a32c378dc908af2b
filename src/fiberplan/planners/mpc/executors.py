"""Executors of the ``mpc`` planner's per-positioner QPs: sequential, or over worker processes.

Every positioner owns one persistent QP workspace, created the first time it needs a QP and
then updated and warm-started at every later step. The parallel executor gives each process
a fixed block of positioners (``index % n_blocks``) and their workspaces for the whole run;
the planner process itself owns block 0. Because each workspace sees exactly the same
sequence of updates in both executors, and OSQP is deterministic, both executors produce
bit-identical trajectories.

A large run (``fresh_after`` given) starts a positioner's workspace afresh when it has not
solved for more than ``fresh_after`` steps, and frees such idle workspaces every
``fresh_after`` steps: memory then follows the positioners in conflict, not the field. The
rule depends only on each positioner's own steps, so both executors stay bit-identical.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.planners.mpc.qp import (
    STATUS_ERROR,
    USABLE,
    OsqpOptions,
    PositionerQP,
    QpData,
    QpLayout,
    SetupTemplate,
    cap_bounds,
    checked,
    solve_with_qpsolvers,
)


@dataclass
class QpBatch(QpData):
    """QP data of ``m`` positioners for one control step: the fields of
    :class:`~fiberplan.planners.mpc.qp.QpData` with a leading ``m`` axis, and ``index``, the
    positioner rows."""

    index: np.ndarray

    def take(self, rows: np.ndarray) -> QpBatch:
        """The sub-batch of the given rows."""
        return QpBatch(**{f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)})

    def data(self, r: int) -> QpData:
        """The :class:`QpData` of row ``r``."""
        return QpData(**{f.name: getattr(self, f.name)[r] for f in dataclasses.fields(QpData)})


@dataclass
class QpBatchResult:
    """Solutions of a batch: status (``qp.STATUS_*``), plans (NaN unless usable), timings,
    and the first backend exception seen (``type: message``), if any."""

    status: np.ndarray
    z: np.ndarray
    iterations: np.ndarray
    solve_s: np.ndarray
    new_workspaces: int
    first_error: str = ""


class _Block:
    """The QP workspaces of one block of positioners (lives in one process)."""

    def __init__(self, layout: QpLayout, options: OsqpOptions, qp_solver: str, fresh_after: int | None = None) -> None:
        self.layout = layout
        self.options = options
        self.qp_solver = qp_solver
        self.workspaces: dict[int, PositionerQP] = {}
        self.fresh_after = fresh_after
        self.last_step: dict[int, int] = {}  # the step each workspace last solved at (with fresh_after)
        self._template: SetupTemplate | None = None  # made with the first workspace

    def solve(self, batch: QpBatch, step: int = 0) -> QpBatchResult:
        m = len(batch.index)
        H = self.layout.horizon_steps
        status = np.zeros(m, dtype=np.int64)
        z = np.full((m, H, 2), np.nan)
        iterations = np.zeros(m, dtype=np.int64)
        solve_s = np.zeros(m)
        created = 0
        first_error = ""
        osqp = self.qp_solver == "osqp"
        if osqp and m:  # the whole batch's vectors in a few numpy operations
            q, lo, hi, ax = self.layout.assemble_batch(
                batch.z_ref, batch.z_lo, batch.z_hi, batch.v_prev, batch.coef, batch.rhs, batch.active, batch.slack_linear
            )
            cap_bounds(lo, hi)
        for r in range(m):
            t0 = time.perf_counter()
            # A backend that raises fails this one solve: the positioner holds, the plan goes on.
            try:
                if osqp:
                    key = int(batch.index[r])
                    workspace = self.workspaces.get(key)
                    if self.fresh_after is not None:
                        if workspace is not None and step - self.last_step[key] > self.fresh_after:
                            workspace = None  # idle too long: a fresh workspace, as if it had been freed
                        self.last_step[key] = step
                    if workspace is None:
                        if self._template is None:
                            self._template = SetupTemplate(self.layout, self.options)
                        workspace = self._template.new()
                        self.workspaces[key] = workspace
                        created += 1
                    t0 = time.perf_counter()
                    st, x, it = checked(*workspace.solve_capped(q[r], lo[r], hi[r], ax[r]))
                else:
                    st, x, it = checked(*solve_with_qpsolvers(self.layout, batch.data(r), self.qp_solver))
            except Exception as e:  # any backend failure is one failed solve
                st, x, it = STATUS_ERROR, None, 0
                first_error = first_error or f"{type(e).__name__}: {e}"
            dt = time.perf_counter() - t0
            status[r], iterations[r], solve_s[r] = st, it, dt
            if x is not None and st in USABLE:
                z[r] = self.layout.split(x)[0]
        if self.fresh_after is not None and step % self.fresh_after == 0:
            for key in [k for k, last in self.last_step.items() if step - last > self.fresh_after]:
                del self.workspaces[key], self.last_step[key]
        return QpBatchResult(status, z, iterations, solve_s, created, first_error)


def _merge(parts: list[tuple[np.ndarray, QpBatchResult]], m: int, H: int) -> QpBatchResult:
    out = QpBatchResult(
        status=np.zeros(m, dtype=np.int64),
        z=np.full((m, H, 2), np.nan),
        iterations=np.zeros(m, dtype=np.int64),
        solve_s=np.zeros(m),
        new_workspaces=0,
    )
    for rows, res in parts:
        out.first_error = out.first_error or res.first_error
        out.status[rows] = res.status
        out.z[rows] = res.z
        out.iterations[rows] = res.iterations
        out.solve_s[rows] = res.solve_s
        out.new_workspaces += res.new_workspaces
    return out


class SequentialExecutor:
    """Solves every QP in the planner's process."""

    def __init__(self, layout: QpLayout, options: OsqpOptions, qp_solver: str, fresh_after: int | None = None) -> None:
        self._block = _Block(layout, options, qp_solver, fresh_after)

    def solve(self, batch: QpBatch, step: int = 0) -> QpBatchResult:
        """Solve a batch, positioner by positioner."""
        return self._block.solve(batch, step)

    def close(self) -> None:
        """Nothing to release."""


def _worker(conn: Connection, layout: QpLayout, options: OsqpOptions, qp_solver: str, fresh_after: int | None) -> None:
    block = _Block(layout, options, qp_solver, fresh_after)
    while True:
        message = conn.recv()
        if message is None:
            break
        conn.send(block.solve(*message))
    conn.close()


class ParallelExecutor:
    """Persistent worker processes, each owning the workspaces of one block of positioners.

    Block ``b`` holds the positioners with ``index % n_blocks == b``; block 0 is solved in
    the planner's process, blocks 1.. in ``n_blocks - 1`` forked worker processes that live
    for the whole planning run. Per step, each worker receives its positioners' QP data
    through a pipe and sends back their plans.
    """

    def __init__(self, layout: QpLayout, options: OsqpOptions, qp_solver: str, workers: int, fresh_after: int | None = None) -> None:
        if workers < 1:
            raise PlannerError(f"mpc: workers must be >= 1, found {workers}")
        self.n_blocks = int(workers)
        self._layout = layout
        self._local = _Block(layout, options, qp_solver, fresh_after)
        self._conns: list[Connection] = []
        self._procs: list[Any] = []
        try:
            ctx = mp.get_context("fork")
        except ValueError as e:
            raise PlannerError("mpc: the parallel executor needs the 'fork' start method (Linux, macOS)") from e
        for _ in range(self.n_blocks - 1):
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(child, layout, options, qp_solver, fresh_after), daemon=True)
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)

    def solve(self, batch: QpBatch, step: int = 0) -> QpBatchResult:
        """Send each block its QPs, solve block 0 here, gather the results in batch order."""
        m = len(batch.index)
        owner = batch.index % self.n_blocks
        sent: list[tuple[np.ndarray, int]] = []
        for b in range(1, self.n_blocks):
            rows = np.flatnonzero(owner == b)
            if len(rows):
                self._conns[b - 1].send((batch.take(rows), step))
                sent.append((rows, b))
        rows0 = np.flatnonzero(owner == 0)
        parts = [(rows0, self._local.solve(batch.take(rows0), step))]
        for rows, b in sent:
            parts.append((rows, self._conns[b - 1].recv()))
        return _merge(parts, m, self._layout.horizon_steps)

    def close(self) -> None:
        """Stop the worker processes."""
        for conn in self._conns:
            try:
                conn.send(None)
                conn.close()
            except (BrokenPipeError, OSError):
                pass
        deadline = time.monotonic() + 5.0
        for proc in self._procs:
            proc.join(timeout=max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                proc.terminate()
        self._conns, self._procs = [], []


def make_executor(
    kind: str, layout: QpLayout, options: OsqpOptions, qp_solver: str, workers: int, fresh_after: int | None = None,
) -> SequentialExecutor | ParallelExecutor:
    """Build the executor named by the ``executor`` setting (``fresh_after``: see the module docstring)."""
    if kind == "sequential":
        return SequentialExecutor(layout, options, qp_solver, fresh_after)
    if kind == "parallel":
        return ParallelExecutor(layout, options, qp_solver, workers, fresh_after)
    raise PlannerError(f"mpc: executor must be 'sequential' or 'parallel', found {kind!r}")
