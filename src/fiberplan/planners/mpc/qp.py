"""The per-positioner quadratic program of the ``mpc`` planner (``formulations/mpc.md``).

One positioner, horizon ``H`` steps of length ``h``, in scaled units: joint motion is
counted in *steps at full speed*, ``z(k) = (q(k) - q(0)) / (omega h)`` (dimensionless), and
the normalised input is ``v(k) = u(k) / omega`` in ``[-1, 1]``. Decision vector::

    x = [ z(1) .. z(H)  (2H) | v(0) .. v(H-1)  (2H) | s_1(1) .. s_S(H)  (S H) ]

with one slack ``s_m(k) >= 0`` (mm) per neighbour slot ``m`` and horizon step ``k``
(``S H`` slacks). The problem

.. math::

    \\min_x \\; \\sum_{k=1}^{H-1} w_t \\|z(k) - \\hat z(k)\\|^2 + w_f \\|z(H) - \\hat z(H)\\|^2
        + w_u \\sum_{k=0}^{H-1} \\|v(k)\\|^2 + w_{\\Delta} \\sum_{k=0}^{H-1} \\|v(k) - v(k-1)\\|^2
        + \\sum_{m,k} (\\lambda_m s_m(k) + \\mu s_m(k)^2)

    \\text{s.t.}\\; z(k) = z(k-1) + v(k-1),\\; z(0) = 0;\\quad -1 \\le v \\le 1;\\quad
    z_{lo} \\le z(k) \\le z_{hi};\\quad |v(k) - v(k-1)| \\le \\delta \\;(\\text{optional});

    c_m(k) \\cdot z(k) + s_m(k) \\ge r_m(k) \\;(\\text{active slots});\\quad s \\ge 0

is assembled once per positioner with a fixed sparsity pattern (:class:`QpLayout`); each
control step only the vectors ``q, l, u`` and the collision coefficients in ``A`` change
(:meth:`QpLayout.assemble`). :class:`PositionerQP` holds one persistent OSQP workspace and
warm-starts it; :func:`solve_with_qpsolvers` routes the same matrices through qpsolvers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from fiberplan.errors import PlannerError

STATUS_SOLVED = 1
STATUS_INACCURATE = 2
STATUS_FAILED = 0
STATUS_NON_FINITE = 3
"""The backend reported a solution with a NaN or inf entry (treated as a failure)."""
STATUS_ERROR = 4
"""The backend raised an exception (treated as a failure; the plan goes on)."""
USABLE = (STATUS_SOLVED, STATUS_INACCURATE)
"""Statuses whose solution is executed."""

_INF = np.inf


@dataclass(frozen=True)
class QpWeights:
    """Cost weights of the per-positioner QP (scaled units, see the module docstring).

    Attributes:
        tracking: ``w_t``, per squared step of deviation from the reference.
        terminal: ``w_f``, on the last horizon step.
        input: ``w_u``, on the squared normalised input.
        input_change: ``w_Delta``, on the squared change of normalised input.
        slack_quadratic: ``mu``, quadratic slack weight (per mm^2); the linear weights
            ``lambda_m`` are given per slot at every step.
    """

    tracking: float
    terminal: float
    input: float
    input_change: float
    slack_quadratic: float


@dataclass
class QpData:
    """Per-step data of one positioner's QP.

    Attributes:
        z_ref: ``(H, 2)`` reference (steps from the current joints).
        z_lo, z_hi: ``(2,)`` joint hard stops in steps from the current joints.
        v_prev: ``(2,)`` normalised input applied at the previous step.
        coef: ``(S, H, 2)`` collision row coefficients ``c_m(k)`` (mm per step).
        rhs: ``(S, H)`` collision row lower bounds ``r_m(k)`` (mm).
        active: ``(S,)`` which slots hold a neighbour.
        slack_linear: ``(S,)`` linear slack weights ``lambda_m``.
    """

    z_ref: np.ndarray
    z_lo: np.ndarray
    z_hi: np.ndarray
    v_prev: np.ndarray
    coef: np.ndarray
    rhs: np.ndarray
    active: np.ndarray
    slack_linear: np.ndarray


class QpLayout:
    """Fixed sparsity pattern and index maps of the QP for ``H`` steps and ``S`` neighbour slots.

    Rows of ``A``, in order: dynamics (2H, equalities), joint stops on ``z`` (2H), input
    bounds on ``v`` (2H), optional input-change bounds (2H), slack signs (S H), collision rows
    (S H, row ``(m, k)`` at ``collision_row0 + m H + k - 1``).
    """

    def __init__(self, horizon_steps: int, n_slots: int, weights: QpWeights, max_input_change: float | None) -> None:
        if horizon_steps < 1:
            raise PlannerError(f"mpc: horizon_steps must be >= 1, found {horizon_steps}")
        H, S = int(horizon_steps), int(max(n_slots, 1))
        self.horizon_steps, self.n_slots = H, S
        self.weights = weights
        self.max_input_change = max_input_change
        self.iz = np.arange(2 * H).reshape(H, 2)
        self.iv = 2 * H + np.arange(2 * H).reshape(H, 2)
        self.isl = 4 * H + np.arange(S * H).reshape(S, H)
        self.n_var = 4 * H + S * H

        # --- cost: 0.5 x' P x + q' x, P constant.
        w = weights
        diag = np.zeros(self.n_var)
        diag[self.iz[:-1].ravel()] = 2 * w.tracking
        diag[self.iz[-1]] = 2 * w.terminal
        n_change = np.full(H, 2.0)  # v(k) appears in the change terms k and k+1 ...
        n_change[-1] = 1.0  # ... except the last
        diag[self.iv] = 2 * (w.input + w.input_change * n_change)[:, None]
        diag[self.isl] = 2 * w.slack_quadratic
        rows, cols, vals = list(range(self.n_var)), list(range(self.n_var)), diag.tolist()
        for k in range(1, H):
            for d in range(2):
                rows.append(int(self.iv[k - 1, d]))
                cols.append(int(self.iv[k, d]))
                vals.append(-2 * w.input_change)
        self.P = sp.csc_matrix((vals, (rows, cols)), shape=(self.n_var, self.n_var))
        self.P_upper = sp.triu(self.P, format="csc")  # what OSQP takes; shared by every workspace

        # --- constraints.
        entries: list[tuple[int, int, float]] = []
        row = 0
        for k in range(H):  # z(k+1) - z(k) - v(k) = 0
            for d in range(2):
                entries.append((row, int(self.iz[k, d]), 1.0))
                if k > 0:
                    entries.append((row, int(self.iz[k - 1, d]), -1.0))
                entries.append((row, int(self.iv[k, d]), -1.0))
                row += 1
        self.row_dyn = np.arange(0, 2 * H)
        self.row_z = np.arange(row, row + 2 * H).reshape(H, 2)
        for k in range(H):
            for d in range(2):
                entries.append((row, int(self.iz[k, d]), 1.0))
                row += 1
        self.row_v = np.arange(row, row + 2 * H).reshape(H, 2)
        for k in range(H):
            for d in range(2):
                entries.append((row, int(self.iv[k, d]), 1.0))
                row += 1
        self.row_dv: np.ndarray | None = None
        if max_input_change is not None:
            self.row_dv = np.arange(row, row + 2 * H).reshape(H, 2)
            for k in range(H):
                for d in range(2):
                    entries.append((row, int(self.iv[k, d]), 1.0))
                    if k > 0:
                        entries.append((row, int(self.iv[k - 1, d]), -1.0))
                    row += 1
        self.row_s = np.arange(row, row + S * H)
        for m in range(S):
            for k in range(H):
                entries.append((row, int(self.isl[m, k]), 1.0))
                row += 1
        self.collision_row0 = row
        for m in range(S):
            for k in range(H):
                entries.append((row, int(self.iz[k, 0]), 1.0))
                entries.append((row, int(self.iz[k, 1]), 1.0))
                entries.append((row, int(self.isl[m, k]), 1.0))
                row += 1
        self.n_con = row
        r_idx = np.array([e[0] for e in entries])
        c_idx = np.array([e[1] for e in entries])
        v_all = np.array([e[2] for e in entries])
        A = sp.csc_matrix((v_all, (r_idx, c_idx)), shape=(self.n_con, self.n_var))
        A.sort_indices()
        self.A = A
        # Where each collision coefficient lives in A.data: (S, H, 2).
        self.ax_collision = np.empty((S, H, 2), dtype=np.int64)
        for m in range(S):
            for k in range(H):
                r = self.collision_row0 + m * H + k
                for d in range(2):
                    col = int(self.iz[k, d])
                    start, stop = A.indptr[col], A.indptr[col + 1]
                    pos = start + int(np.flatnonzero(A.indices[start:stop] == r)[0])
                    self.ax_collision[m, k, d] = pos
        self.A_data0 = A.data.copy()
        self.A_data0[self.ax_collision.ravel()] = 0.0
        self.A.data[:] = self.A_data0
        self.row_collision = self.collision_row0 + np.arange(S * H).reshape(S, H)

        lo = np.full(self.n_con, -_INF)
        hi = np.full(self.n_con, _INF)
        lo[self.row_dyn] = hi[self.row_dyn] = 0.0
        lo[self.row_v] = -1.0
        hi[self.row_v] = 1.0
        if self.row_dv is not None and max_input_change is not None:
            lo[self.row_dv] = -max_input_change
            hi[self.row_dv] = max_input_change
        lo[self.row_s] = 0.0
        self.l0, self.u0 = lo, hi

    def assemble(self, data: QpData) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Vectors ``q, l, u`` and the data array of ``A`` for one step (a few numpy operations)."""
        one = self.assemble_batch(
            data.z_ref[None], data.z_lo[None], data.z_hi[None], data.v_prev[None],
            data.coef[None], data.rhs[None], data.active[None], data.slack_linear[None],
        )
        q, lo, hi, ax = (a[0] for a in one)
        return q, lo, hi, ax

    def assemble_batch(
        self, z_ref: np.ndarray, z_lo: np.ndarray, z_hi: np.ndarray, v_prev: np.ndarray,
        coef: np.ndarray, rhs: np.ndarray, active: np.ndarray, slack_linear: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`assemble` for ``m`` positioners at once: the :class:`QpData` fields with a
        leading ``m`` axis in, ``(m, n_var)``, ``(m, n_con)`` twice and ``(m, nnz)`` out."""
        w = self.weights
        m = len(z_ref)
        q = np.zeros((m, self.n_var))
        q[:, self.iz[:-1]] = -2 * w.tracking * z_ref[:, :-1]
        q[:, self.iz[-1]] = -2 * w.terminal * z_ref[:, -1]
        q[:, self.iv[0]] = -2 * w.input_change * v_prev
        q[:, self.isl] = slack_linear[:, :, None]
        lo = np.tile(self.l0, (m, 1))
        hi = np.tile(self.u0, (m, 1))
        lo[:, self.row_z] = z_lo[:, None, :]
        hi[:, self.row_z] = z_hi[:, None, :]
        if self.row_dv is not None:
            lo[:, self.row_dv[0]] += v_prev
            hi[:, self.row_dv[0]] += v_prev
        lo[:, self.row_collision] = np.where(active[:, :, None], rhs, -_INF)
        ax = np.tile(self.A_data0, (m, 1))
        ax[:, self.ax_collision] = np.where(active[:, :, None, None], coef, 0.0)
        return q, lo, hi, ax

    def dense(self, data: QpData) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The full problem ``(P, q, A, l, u)`` as dense arrays (``P`` symmetric)."""
        q, lo, hi, ax = self.assemble(data)
        A = self.A.copy()
        A.data = ax
        P = self.P.toarray()
        P = P + np.triu(P, 1).T
        return P, q, A.toarray(), lo, hi

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Split a decision vector into ``z (H, 2)``, ``v (H, 2)`` and slacks ``(S, H)``."""
        return x[self.iz], x[self.iv], x[self.isl]


def reference_keeps_constraints(
    layout: QpLayout, z_ref: np.ndarray, z_lo: np.ndarray, z_hi: np.ndarray, v_prev: np.ndarray, coef: np.ndarray,
    rhs: np.ndarray, active: np.ndarray, clearance_mm: float = 0.0, tol: float = 1e-9,
) -> np.ndarray:
    """Which of ``m`` positioners' references keep every constraint of their QP with zero slack
    (the :class:`QpData` fields with a leading ``m`` axis in, ``(m,)`` booleans out).

    The reference ``z_ref`` read as the plan ``z``: its inputs ``v(k-1) = z(k) - z(k-1)``
    (``z(0) = 0``) within ``[-1, 1]`` and, with ``max_input_change``, their changes (from
    ``v_prev``) within it; ``z`` within the hard stops; every active collision row
    ``c_m(k) . z(k) >= r_m(k) + clearance_mm``. Such a QP's constraints leave its optimum where its cost puts
    it: on the reference but for the small input terms. ``tol`` absorbs the rounding of
    ``z_ref`` (steps of exactly one full step)."""
    v = np.diff(z_ref, axis=1, prepend=np.zeros_like(z_ref[:, :1]))
    ok = np.all(np.abs(v) <= 1.0 + tol, axis=(1, 2))
    ok &= np.all((z_ref >= z_lo[:, None, :] - tol) & (z_ref <= z_hi[:, None, :] + tol), axis=(1, 2))
    if layout.max_input_change is not None:
        dv = np.diff(v, axis=1, prepend=v_prev[:, None, :])
        ok &= np.all(np.abs(dv) <= layout.max_input_change + tol, axis=(1, 2))
    lhs = np.einsum("mshc,mhc->msh", coef, z_ref)
    ok &= np.all((lhs >= rhs + clearance_mm) | ~active[:, :, None], axis=(1, 2))
    return ok


@dataclass(frozen=True)
class OsqpOptions:
    """OSQP settings used by every workspace."""

    eps_abs: float = 1e-3
    eps_rel: float = 1e-3
    max_iter: int = 400
    check_termination: int = 10


_OSQP_INFTY = 1e30  # osqp's OSQP_INFTY (builtin algebra); checked against the library in PositionerQP


class SetupTemplate:
    """What every workspace of one layout is set up from, converted for OSQP once.

    ``osqp.OSQP.setup`` checks and converts its matrices (a lower-triangle test of ``P``, CSC
    copies, dtype casts) and builds a settings object on every call: about as long as the C
    set-up itself for these small QPs, and the same for every workspace of a layout. Here the
    public set-up runs once (the first workspace), and later workspaces are built by the same
    extension constructor it calls, from the same converted inputs (OSQP copies its matrices and
    settings into each workspace, so sharing them is safe; tested: the same solutions, bit for
    bit). ``usable`` is false if a future osqp release changes these internals; workspaces are
    then set up through the public interface.
    """

    def __init__(self, layout: QpLayout, options: OsqpOptions) -> None:
        self.layout, self.options = layout, options
        first = PositionerQP(layout, options)
        solver = first._solver
        ext = getattr(solver, "ext", None)
        self.usable = first._ext is not None and all(hasattr(ext, a) for a in ("OSQPSolver", "CSC")) and hasattr(solver, "settings")
        self.first: PositionerQP | None = first  # handed to the first caller of ``new``
        if self.usable:
            dtype = np.float64 if ext.OSQP_USE_FLOAT != 1 else np.float32
            P, q, A, lo, hi = _setup_inputs(layout)
            # As ``osqp.OSQP._infer_mnpqalu`` and ``setup`` convert them (P is upper-triangular, both CSC, sorted).
            self._args = (
                ext.CSC(P.astype(dtype)), q.astype(dtype), ext.CSC(A.astype(dtype)),
                np.maximum(lo, -_OSQP_INFTY).astype(dtype), hi.astype(dtype),
                A.shape[0], A.shape[1], solver.settings,
            )
            self._ext_module = ext

    def new(self) -> PositionerQP:
        """A workspace set up from the template (the first call returns the one built to make it)."""
        if self.first is not None:
            first, self.first = self.first, None
            return first
        if not self.usable:
            return PositionerQP(self.layout, self.options)
        workspace = PositionerQP.__new__(PositionerQP)
        workspace.layout = self.layout
        workspace._solver = None
        workspace._ext = self._ext_module.OSQPSolver(*self._args)
        workspace._infty = _OSQP_INFTY
        return workspace


def _setup_inputs(layout: QpLayout) -> tuple:
    """The set-up problem of every workspace: ``P`` (upper triangle), ``q = 0``, ``A`` with its
    collision coefficients zero, and the bounds ``l0``, ``u0`` (capped at OSQP's infinity)."""
    return layout.P_upper, np.zeros(layout.n_var), layout.A.copy(), layout.l0, np.minimum(layout.u0, _OSQP_INFTY)


class PositionerQP:
    """One positioner's persistent OSQP workspace: set up once, then ``update`` + warm start."""

    def __init__(self, layout: QpLayout, options: OsqpOptions) -> None:
        import osqp

        self.layout = layout
        # The builtin algebra named explicitly: the same linear algebra on every machine (results
        # reproducible), and OSQP() skips probing for the optional MKL/CUDA backends (0.2 ms each).
        self._solver = osqp.OSQP(algebra="builtin")
        P, q, A, lo, hi = _setup_inputs(layout)
        self._solver.setup(
            P,
            q,
            A,
            lo,
            hi,
            verbose=False,
            polishing=False,
            warm_starting=True,
            eps_abs=options.eps_abs,
            eps_rel=options.eps_rel,
            max_iter=options.max_iter,
            check_termination=options.check_termination,
            eps_prim_inf=1e-6,
            eps_dual_inf=1e-6,
        )

        # The extension-level solver: the same calls ``osqp.OSQP.update`` / ``solve`` make, without
        # their per-call Python bookkeeping (derivative caches, info namespaces, constant
        # look-ups), which cost as much as the solve itself for these small QPs. Falls back to
        # the public interface if a future osqp release changes it.
        ext = getattr(self._solver, "_solver", None)
        self._ext = ext if all(hasattr(ext, a) for a in ("update_data_vec", "update_data_mat", "solve", "info", "solution")) else None
        self._infty = float(self._solver.constant("OSQP_INFTY"))
        if self._infty != _OSQP_INFTY:
            self._ext = None  # not the library this was written for: the public interface throughout

    def solve(self, data: QpData) -> tuple[int, np.ndarray | None, int]:
        """Update the workspace and solve; returns ``(status, x or None, iterations)``."""
        return self.solve_assembled(*self.layout.assemble(data))

    def solve_assembled(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, ax: np.ndarray) -> tuple[int, np.ndarray | None, int]:
        """:meth:`solve` with the step's vectors already assembled (:meth:`QpLayout.assemble_batch`)."""
        if self._ext is None:
            self._solver.update(q=q, l=lo, u=hi, Ax=ax)
            res = self._solver.solve(raise_error=False)
            status_val, x, iters = int(res.info.status_val), res.x, int(res.info.iter)
            if status_val in (STATUS_SOLVED, STATUS_INACCURATE) and x is not None:
                return checked(status_val, np.asarray(x), iters)
            return STATUS_FAILED, None, iters
        return checked(*self.solve_capped(q, np.maximum(lo, -self._infty), np.minimum(hi, self._infty), ax))

    def solve_capped(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, ax: np.ndarray) -> tuple[int, np.ndarray | None, int]:
        """:meth:`solve_assembled` with the bounds already within OSQP's infinity (``cap_bounds``):
        the per-solve path of the executors. The answer's entries are *not* checked here: the
        caller passes it through :func:`checked` (the executors do, for every backend), so that
        each solution is checked once."""
        ext = self._ext
        if ext is None:
            return self.solve_assembled(q, lo, hi, ax)
        ext.update_data_vec(q=q, l=lo, u=hi)
        ext.update_data_mat(P_x=None, P_i=None, A_x=ax, A_i=None)
        ext.solve()
        info = ext.info
        status_val, iters = int(info.status_val), int(info.iter)
        if status_val not in (STATUS_SOLVED, STATUS_INACCURATE):
            return STATUS_FAILED, None, iters
        return status_val, np.array(ext.solution.x), iters


def cap_bounds(lo: np.ndarray, hi: np.ndarray) -> None:
    """Bounds of a batch capped at OSQP's infinity in place, as ``osqp.OSQP.update`` caps them."""
    np.maximum(lo, -_OSQP_INFTY, out=lo)
    np.minimum(hi, _OSQP_INFTY, out=hi)


def checked(status: int, x: np.ndarray | None, iterations: int) -> tuple[int, np.ndarray | None, int]:
    """A backend's answer with every entry checked: a non-finite solution is a failure, whatever
    status the backend gave (``STATUS_NON_FINITE``, no solution)."""
    if status in USABLE and (x is None or not np.isfinite(x).all()):
        return STATUS_NON_FINITE, None, iterations
    return status, x, iterations


def solve_with_qpsolvers(layout: QpLayout, data: QpData, solver: str) -> tuple[int, np.ndarray | None, int]:
    """Solve the same QP with a qpsolvers backend (no persistent workspace).

    Rows with equal bounds become equalities, the others one-sided inequalities ``G x <= h``.
    """
    import qpsolvers

    P, q, A, lo, hi = layout.dense(data)
    eq = lo == hi
    up = ~eq & np.isfinite(hi)
    dn = ~eq & np.isfinite(lo)
    G = np.vstack([A[up], -A[dn]])
    h = np.concatenate([hi[up], -lo[dn]])
    x = qpsolvers.solve_qp(sp.csc_matrix(P), q, sp.csc_matrix(G), h, sp.csc_matrix(A[eq]), lo[eq], solver=solver)
    if x is None:
        return STATUS_FAILED, None, 0
    return checked(STATUS_SOLVED, np.asarray(x), 0)

