"""The ``mpc`` planner: decentralised model-predictive control with per-positioner OSQP QPs.

At every control step (``formulations/mpc.md``):

1. Conflict detection (vectorised): a pair of neighbours is *in conflict* when its clearance
   now, or between the two positioners' published plans at any horizon step, is below
   ``conflict_radius_mm``. Positioners in no conflict take the saturated step toward their
   target without a QP.
2. Every positioner in conflict solves its own QP (:mod:`fiberplan.planners.mpc_qp`) against
   the plans its neighbours published in the previous round (Jacobi style: the result does
   not depend on solve order, and the solves run in parallel,
   :mod:`fiberplan.planners.mpc_exec`). Its separation from each neighbour ``j`` at horizon
   step ``k`` is linearised around its own previous plan ``qbar_i(k)`` and ``j``'s plan
   ``qhat_j(k)``:

   .. math:: g_{ij}(\\bar q_i(k), \\hat q_j(k)) + \\nabla_{q_i} g_{ij} \\cdot (q_i(k) - \\bar q_i(k)) \\ge m_{ij} - s_{ij}

   with asymmetric margins and slack weights from priorities (the higher-priority side of a
   pair gets the small margin and the cheap slack: the other side yields).
3. Safety layer: the configuration every positioner will actually reach is checked with
   exact capsule distances, together with a bound on the clearance between the two samples;
   positioners of unsafe pairs are stopped (the lower-priority one first) until every pair is
   safe. Holding still is always safe, so this terminates.
4. Deadlocks: a positioner not at its target whose time-to-go has not decreased for
   ``deadlock_window_steps`` is deadlocked. If it and a neighbour in conflict are ordered by
   their targets (one's path crosses the other's target or position), the one that must wait
   goes to a waiting configuration until the other has arrived (:func:`waiting_configuration`).
   Otherwise it is given top priority (its neighbours fold out of its way); if it stays stuck
   for two more windows it retreats: folds, turns alpha to its target, and unfolds with top
   priority.
5. The run ends when all are at their targets, when nothing can progress any more
   (``stop_after_stalled_windows``), or at the time limit.

Before the first step (on by default for every instrument preset), every positioner gets a start delay
such that the delayed straight moves keep their margins pairwise where a delay can; a
positioner no delay fits may take an L-shaped move instead, followed as a route through its
corner, or else a timed path found by a search over its joint grid x time, followed as a route
whose waypoints it leaves no earlier than scheduled; one no timed path fits may go first, a
neighbour being placed again after it (:mod:`fiberplan.planners.mpc_schedule`). Each
positioner holds until its start.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.geometry import clearance_between, pair_clearance
from fiberplan.instrument import Instrument
from fiberplan.kinematics import fiber_positions, straight_path
from fiberplan.layout import neighbour_lists
from fiberplan.planners import ProgressCallback, instrument_defaults
from fiberplan.planners.mpc_detour import PairResolution, detour_route, pair_resolution
from fiberplan.planners.mpc_exec import QpBatch, make_executor
from fiberplan.planners.mpc_qp import (
    STATUS_ERROR,
    STATUS_INACCURATE,
    STATUS_NON_FINITE,
    STATUS_SOLVED,
    USABLE,
    OsqpOptions,
    QpLayout,
    QpWeights,
)
from fiberplan.planners.mpc_schedule import start_schedule
from fiberplan.scenario import Scenario
from fiberplan.settings import check_settings, check_step_budget, setting
from fiberplan.trajectory import PlanResult, Trajectory

QP_SOLVERS = ("osqp", "clarabel", "proxqp", "daqp", "highs", "scs", "quadprog", "cvxopt", "piqp")


@dataclass(frozen=True)
class MpcSettings:
    """Settings of the ``mpc`` planner (defaults per instrument: :meth:`for_instrument`).

    Every field is declared with :func:`fiberplan.settings.setting`: its documentation, unit,
    valid range and group (``fiberplan planners --settings mpc`` lists them).
    """

    # --- run length
    dt_s: float = setting(0.01, "control step, also the length h of each horizon step", unit="s", low=1e-3, high=1.0, group="run")
    max_duration_factor: float = setting(4.0, "the run stops after this many times the lower bound ...", low=0.0, high=100.0,
                                         low_open=True, group="run")
    max_duration_extra_s: float = setting(1.0, "... plus this long (instrument default: one turn of the slower joint)", unit="s",
                                          low=0.0, high=1e5, group="run")
    stop_after_stalled_windows: int = setting(8, "stop once nothing not at its target has progressed for this many deadlock windows "
                                              "(0: never)", unit="windows", low=0, high=1000, group="run")
    # --- the QP
    horizon_steps: int = setting(4, "H, steps in the prediction horizon", unit="steps", low=1, high=100, group="qp")
    weight_tracking: float = setting(1.0, "weight of the squared deviation from the time-optimal reference (per squared full step)",
                                     low=0.0, high=1e6, low_open=True, group="qp")
    weight_terminal: float = setting(5.0, "the same on the last horizon step", low=0.0, high=1e6, low_open=True, group="qp")
    weight_input: float = setting(0.01, "weight of the squared normalised input u / omega_max", low=0.0, high=1e6, group="qp")
    weight_input_change: float = setting(0.02, "weight of the squared change of normalised input", low=0.0, high=1e6, group="qp")
    slack_weight_linear: float = setting(200.0, "exact-penalty weight of the separation slacks", unit="1/mm", low=0.0, high=1e9,
                                         low_open=True, group="qp")
    slack_weight_quadratic: float = setting(10.0, "small quadratic slack weight", unit="1/mm^2", low=0.0, high=1e9, group="qp")
    priority_slack_ratio: float = setting(0.01, "factor on the slack weights of the higher-priority side of a pair", low=0.0,
                                          high=1.0, group="qp")
    margin_mm: float = setting(0.3, "separation the lower-priority side of a pair keeps in its QP (instrument default: 1.2 step "
                               "motions)", unit="mm", low=0.0, high=10.0, group="qp")
    priority_margin_mm: float = setting(0.1, "separation the higher-priority side keeps in its QP", unit="mm", low=0.0, high=10.0,
                                        group="qp")
    conflict_radius_mm: float = setting(1.0, "pairs closer than this, now or along the published plans, get QP constraints",
                                        unit="mm", low=0.0, high=100.0, group="qp")
    max_neighbour_constraints: int = setting(6, "neighbour slots per QP; the closest neighbours in conflict are kept", low=1,
                                             high=64, group="qp")
    max_input_change: float | None = setting(None, "bound on |u(k+1) - u(k)| / omega_max per step (null: none)", low=0.0, high=2.0,
                                             low_open=True, optional=True, group="qp", kind="float")
    # --- the safety layer
    safety_margin_mm: float = setting(0.02, "smallest clearance the safety layer lets an executed step reach", unit="mm", low=0.0,
                                      high=10.0, group="safety")
    # --- deadlocks
    deadlock_window_steps: int = setting(40, "steps without progress that mark a positioner deadlocked", unit="steps", low=1,
                                         high=100000, group="deadlocks")
    deadlock_progress_fraction: float = setting(0.0125, "progress counts when the time-to-go falls by this fraction of a window",
                                                low=0.0, high=1.0, high_open=True, group="deadlocks")
    wait_rules: bool = setting(True, "a deadlocked pair whose targets impose an order: the one that must wait goes to a waiting "
                               "configuration", group="deadlocks")
    detours: bool = setting(True, "a positioner deadlocked again gets a detour route around its neighbours before it retreats",
                            group="deadlocks")
    detour_max: int = setting(3, "detour routes planned per positioner at most", low=1, high=100, group="deadlocks")
    detour_after_deadlocks: int = setting(2, "a positioner found deadlocked this many times gets a detour", low=1, high=100,
                                          group="deadlocks")
    route_progress: bool = setting(False, "on a route (L-shaped move, timed path, detour) progress is measured along the route",
                                   group="deadlocks")
    # --- the start schedule
    start_schedule: bool = setting(False, "before the first step, give positioners start delays so that their delayed straight "
                                   "moves keep margin_mm pairwise", group="schedule")
    schedule_delay_steps: int = setting(4, "granularity of the start delays", unit="steps", low=1, high=10000, group="schedule")
    schedule_slack: float = setting(1.2, "every delayed move must end by this many times the longest move", low=1.0, high=100.0,
                                    group="schedule")
    schedule_l_paths: bool = setting(False, "a positioner no delay fits tries the two L-shaped moves (one joint, then the other)",
                                     group="schedule")
    schedule_space_time: bool = setting(False, "a positioner still unplaced searches a timed path through its joint grid x time",
                                        group="schedule")
    schedule_cell_steps: int = setting(2, "full-speed control steps per grid cell and time layer of that search", unit="steps",
                                       low=1, high=1000, group="schedule")
    schedule_repair: bool = setting(False, "a positioner no timed path fits goes first; a placed neighbour is placed again after it",
                                    group="schedule")
    # --- the solver
    executor: str = setting("sequential", "where the QPs are solved", choices=("sequential", "parallel"), group="solver")
    workers: int = setting(2, "processes of the parallel executor (the planning process counts as one)", low=1, high=256,
                           group="solver")
    qp_solver: str = setting("osqp", "osqp (persistent workspaces, the fast path) or a qpsolvers backend", choices=QP_SOLVERS,
                             group="solver")
    osqp_eps: float = setting(1e-3, "OSQP absolute and relative tolerance", low=0.0, high=1.0, low_open=True, group="solver")
    osqp_max_iter: int = setting(400, "OSQP iteration limit per solve", low=1, high=1_000_000, group="solver")

    @classmethod
    def for_instrument(cls, instrument: Instrument) -> MpcSettings:
        """Defaults scaled to an instrument's control period and per-step motion.

        The control step is the instrument's ``control_dt_s``; margins and the conflict
        radius are multiples of the largest distance any capsule point moves in one step
        (``step_motion_mm``), so slow (MOONS) and fast (DESI) motors get the same behaviour
        per step. An instrument file may override any setting in a ``[planner_defaults.mpc]``
        table (every preset turns the start schedule on). The time budget beyond ``4 x`` the
        lower bound is the DNF's, one turn of the slower joint.

        Raises:
            PlannerError: the ``[planner_defaults.mpc]`` table names an unknown setting.
        """
        dt = instrument.control_dt_s
        step_mm = _step_motion_mm(instrument, dt)
        defaults = cls(
            dt_s=dt,
            margin_mm=round(1.2 * step_mm, 4),
            priority_margin_mm=round(0.4 * step_mm, 4),
            safety_margin_mm=round(0.1 * step_mm, 4),
            conflict_radius_mm=round(4.0 * step_mm, 4),
            max_duration_extra_s=instrument.full_turn_s,
        )
        return instrument_defaults(instrument, "mpc", defaults)

    def __post_init__(self) -> None:
        check_settings(self, "mpc")
        if self.qp_solver != "osqp":
            try:
                import qpsolvers
            except ImportError as e:
                raise PlannerError(f"mpc: qp_solver {self.qp_solver!r} needs the qpsolvers package (pip install qpsolvers)") from e
            if self.qp_solver not in qpsolvers.available_solvers:
                raise PlannerError(
                    f"mpc: qp_solver {self.qp_solver!r} is not installed; qpsolvers has {', '.join(qpsolvers.available_solvers)}"
                )


def _step_motion_mm(instrument: Instrument, dt_s: float) -> float:
    """Largest distance a capsule point moves in one step at full speed (mm)."""
    return float(
        (instrument.alpha_point_extent_mm * instrument.alpha_speed_rad_s + instrument.beta_point_extent_mm * instrument.beta_speed_rad_s)
        * dt_s
    )


ROUTE_PASS = 0.5
"""A detour waypoint counts as passed within this many full steps of it (per joint)."""


def route_path(
    q: np.ndarray, route: np.ndarray, pos: int, step_rad: np.ndarray, n_steps: int, depart: np.ndarray | None = None, step: int = 0,
) -> np.ndarray:
    """Saturated path of one positioner along its detour waypoints ``route[pos:]``: ``(n_steps, 2)``.

    Each step moves every joint up to a full step toward the current waypoint and passes on to
    the next one once there, so the reference runs through the waypoints instead of stopping at
    each (a stop costs a step of deceleration per waypoint, a third of a detour's time when the
    waypoints are two steps apart). The part of a step left when a waypoint is reached mid-step
    is not carried over: the path stays on the route's segments, which are what the detour search
    checked for clearance.

    A timed route (``depart``, from the start schedule's space-time search) leaves for waypoint
    ``m`` no earlier than control step ``depart[m]``, holding where it is until then; ``step``
    is the control step of the path's first move.
    """
    out = np.empty((n_steps, 2))
    p = q.astype(float)
    last = len(route) - 1
    for k in range(n_steps):
        while pos < last and np.all(np.abs(p - route[pos]) <= ROUTE_PASS * step_rad) and (depart is None or step + k >= depart[pos + 1]):
            pos += 1
        if depart is None or step + k >= depart[pos]:
            p = p + np.clip(route[pos] - p, -step_rad, step_rad)
        out[k] = p
    return out


def _path_clearance(
    scenario: Scenario, mover: np.ndarray, other: np.ndarray, q_from: np.ndarray, q_to: np.ndarray, q_other: np.ndarray,
    step_rad: np.ndarray, stride: int = 2,
) -> np.ndarray:
    """Smallest clearance of ``mover`` along its saturated path ``q_from -> q_to`` to ``other`` held at ``q_other``.

    All arrays are row-matched (one row per directed pair); the path is sampled every ``stride``
    control steps and at its end.
    """
    if len(mover) == 0:
        return np.zeros(0)
    n_steps = int(np.ceil(np.max(np.abs(q_to - q_from) / step_rad, initial=0.0))) + 1
    path = straight_path(q_from, q_to, stride * step_rad, max(1, int(np.ceil(n_steps / stride))))  # (M, K, 2)
    k = path.shape[1]
    c = clearance_between(
        scenario.instrument,
        np.repeat(scenario.base_xy[mover], k, axis=0), np.repeat(scenario.orient[mover], k), path.reshape(-1, 2),
        np.repeat(scenario.base_xy[other], k, axis=0), np.repeat(scenario.orient[other], k), np.repeat(q_other, k, axis=0),
    ).min(axis=-1)
    return c.reshape(-1, k).min(axis=1)


def waiting_configuration(
    scenario: Scenario, first: int, waiter: int, q: np.ndarray, datum: np.ndarray, step_rad: np.ndarray, blocked_mm: float,
) -> np.ndarray | None:
    """Where ``waiter`` should wait so that its neighbour ``first`` can arrive first, or ``None``.

    Precedence from the targets: ``first`` must arrive first when its straight path from ``q``
    to its target passes closer than ``blocked_mm`` to ``waiter`` at its target. The waiting
    configuration is the first of: ``waiter``'s start, folded at its target alpha, folded at
    its current alpha, such that ``first``'s path clears it and ``waiter``'s path from it to its
    target clears ``first`` at its target. ``first``'s path blocked by where ``waiter`` is now
    also imposes the order (a face-to-face deadlock mid-way).
    """
    f, w = np.array([first]), np.array([waiter])
    target = scenario.target
    blockers = np.array([target[waiter], q[waiter]])
    f2, w2 = np.repeat(f, 2), np.repeat(w, 2)
    if np.all(_path_clearance(scenario, f2, w2, q[f2], target[f2], blockers, step_rad) >= blocked_mm):
        return None  # no precedence: first's path is free of waiter's target and of where it is
    candidates = np.array([
        scenario.start[waiter],
        [target[waiter, 0], datum[waiter, 1]],
        [q[waiter, 0], datum[waiter, 1]],
    ])
    m = len(candidates)
    ff, ww = np.repeat(f, m), np.repeat(w, m)
    ok = _path_clearance(scenario, ff, ww, np.repeat(q[f], m, axis=0), np.repeat(target[f], m, axis=0), candidates, step_rad) >= blocked_mm
    ok &= _path_clearance(scenario, ww, ff, candidates, np.repeat(target[w], m, axis=0), np.repeat(target[f], m, axis=0), step_rad) >= blocked_mm
    good = np.flatnonzero(ok)
    return candidates[good[0]] if len(good) else None


def outranks(a: np.ndarray, b: np.ndarray, rank: np.ndarray, defer_to: np.ndarray) -> np.ndarray:
    """Whether ``a`` has priority over ``b`` (row-wise): global ``rank``, except that a waiter
    ``w`` always defers to the neighbour ``defer_to[w]`` it waits for."""
    res = rank[a] < rank[b]
    res = np.where(defer_to[b] == a, True, res)
    return np.where(defer_to[a] == b, False, res)


@dataclass
class _Counters:
    qp_solves: int = 0
    qp_solved: int = 0
    qp_inaccurate: int = 0
    qp_failures: int = 0
    qp_non_finite: int = 0
    non_finite_steps: int = 0
    qp_errors: int = 0
    first_qp_error: str = ""
    workspaces: int = 0
    safety_holds: int = 0
    safety_iterations_max: int = 0
    retreats: int = 0
    waiting: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=bool))


class _SafetyLayer:
    """Stops positioners whose executed step would bring a pair too close (exact distances)."""

    def __init__(self, scenario: Scenario, floor_mm: float, subdivisions: int = 8, bisections: int = 6) -> None:
        self.inst = scenario.instrument
        self.base = scenario.base_xy
        self.orient = scenario.orient
        self.pairs = scenario.pairs
        self.floor = floor_mm
        self.subdivisions = subdivisions
        self.bisections = bisections
        self.rho = np.array([self.inst.alpha_point_extent_mm, self.inst.beta_point_extent_mm])
        # Per pair: the floor, but at most half the pair's clearance at the targets, so that
        # targets closer together than the floor stay reachable (still proven > 0 in between).
        self.half_target_clearance = 0.5 * np.maximum(self.clearance(scenario.target, self.pairs), 0.0)
        self.pair_floor = np.minimum(floor_mm, self.half_target_clearance)

    def clearance(self, joints: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """Smallest clearance over capsule combinations of each pair, all at ``joints``."""
        if len(pairs) == 0:
            return np.zeros(0)
        return pair_clearance(self.inst, self.base, self.orient, joints, pairs).clearance.min(axis=-1)

    def _between(self, pairs: np.ndarray, qi: np.ndarray, qj: np.ndarray) -> np.ndarray:
        """Clearance of row-matched pairs with ``i`` at ``qi`` and ``j`` at ``qj``."""
        i, j = pairs[:, 0], pairs[:, 1]
        return clearance_between(self.inst, self.base[i], self.orient[i], qi, self.base[j], self.orient[j], qj).min(axis=-1)

    def unsafe(self, pairs: np.ndarray, q: np.ndarray, q_next: np.ndarray, c0: np.ndarray, floor: np.ndarray) -> np.ndarray:
        """Which pairs are unsafe when moving from ``q`` to ``q_next`` (linear in joints).

        Safe: clearance at the next sample ``c1 >= f = min(floor, c0)``, and the clearance
        provably stays ``>= f / 2`` in between. Proof: over a piece of the step where the
        pair's capsule points move at most ``B`` (the verifier's motion bound
        ``M_i + M_j``), the clearance is at least ``(c_a + c_b - B) / 2`` with ``c_a, c_b``
        the clearances at the piece's ends. The whole step is tried first, then
        ``subdivisions`` equal pieces with exact clearances at their ends.
        """
        i, j = pairs[:, 0], pairs[:, 1]
        return self.unsafe_rows(pairs, q[i], q[j], q_next[i], q_next[j], c0, floor)

    def unsafe_rows(
        self, pairs: np.ndarray, qi: np.ndarray, qj: np.ndarray, qi_next: np.ndarray, qj_next: np.ndarray,
        c0: np.ndarray, floor: np.ndarray,
    ) -> np.ndarray:
        """:meth:`unsafe` with the pair's configurations given row by row (so that several
        trial steps of the same pairs are checked in one vectorised call)."""
        bound = np.abs(qi_next - qi) @ self.rho + np.abs(qj_next - qj) @ self.rho
        f = np.minimum(floor, c0)
        c1 = self._between(pairs, qi_next, qj_next)
        bad = c1 < f
        coarse = ~bad & (0.5 * (c0 + c1 - bound) < 0.5 * f)
        rows = np.flatnonzero(coarse)
        if len(rows):
            n_sub = self.subdivisions
            pr = pairs[rows]
            t = np.arange(1, n_sub) / n_sub
            qi_mid = qi[rows][None] + t[:, None, None] * (qi_next[rows] - qi[rows])[None]
            qj_mid = qj[rows][None] + t[:, None, None] * (qj_next[rows] - qj[rows])[None]
            m = len(rows)
            c_mid = self._between(np.tile(pr, (n_sub - 1, 1)), qi_mid.reshape(-1, 2), qj_mid.reshape(-1, 2)).reshape(n_sub - 1, m)
            c_all = np.vstack([c0[rows][None], c_mid, c1[rows][None]])
            lower = 0.5 * (c_all[:-1] + c_all[1:] - bound[rows] / n_sub)
            sampled_bad = np.any(c_mid < f[rows], axis=0)
            unproven = (lower < 0.5 * f[rows]) & ~sampled_bad[None, :]
            bad[rows] = sampled_bad
            if np.any(unproven):
                # Pieces the bound cannot prove: bisected (a pair in near contact can only
                # be proven to part over short pieces, since the bound assumes the closest
                # points approach at the full motion speed).
                k, r = np.nonzero(unproven)
                row = rows[r]
                t0 = k / n_sub
                proves = self._bisect_proves(
                    pairs[row], qi[row], qj[row], qi_next[row], qj_next[row], t0, 1.0 / n_sub,
                    c_all[k, r], c_all[k + 1, r], bound[row] / n_sub, f[row],
                )
                bad[np.unique(row[~proves])] = True
        return bad

    def _bisect_proves(
        self, pairs: np.ndarray, qi: np.ndarray, qj: np.ndarray, qi_next: np.ndarray, qj_next: np.ndarray,
        t0: np.ndarray, width: float, ca: np.ndarray, cb: np.ndarray, bound: np.ndarray, f: np.ndarray,
    ) -> np.ndarray:
        """Whether each piece ``[t0, t0 + width]`` of a step keeps the clearance ``>= f / 2``,
        by bisection (exact clearances at the midpoints, at most ``bisections`` levels)."""
        failed = np.zeros(len(pairs), dtype=bool)
        piece = np.arange(len(pairs))  # the original piece each open sub-piece belongs to
        for _ in range(self.bisections):
            if len(piece) == 0:
                break
            width = 0.5 * width
            tm = t0 + width
            cm = self._between(
                pairs[piece], qi[piece] + tm[:, None] * (qi_next[piece] - qi[piece]), qj[piece] + tm[:, None] * (qj_next[piece] - qj[piece]),
            )
            failed[piece[cm < 0.5 * f]] = True
            half = 0.5 * bound
            open_l = ~failed[piece] & (0.5 * (ca + cm - half) < 0.5 * f)
            open_r = ~failed[piece] & (0.5 * (cm + cb - half) < 0.5 * f)
            piece = np.concatenate([piece[open_l], piece[open_r]])
            t0 = np.concatenate([t0[open_l], tm[open_r]])
            ca, cb = np.concatenate([ca[open_l], cm[open_r]]), np.concatenate([cm[open_l], cb[open_r]])
            bound, f = np.concatenate([half[open_l], half[open_r]]), np.concatenate([f[open_l], f[open_r]])
        failed[piece] = True  # still open after the last level: not proven
        return ~failed

    def apply(
        self, q: np.ndarray, q_next: np.ndarray, c_now: np.ndarray, rank: np.ndarray, defer_to: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Return the safe next configuration, which positioners were stopped, and iterations.

        For an unsafe pair, the lower-priority mover is stopped if that makes the pair safe,
        else the higher-priority one, else both; repeated until every pair is safe (holding
        still is always safe, so this terminates).
        """
        q_next = q_next.copy()
        held = np.zeros(len(q), dtype=bool)
        pairs = self.pairs
        iterations = 0
        if len(pairs) == 0:
            return q_next, held, 0
        i_all, j_all = pairs[:, 0], pairs[:, 1]
        recheck = np.ones(len(pairs), dtype=bool)
        while True:
            motion = np.abs(q_next - q) @ self.rho
            bound = motion[i_all] + motion[j_all]
            # Only pairs with a positioner stopped in the last round can have changed (every
            # unsafe pair had one of its positioners stopped; the others were safe and are as
            # they were), so later rounds re-check those alone.
            idx = np.flatnonzero(recheck & (bound > 0) & (c_now - bound < self.pair_floor + 1e-9))
            if len(idx) == 0:
                break
            bad = self.unsafe(pairs[idx], q, q_next, c_now[idx], self.pair_floor[idx])
            if not np.any(bad):
                break
            iterations += 1
            bp = pairs[idx[bad]]
            c0b = c_now[idx[bad]]
            fb = self.pair_floor[idx[bad]]
            i, j = bp[:, 0], bp[:, 1]
            i_first = outranks(i, j, rank, defer_to)  # i has the higher priority
            hi = np.where(i_first, i, j)
            lo = np.where(i_first, j, i)
            moving = np.any(q_next != q, axis=1)
            # Two trial steps per pair, checked in one call: (a) the lower-priority one stopped,
            # (b) the higher-priority one stopped.
            q_a = q_next.copy()
            q_a[lo] = q[lo]
            q_b = q_next.copy()
            q_b[hi] = q[hi]
            pp = np.concatenate([bp, bp])
            trial_bad = self.unsafe_rows(
                pp, np.concatenate([q[i], q[i]]), np.concatenate([q[j], q[j]]),
                np.concatenate([q_a[i], q_b[i]]), np.concatenate([q_a[j], q_b[j]]),
                np.concatenate([c0b, c0b]), np.concatenate([fb, fb]),
            )
            ok_a = moving[lo] & ~trial_bad[: len(bp)]
            ok_b = moving[hi] & ~ok_a & ~trial_bad[len(bp):]
            both = ~ok_a & ~ok_b
            stop = np.unique(np.concatenate([lo[ok_a], hi[ok_b], lo[both], hi[both]]))
            stop = stop[moving[stop]]
            if len(stop) == 0:  # pragma: no cover - every unsafe pair has a mover
                raise PlannerError("mpc: safety layer found an unsafe pair with both positioners still")
            q_next[stop] = q[stop]
            held[stop] = True
            stopped_now = np.zeros(len(q), dtype=bool)
            stopped_now[stop] = True
            recheck = stopped_now[i_all] | stopped_now[j_all]
        return q_next, held, iterations


def plan_mpc(scenario: Scenario, settings: MpcSettings, progress: ProgressCallback | None = None) -> PlanResult:
    """Plan with decentralised MPC; see the module docstring and ``formulations/mpc.md``."""
    inst = scenario.instrument
    n = scenario.n_positioners
    h = settings.dt_s
    H = settings.horizon_steps
    step_rad = inst.speeds_rad_s * h
    lim = inst.limits_rad
    goal_final = scenario.target.copy()
    pairs = scenario.pairs
    n_pairs = len(pairs)
    degree = np.bincount(pairs.ravel(), minlength=n) if n_pairs else np.zeros(n, dtype=np.int64)
    n_slots = int(max(1, min(degree.max(initial=0), settings.max_neighbour_constraints)))
    rho = np.array([inst.alpha_point_extent_mm, inst.beta_point_extent_mm])
    step_mm = float(rho @ step_rad)
    datum = np.broadcast_to(np.array(inst.datum_rad), (n, 2))
    # Waiting rules activated by deadlocks: waiter -> (first, waiting configuration).
    wait_first = np.full(n, -1, dtype=np.int64)
    wait_q = np.zeros((n, 2))
    first_arrived = np.zeros(n, dtype=bool)
    leader_home_since = np.zeros(n, dtype=np.int64)
    n_rules = 0

    weights = QpWeights(
        tracking=settings.weight_tracking,
        terminal=settings.weight_terminal,
        input=settings.weight_input,
        input_change=settings.weight_input_change,
        slack_quadratic=settings.slack_weight_quadratic,
    )
    layout = QpLayout(H, n_slots, weights, settings.max_input_change)
    options = OsqpOptions(eps_abs=settings.osqp_eps, eps_rel=settings.osqp_eps, max_iter=settings.osqp_max_iter)
    safety = _SafetyLayer(scenario, settings.safety_margin_mm)
    # A pair whose targets are closer than the margins could never both arrive: its QP
    # margins are capped at half its clearance at the targets.
    margin_cap = safety.half_target_clearance

    move = np.max(np.abs(goal_final - scenario.start) / inst.speeds_rad_s, axis=1)
    bound_s = float(move[scenario.has_target].max()) if np.any(scenario.has_target) else 0.0
    limit_s = settings.max_duration_factor * bound_s + settings.max_duration_extra_s
    max_steps = int(np.ceil(limit_s / h))
    check_step_budget("mpc", max_steps, h, limit_s)
    window = settings.deadlock_window_steps
    # Start schedule (mpc_schedule): each positioner's reference starts after its delay.
    schedule_t0 = time.perf_counter()
    schedule = start_schedule(scenario, step_rad, settings.margin_mm, settings.schedule_delay_steps, settings.schedule_slack,
                              l_paths=settings.schedule_l_paths, space_time=settings.schedule_space_time,
                              cell_steps=settings.schedule_cell_steps, repair=settings.schedule_repair) if settings.start_schedule else None
    schedule_wall_s = time.perf_counter() - schedule_t0
    start_step = schedule.delay_steps if schedule is not None else np.zeros(n, dtype=np.int64)

    q = scenario.start.copy()
    goal = goal_final.copy()
    goal_prev = goal
    c_now = safety.clearance(q, pairs)
    plan = straight_path(q, np.where((start_step > 0)[:, None], q, goal), step_rad, H)  # published plans (what neighbours see)
    own_plan = plan.copy()  # linearisation points of each positioner's own QP
    v_prev = np.zeros((n, 2))
    history = [q.copy()]
    counters = _Counters(waiting=np.zeros(n, dtype=bool))
    solve_times: list[np.ndarray] = []
    iter_counts: list[np.ndarray] = []
    qp_per_step: list[int] = []

    # Deadlock state.
    best_ttg = move.copy()
    last_progress = np.zeros(n, dtype=np.int64)
    level = np.zeros(n, dtype=np.int64)  # 0 normal, 1 top priority, 2 retreating
    level_since = np.zeros(n, dtype=np.int64)
    ever_deadlocked = np.zeros(n, dtype=bool)
    first_dead = np.zeros(n, dtype=np.int64)
    ever_yielded = np.zeros(n, dtype=bool)
    yield_until = np.zeros(n, dtype=np.int64)
    yield_to = np.zeros(n, dtype=np.int64)
    waiting = np.zeros(n, dtype=bool)
    stopped_stalled = False
    best_ever = move.copy()  # best time-to-go ever (not reset by retreats)
    last_best_ever = np.zeros(n, dtype=np.int64)
    progress_eps = settings.deadlock_progress_fraction * window * h
    # Detour routes: positioner -> waypoints, and the index of the waypoint it heads for.
    n_dead = np.zeros(n, dtype=np.int64)
    routes: dict[int, np.ndarray] = {}
    route_pos: dict[int, int] = {}
    route_depart: dict[int, np.ndarray] = {}  # timed routes (space-time schedule): departure step per waypoint
    route_tail: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # route -> time from each waypoint on to the goal
    n_routes = np.zeros(n, dtype=np.int64)
    n_detour_failed = 0
    n_pair_resolutions = 0
    grids: dict = {}  # joint-space grids of the positioners that needed a detour (mpc_detour)
    after_wait: dict[int, np.ndarray] = {}  # a waiter's route from its waiting place, once released
    neighbours, neighbour_rows = neighbour_lists(pairs, n) if settings.detours else ([], [])
    if schedule is not None:
        # L-shaped scheduled moves follow their corner as a route (from their start on).
        for who in np.flatnonzero(~np.isnan(schedule.corner[:, 0])).tolist():
            routes[who] = np.array([schedule.corner[who], goal_final[who]])
            route_pos[who] = 0
            if start_step[who] == 0:
                plan[who] = own_plan[who] = route_path(q[who], routes[who], 0, step_rad, H)
        # Timed paths leave each waypoint no earlier than scheduled.
        for who, (waypoints, depart) in schedule.timed.items():
            routes[who], route_depart[who] = waypoints, depart
            route_pos[who] = 0
            if start_step[who] == 0:
                plan[who] = own_plan[who] = route_path(q[who], waypoints, 0, step_rad, H, depart, 0)
        if settings.route_progress:
            best_ttg[list(routes)] = np.inf  # measured along their routes

    executor = make_executor(settings.executor, layout, options, settings.qp_solver, settings.workers)
    try:
        for step in range(max_steps):
            at_goal_final = np.all(q == goal_final, axis=1)
            if np.all(at_goal_final):
                break
            # Nothing left can progress: no positioner not at its target has come closer than it
            # ever was for stop_after_stalled_windows windows (a retreat cycle included), waiters
            # included unless the neighbour they wait for is still on its way. Planning on would
            # only burn time.
            if settings.stop_after_stalled_windows and np.all(
                at_goal_final | (step - last_best_ever >= settings.stop_after_stalled_windows * window)
            ):
                stopped_stalled = True
                break
            ttg_final = np.max(np.abs(goal_final - q) / inst.speeds_rad_s, axis=1)
            better = ttg_final < best_ever - progress_eps
            best_ever = np.where(better, ttg_final, best_ever)
            # A waiter counts as progressing while the neighbour it waits for is on its way.
            first = np.maximum(wait_first, 0)
            first_moving = ~at_goal_final[first] & (step - last_best_ever[first] < settings.stop_after_stalled_windows * window)
            unstarted = step < start_step  # waiting for its scheduled start
            # Holding: unstarted, or at a waypoint of a timed route until its next departure.
            holding = unstarted.copy()
            for who, depart in route_depart.items():
                pos = route_pos[who]
                if pos + 1 < len(depart) and step < depart[pos + 1] and np.all(np.abs(q[who] - routes[who][pos]) <= ROUTE_PASS * step_rad):
                    holding[who] = True
            last_best_ever = np.where(better | (waiting & first_moving) | holding, step, last_best_ever)

            # --- conflict detection (depends only on the configuration and the published plans).
            # Two positioners holding still at their goals need no QP: nothing changes.
            resting = np.all(q == goal_prev, axis=1) & np.all(plan == q[:, None, :], axis=(1, 2))
            near = c_now < settings.conflict_radius_mm + 2 * H * step_mm
            cand = np.flatnonzero(near & ~(resting[pairs[:, 0]] & resting[pairs[:, 1]])) if n_pairs else np.zeros(0, dtype=np.int64)
            sel = cand
            if len(cand):
                pred = pair_clearance(inst, scenario.base_xy, scenario.orient, np.swapaxes(plan, 0, 1), pairs[cand])
                c_min = np.minimum(c_now[cand], pred.clearance.min(axis=(0, 2)))
                sel = cand[c_min < settings.conflict_radius_mm]

            # --- deadlock detection and resolution (deterministic).
            # Stalled: the best time-to-go has not improved for a window. On a route it is the
            # time along the route (an L-shaped move's first leg need not bring the slower joint
            # closer to its target).
            ttg_progress = ttg_final
            if settings.route_progress:
                ttg_progress = ttg_final.copy()  # ttg_final itself is used below
                for who, route in routes.items():
                    if route_tail.get(who, (None,))[0] is not route:  # a new route: its legs' times once
                        legs = np.max(np.abs(np.diff(np.vstack([route, goal_final[who]]), axis=0)) / inst.speeds_rad_s, axis=1)
                        route_tail[who] = (route, np.append(np.cumsum(legs[::-1])[::-1], 0.0))
                    pos = route_pos[who]
                    ttg_progress[who] = np.max(np.abs(route[pos] - q[who]) / inst.speeds_rad_s) + route_tail[who][1][pos]
            improved = ttg_progress < best_ttg - progress_eps
            best_ttg = np.where(improved, ttg_progress, best_ttg)
            last_progress = np.where(improved | at_goal_final | waiting | holding, step, last_progress)
            best_ttg = np.where(waiting, ttg_progress, best_ttg)
            stalled = (step - last_progress >= window) & ~at_goal_final
            new_dead = stalled & (level == 0)
            first_dead[new_dead & ~ever_deadlocked] = step
            ever_deadlocked |= new_dead
            level[new_dead] = 1
            level_since[new_dead] = step
            if settings.wait_rules and np.any(new_dead) and n_pairs:
                # A deadlocked pair whose targets impose an order: the one that must wait goes
                # to a waiting configuration, the other keeps top priority.
                hit = new_dead[pairs[:, 0]] | new_dead[pairs[:, 1]]
                for r in np.flatnonzero(hit & (c_now < settings.conflict_radius_mm)):
                    a, b = int(pairs[r, 0]), int(pairs[r, 1])
                    for leader, waiter in ((a, b), (b, a)):
                        if wait_first[leader] >= 0 or wait_first[waiter] >= 0 or at_goal_final[leader]:
                            continue
                        wq = waiting_configuration(scenario, leader, waiter, q, datum, step_rad, settings.margin_mm)
                        if wq is not None:
                            wait_first[waiter] = leader
                            wait_q[waiter] = wq
                            level[waiter] = 0
                            level[leader] = 1
                            level_since[leader] = step
                            n_rules += 1
                            break
            # Still stuck with top priority for two more windows: retreat sub-goals, i.e. fold
            # the beta arm (level 2), turn alpha to the target while folded (level 3), then
            # unfold with top priority again (level 1).
            escalate = (level == 1) & stalled & (step - level_since >= 2 * window)
            if settings.detours:
                # Deadlocked a second time (pairs that push each other off their targets in
                # turn), or still stuck two windows after: a waiting place for one of the pair
                # that lets the other through, else a detour route (_resolve_blocked), before
                # any retreat.
                n_dead[new_dead] += 1
                want = (new_dead & (n_dead >= settings.detour_after_deadlocks) & (level == 1)) | escalate
                want &= (n_routes < settings.detour_max) & ((wait_first < 0) | first_arrived)
                for b in np.flatnonzero(want).tolist():
                    if wait_first[b] >= 0 and not first_arrived[b]:
                        continue  # made a waiter earlier in this loop
                    n_routes[b] += 1
                    resolution = _resolve_blocked(scenario, settings, b, q, goal_final, neighbours, c_now[neighbour_rows[b]], wait_first,
                                                  first_arrived, step_rad, grids)
                    if isinstance(resolution, PairResolution):
                        f, w = resolution.first, resolution.waiter
                        routed = [(f, resolution.first_route), (w, resolution.to_wait)]
                        wait_first[w] = f
                        wait_q[w] = resolution.wait_q
                        first_arrived[w] = False
                        after_wait[w] = resolution.from_wait
                        level[w] = 0
                        escalate[w] = False
                        n_pair_resolutions += 1
                    elif resolution is not None:
                        routed = [(b, resolution)]
                    else:
                        n_detour_failed += 1
                        continue
                    for k, (who, route) in enumerate(routed):
                        routes[who] = route
                        route_pos[who] = 0
                        route_depart.pop(who, None)
                        if k == 0:
                            escalate[who] = False
                            level[who] = 1
                            level_since[who] = step
                            last_progress[who] = step
                            # Measured along the new route from the next step.
                            best_ttg[who] = np.inf if settings.route_progress else ttg_final[who]
            level[escalate] = 2
            level_since[escalate] = step
            counters.retreats += int(escalate.sum())
            tol = 1e-9
            folded = np.abs(q[:, 1] - datum[:, 1]) <= tol
            turned = folded & (np.abs(q[:, 0] - goal_final[:, 0]) <= tol)
            timeout = (level >= 2) & (step - level_since >= 4 * window)
            to3 = (level == 2) & folded
            level[to3] = 3
            back = ((level == 3) & turned) | timeout
            level[back] = 1
            level_since[back] = step
            last_progress[back] = step
            best_ttg[back] = ttg_final[back]
            level[(level > 0) & at_goal_final] = 0
            for who in list(routes):
                if level[who] >= 2:
                    del routes[who], route_pos[who]
                    route_depart.pop(who, None)
                elif who in route_depart and route_pos[who] + 1 < len(routes[who]) and step < route_depart[who][route_pos[who] + 1]:
                    continue  # its next departure is later
                elif np.all(np.abs(q[who] - routes[who][route_pos[who]]) <= ROUTE_PASS * step_rad):
                    # A waypoint passed (within half a step: the QP rounds the corners of the
                    # reference, which runs through the waypoints) counts as progress.
                    route_pos[who] += 1
                    last_progress[who] = last_best_ever[who] = step
                    if route_pos[who] == len(routes[who]):
                        del routes[who], route_pos[who]
                        route_depart.pop(who, None)

            # Priorities: deadlocked positioners first, in the order they were first found
            # deadlocked (sticky, so two of them never swap roles); then the longest time-to-go.
            boosted = level >= 1
            order = np.lexsort((np.arange(n), -ttg_final, np.where(boosted, first_dead, 0), ~boosted))
            rank = np.empty(n, dtype=np.int64)
            rank[order] = np.arange(n)

            # Retreat sub-goals: a lower-priority neighbour in conflict with a deadlocked
            # positioner folds its beta arm until the conflict is over.
            # It keeps yielding for a window after the last conflict (hysteresis), as long as
            # a deadlocked positioner remains.
            if len(sel):
                ci, cj = pairs[sel, 0], pairs[sel, 1]
                i_first = outranks(ci, cj, rank, wait_first)
                hi = np.where(i_first, ci, cj)
                lo = np.where(i_first, cj, ci)
                pushing = level[hi] == 1
                yield_until[lo[pushing]] = step + window
                yield_to[lo[pushing]] = hi[pushing]
            yielding = (yield_until > step) & ~boosted & (level[yield_to] == 1)
            fold = yielding | (level == 2)
            ever_yielded |= yielding
            goal = goal_final.copy()
            goal[holding] = q[holding]
            # Folding (yielders and level-2 retreats) moves beta to the datum with alpha held.
            # Letting alpha head for its target meanwhile measured no better on DESI (N = 500
            # failures, seeds 0-11 / 36-47: 17 / 16 held, 16 / 19 not) and worse on MOONS
            # (N = 61 random, seeds 0-4: 69 % reached held, 63 % not).
            goal[fold, 0] = q[fold, 0]
            # Waiting rules, in two phases: the waiter goes to its waiting configuration and stays
            # there until its neighbour has arrived, then moves to its target still deferring to
            # that neighbour; the rule ends when it arrives.
            has_rule = wait_first >= 0
            # Released once the neighbour has arrived and the waiter is at its waiting place;
            # a waiter of a pair resolution also when it has not got there within a window of
            # the neighbour's arrival (blocked on its way by a third positioner).
            leader_home = has_rule & at_goal_final[np.maximum(wait_first, 0)]
            leader_home_since = np.where(leader_home, leader_home_since, step)
            release = np.all(q == wait_q, axis=1)
            # A waiter still on its way to its waiting place when its neighbour arrives goes
            # straight to its target if that path clears the neighbour there (the detour via
            # the waiting place only served to let the neighbour through).
            early = np.flatnonzero(leader_home & ~release & ~first_arrived)
            if len(early):
                ahead = wait_first[early]
                clear = _path_clearance(scenario, early, ahead, q[early], goal_final[early], goal_final[ahead], step_rad)
                release[early[clear >= settings.margin_mm]] = True
            if after_wait:
                late = np.zeros(n, dtype=bool)
                late[list(after_wait)] = True
                release |= late & (step - leader_home_since >= window)
            first_arrived |= leader_home & release
            for w in [w for w in after_wait if first_arrived[w]]:
                route = after_wait.pop(w)
                route_depart.pop(w, None)
                if np.all(q[w] == wait_q[w]):  # else the route does not start where it is
                    routes[w] = route
                    route_pos[w] = 0
                    if settings.route_progress:
                        best_ttg[w] = np.inf  # measured along the route from the next step
                else:
                    routes.pop(w, None)
                    route_pos.pop(w, None)
            ended = has_rule & at_goal_final
            wait_first[ended] = -1
            first_arrived[ended] = False
            waiting = (wait_first >= 0) & ~first_arrived
            goal[waiting] = wait_q[waiting]
            counters.waiting |= waiting
            goal[fold, 1] = datum[fold, 1]
            for who in routes:
                if not holding[who]:
                    goal[who] = routes[who][route_pos[who]]
            goal[level == 3, 1] = datum[level == 3, 1]

            goal_prev = goal
            ref = straight_path(q, goal, step_rad, H)
            for who in routes:
                # (A timed route holding at a waypoint follows its route: it shows the
                # departure ahead.)
                if not unstarted[who]:
                    ref[who] = route_path(q[who], routes[who], route_pos[who], step_rad, H, route_depart.get(who), step)
            q_next = ref[:, 0].copy()
            new_plan = ref.copy()
            n_qp = 0
            if len(cand):
                if len(sel):
                    batch = _build_batch(
                        scenario, settings, layout, pairs[sel], margin_cap[sel], q, own_plan, plan, ref, v_prev, rank, wait_first, boosted,
                        step_rad, lim,
                    )
                    result = executor.solve(batch)
                    idx = batch.index
                    n_qp = len(idx)
                    counters.qp_solves += n_qp
                    counters.qp_solved += int(np.sum(result.status == STATUS_SOLVED))
                    counters.qp_inaccurate += int(np.sum(result.status == STATUS_INACCURATE))
                    counters.qp_failures += int(np.sum(~np.isin(result.status, USABLE)))
                    counters.qp_non_finite += int(np.sum(result.status == STATUS_NON_FINITE))
                    counters.qp_errors += int(np.sum(result.status == STATUS_ERROR))
                    counters.first_qp_error = counters.first_qp_error or result.first_error
                    counters.workspaces += result.new_workspaces
                    solve_times.append(result.solve_s)
                    iter_counts.append(result.iterations)
                    ok = np.isin(result.status, USABLE)
                    qplan = q[idx, None, :] + result.z * step_rad
                    qplan = np.clip(qplan, lim[:, 0], lim[:, 1])
                    # Executed first step: within the speed bound and the hard stops.
                    first = q[idx] + np.clip(qplan[:, 0] - q[idx], -step_rad, step_rad)
                    first = np.clip(first, lim[:, 0], lim[:, 1])
                    # Failed solves brake: the positioner holds and publishes a hold plan.
                    first = np.where(ok[:, None], first, q[idx])
                    qplan = np.where(ok[:, None, None], qplan, q[idx, None, :])
                    q_next[idx] = first
                    new_plan[idx] = qplan
            qp_per_step.append(n_qp)

            # Snap onto the goal when within a small fraction of a step of it.
            near = np.all(np.abs(goal - q_next) <= 0.05 * step_rad, axis=1) & np.all(np.abs(goal - q) <= step_rad, axis=1)
            q_next[near] = goal[near]

            # A non-finite step (none is known to arise: every QP solution is checked) holds.
            bad_step = ~np.isfinite(q_next).all(axis=1)
            if bad_step.any():
                q_next[bad_step] = q[bad_step]
                counters.non_finite_steps += int(bad_step.sum())
            # --- safety layer: exact distances of what will actually be executed.
            q_next, held, iters = safety.apply(q, q_next, c_now, rank, wait_first)
            counters.safety_holds += int(held.sum())
            counters.safety_iterations_max = max(counters.safety_iterations_max, iters)

            # --- publish plans for the next round (shifted by one step).
            tail = new_plan[:, -1] + np.clip(goal - new_plan[:, -1], -step_rad, step_rad)
            shifted = np.concatenate([new_plan[:, 1:], tail[:, None]], axis=1)
            # A stopped positioner publishes its intention one step late, but linearises its
            # own next QP around where it actually is (holding).
            plan = np.where(held[:, None, None], new_plan, shifted)
            own_plan = np.where(held[:, None, None], q_next[:, None, :], shifted)
            v_prev = (q_next - q) / step_rad
            # Clearances change only for pairs with a moving positioner.
            moved = np.any(q_next != q, axis=1)
            if n_pairs:
                changed = np.flatnonzero(moved[pairs[:, 0]] | moved[pairs[:, 1]])
                c_now[changed] = safety.clearance(q_next, pairs[changed])
            q = q_next
            history.append(q.copy())
            if progress is not None and step % 20 == 0:
                progress(min(1.0, step / max_steps))
    finally:
        executor.close()
    if progress is not None:
        progress(1.0)

    joints = np.stack(history)
    times = np.arange(len(joints)) * h
    final_xy = fiber_positions(inst, scenario.base_xy, scenario.orient, joints[-1])
    reached = np.linalg.norm(final_xy - scenario.target_xy, axis=1) <= inst.tolerance_mm
    reached |= ~scenario.has_target & np.all(joints[-1] == scenario.start, axis=1)
    outcome = np.where(reached, "reached", "deadlocked")
    all_times = np.concatenate(solve_times) if solve_times else np.zeros(0)
    all_iters = np.concatenate(iter_counts) if iter_counts else np.zeros(0)
    n_steps = len(joints) - 1
    stats = {
        "n_steps": n_steps,
        "qp_solves": counters.qp_solves,
        "qp_solved": counters.qp_solved,
        "qp_inaccurate": counters.qp_inaccurate,
        "qp_failures": counters.qp_failures,
        "qp_non_finite": counters.qp_non_finite,
        "qp_errors": counters.qp_errors,
        "non_finite_steps_held": counters.non_finite_steps,
        "qp_workspaces": counters.workspaces,
        "qp_fraction": counters.qp_solves / max(1, n * n_steps),
        # Per QP: OSQP's update + solve (the vectors are assembled for the whole batch before).
        "qp_solve_ms_median": float(np.median(all_times) * 1e3) if len(all_times) else 0.0,
        "qp_solve_ms_p95": float(np.percentile(all_times, 95) * 1e3) if len(all_times) else 0.0,
        "qp_iterations_median": float(np.median(all_iters)) if len(all_iters) else 0.0,
        "qp_max_per_step": int(max(qp_per_step, default=0)),
        "safety_holds": counters.safety_holds,
        "safety_iterations_max": counters.safety_iterations_max,
        "deadlocks_detected": int(ever_deadlocked.sum()),
        "deadlocks_resolved": int(np.sum(ever_deadlocked & reached)),
        "deadlocks_remaining": int(np.sum(~reached & scenario.has_target)),
        "retreats": counters.retreats,
        "yielding_positioners": int(ever_yielded.sum()),
        "waiting_rules": n_rules,
        "waiting_positioners": int(counters.waiting.sum()),
        "detours": int(n_routes.sum()) - n_detour_failed - n_pair_resolutions,
        "pair_resolutions": n_pair_resolutions,
        "detours_not_found": n_detour_failed,
        "n_slots": n_slots,
        "stopped_stalled": stopped_stalled,
        "schedule_delayed": int(np.count_nonzero(start_step)),
        "schedule_unplaced": len(schedule.unplaced) if schedule is not None else 0,
        "schedule_l_paths": int(np.count_nonzero(~np.isnan(schedule.corner[:, 0]))) if schedule is not None else 0,
        "schedule_timed": len(schedule.timed) if schedule is not None else 0,
        "schedule_swaps": schedule.swaps if schedule is not None else 0,
        "schedule_wall_s": schedule_wall_s,
    }
    warnings = _run_warnings(scenario, reached, stopped_stalled, times[-1], counters)
    return PlanResult(
        scenario=scenario,
        trajectory=Trajectory(times, joints),
        outcome=outcome,
        planner="mpc",
        settings=dataclasses.asdict(settings),
        stats=stats,
        warnings=warnings,
    )


def _run_warnings(scenario: Scenario, reached: np.ndarray, stopped_stalled: bool, end_s: float, counters: _Counters) -> tuple[str, ...]:
    """What the run gave up on, in words (the command line prints them)."""
    out = []
    short = int(np.sum(scenario.has_target & ~reached))
    if short:
        why = "nothing could progress any more" if stopped_stalled else "the time limit was reached"
        out.append(f"mpc: {short} of {int(scenario.has_target.sum())} positioners did not reach their targets; "
                   f"the run stopped at t = {end_s:.2f} s because {why}")
    if counters.qp_non_finite or counters.qp_errors or counters.non_finite_steps:
        first = f" (first error: {counters.first_qp_error})" if counters.first_qp_error else ""
        out.append(f"mpc: {counters.qp_non_finite} QP solve(s) returned a non-finite solution and {counters.qp_errors} raised{first}; "
                   "each such positioner held for that step")
    return tuple(out)


def _resolve_blocked(
    scenario: Scenario, settings: MpcSettings, i: int, q: np.ndarray, goal: np.ndarray, neighbours: list[np.ndarray],
    c_nb: np.ndarray, wait_first: np.ndarray, released: np.ndarray, step_rad: np.ndarray, grids: dict,
) -> PairResolution | np.ndarray | None:
    """A way out for the deadlocked positioner ``i`` (``mpc_detour``), or ``None``.

    First a pair resolution with its closest neighbour in conflict (``i`` first, else the
    neighbour first): the waiter gets a way home around the first at its target, where a lone
    detour could end on a target that blocks the neighbour (the pair would then push each other
    off their targets in turn). Else a lone detour route around the neighbours held where they
    are. Neighbours waiting for someone (not yet released) or waited for are left alone.
    ``c_nb`` are the clearances to ``neighbours[i]`` now (the loop's ``c_now``).
    """
    nb = neighbours[i]
    leaders = set(wait_first[wait_first >= 0].tolist())
    for k in np.argsort(c_nb, kind="stable"):
        j = int(nb[k])
        if c_nb[k] >= settings.conflict_radius_mm or (wait_first[j] >= 0 and not released[j]) or j in leaders:
            continue
        for f, w in ((i, j), (j, i)):
            resolution = pair_resolution(scenario, f, w, q, goal, neighbours, step_rad, settings.margin_mm, settings.safety_margin_mm,
                                         cache=grids)
            if resolution is not None:
                return resolution
        break  # the closest one only
    return detour_route(scenario, i, q[i], goal[i], nb, q[nb], step_rad, settings.margin_mm, settings.safety_margin_mm, cache=grids)


def _build_batch(
    scenario: Scenario,
    settings: MpcSettings,
    layout: QpLayout,
    cp: np.ndarray,
    cap_mm: np.ndarray,
    q: np.ndarray,
    own_plan: np.ndarray,
    plan: np.ndarray,
    ref: np.ndarray,
    v_prev: np.ndarray,
    rank: np.ndarray,
    defer_to: np.ndarray,
    boosted: np.ndarray,
    step_rad: np.ndarray,
    lim: np.ndarray,
) -> QpBatch:
    """Linearise the separation of every conflicting pair along the plans; stack per-positioner QP data."""
    inst = scenario.instrument
    H, S = layout.horizon_steps, layout.n_slots
    i, j = cp[:, 0], cp[:, 1]
    owner = np.concatenate([i, j])
    nbr = np.concatenate([j, i])
    n_d = len(owner)
    # Virtual positioners: row r = (directed pair d, step k): the owner at its own plan
    # (index r), the neighbour at its published plan (index R + r).
    R = n_d * H
    oo = np.repeat(owner, H)
    nn = np.repeat(nbr, H)
    kk = np.tile(np.arange(H), n_d)
    base = np.concatenate([scenario.base_xy[oo], scenario.base_xy[nn]])
    orient = np.concatenate([scenario.orient[oo], scenario.orient[nn]])
    joints = np.concatenate([own_plan[oo, kk], plan[nn, kk]])
    virt = np.stack([np.arange(R), R + np.arange(R)], axis=1)
    pc = pair_clearance(inst, base, orient, joints, virt, gradient=True)
    if pc.grad_i is None:  # pragma: no cover - asked for above
        raise PlannerError("mpc: clearance gradients missing")
    best = pc.clearance.argmin(axis=1)
    rows = np.arange(R)
    g2 = pc.clearance[rows, best].reshape(n_d, H)
    grad = pc.grad_i[rows, best].reshape(n_d, H, 2)
    higher = outranks(owner, nbr, rank, defer_to)
    cap2 = np.concatenate([cap_mm, cap_mm])
    margin = np.minimum(np.where(higher, settings.priority_margin_mm, settings.margin_mm), cap2)
    # A deadlocked positioner (boosted) plans straight through lower-priority neighbours,
    # which see its plan and yield; the safety layer keeps the executed steps apart.
    ratio = np.where(boosted[owner], 0.01 * settings.priority_slack_ratio, settings.priority_slack_ratio)
    slack_w = settings.slack_weight_linear * np.where(higher, ratio, 1.0)
    lin_point = own_plan[owner]  # (D, H, 2)
    rhs = margin[:, None] - g2 + np.einsum("dkc,dkc->dk", grad, lin_point - q[owner][:, None, :])
    coef = grad * step_rad

    order = np.lexsort((nbr, g2.min(axis=1), owner))
    owner, rhs, coef, slack_w = owner[order], rhs[order], coef[order], slack_w[order]
    index, first, counts = np.unique(owner, return_index=True, return_counts=True)
    local = np.repeat(np.arange(len(index)), counts)
    slot = np.arange(len(owner)) - np.repeat(first, counts)
    keep = slot < S  # the S most critical neighbours of each positioner
    owner, rhs, coef, slack_w, local, slot = owner[keep], rhs[keep], coef[keep], slack_w[keep], local[keep], slot[keep]
    m = len(index)
    coef_b = np.zeros((m, S, H, 2))
    rhs_b = np.zeros((m, S, H))
    active_b = np.zeros((m, S), dtype=bool)
    slack_b = np.full((m, S), settings.slack_weight_linear)
    coef_b[local, slot] = coef
    rhs_b[local, slot] = rhs
    active_b[local, slot] = True
    slack_b[local, slot] = slack_w
    qi = q[index]
    return QpBatch(
        index=index,
        z_ref=(ref[index] - qi[:, None, :]) / step_rad,
        z_lo=(lim[:, 0] - qi) / step_rad,
        z_hi=(lim[:, 1] - qi) / step_rad,
        v_prev=v_prev[index],
        coef=coef_b,
        rhs=rhs_b,
        active=active_b,
        slack_linear=slack_b,
    )
