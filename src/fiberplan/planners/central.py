"""The ``central`` planner: one CasADi/IPOPT nonlinear program over a whole small group.

A *reference*, not a planner for thousands (``formulations/central.md``): it measures how
far the decentralised planners (``mpc``, ``dnf``) are from a centralised optimum, as
reference 004, section 7.5 does for the DNF. CasADi is imported by this module only.

Decision variables: the joint angles ``q[k]`` of every positioner at ``T + 1`` knots, the
scaled final time ``tau = t_f / t_LB`` (``t_LB`` the lower bound of ``metrics``), and one
separating line ``(n, c)`` per constrained capsule combination and interval. Velocities are
``u[k] = (q[k+1] - q[k]) / h`` with ``h = t_f / T`` (eliminated, so the dynamics and speed
bounds are linear in ``(q, t_f)``):

.. math::

    \\min\\; \\tau + w_E \\frac{E}{E_{ref}} \\quad (\\text{mode "time"}), \\qquad
    \\min\\; \\frac{E}{E_{ref}},\\; t_f \\text{ fixed} \\quad (\\text{mode "energy"}),
    \\qquad E = \\sum_k \\frac{\\|q[k+1] - q[k]\\|^2}{h}

    \\text{s.t.}\\; |q_{ij}[k+1] - q_{ij}[k]| \\le \\omega_j h, \\; q[k] \\in [q_{lo}, q_{hi}],
    \\; q[0] = q_{start},\\; q[T] = q_{target},

    n_\\ell \\cdot x - c_\\ell \\ge r_A + m/2 + \\delta_x(h) \\;\\; (x \\text{ an end point of } A \\text{ at } k, k+1),
    \\quad c_\\ell - n_\\ell \\cdot y \\ge r_B + m/2 + \\delta_y(h), \\quad \\|n_\\ell\\|^2 \\le 1,

where ``delta`` bounds how far a capsule end point strays from its chord between two knots
(so the linear joint motion between knots is covered, not only the knots). Lines are added
lazily: only for (pair, combination, interval) triples that come within ``activate_mm`` of
contact along the current guess; after every solve the triples the solution brings close
are added and the problem is solved again (``lazy_rounds``).

The planner returns the best converged candidate of several warm starts; it never checks
itself. :func:`central_reference` runs the independent verifier on the candidates (best
first) and returns the first verified one, marking the result ``failed`` if none passes.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from fiberplan.errors import PlannerError, SettingsError
from fiberplan.geometry import pair_clearance, segment_distance
from fiberplan.instrument import Instrument
from fiberplan.kinematics import move_times
from fiberplan.outcomes import outcome_labels
from fiberplan.planners import ProgressCallback
from fiberplan.scenario import Scenario
from fiberplan.settings import check_settings, setting
from fiberplan.trajectory import PlanResult, Trajectory

CentralMode = Literal["time", "energy"]

_IPOPT_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
_STRAIGHT = "straight"
"""Warm start name: every joint moves at constant speed from start to target (synchronised)."""
_SEQUENTIAL = "sequential"
"""Warm start name: positioners move straight at full speed one after another, longest first."""
_BUILTIN_STARTS = (_STRAIGHT, _SEQUENTIAL)


@dataclass(frozen=True)
class CentralSettings:
    """Settings of the ``central`` planner (defaults per instrument: :meth:`for_instrument`).

    Every field is declared with :func:`fiberplan.settings.setting` (doc, unit, valid range,
    group). ``warm_start`` names the starts to solve from: ``"straight"`` (constant-speed joint
    interpolation over ``straight_stretch`` lower bounds), ``"sequential"`` (one positioner
    after another, longest move first) or a registered planner (its trajectory, resampled);
    the best converged candidate is kept. In ``"time"`` mode the objective is ``t_f / t_LB +
    energy_weight E / E_ref``; in ``"energy"`` mode ``E / E_ref`` at a fixed makespan.
    """

    mode: CentralMode = setting("time", "minimise the makespan (time) or the energy at a fixed makespan", choices=("time", "energy"),
                                group="problem")
    steps: int = setting(40, "T, number of intervals of the discretised motion", low=2, high=2000, group="problem")
    energy_weight: float = setting(0.01, "w_E, weight of E / E_ref against t_f / t_LB in time mode", low=0.0, high=1e6, group="problem")
    makespan_s: float | None = setting(None, "energy mode: the fixed final time (null: makespan_factor lower bounds)", unit="s",
                                       low=0.0, high=1e5, low_open=True, optional=True, group="problem", kind="float")
    makespan_factor: float = setting(1.5, "energy mode default final time, in lower bounds", low=0.0, high=100.0, low_open=True,
                                     group="problem")
    warm_start: tuple[str, ...] = setting((_STRAIGHT, _SEQUENTIAL), "starts to solve from: straight, sequential or planner names",
                                          group="problem", kind="list")
    straight_stretch: float = setting(1.2, "duration of the straight warm start, in lower bounds", low=0.0, high=100.0, low_open=True,
                                      group="problem")
    margin_mm: float = setting(0.02, "extra clearance m demanded by the collision constraints", unit="mm", low=0.0, high=10.0,
                               group="problem")
    activate_mm: float = setting(2.5, "a capsule combination gets a separating line where its clearance along the guess is below this",
                                 unit="mm", low=0.0, high=1000.0, group="problem")
    activation_window: int = setting(2, "the initial activation also covers this many intervals around each close approach", low=0,
                                     high=1000, group="problem")
    lazy_rounds: int = setting(4, "re-solves allowed after adding the lines a solution made necessary", low=0, high=100, group="solver")
    max_iter: int = setting(1500, "IPOPT iteration limit per solve", low=2, high=1_000_000, group="solver")
    tol: float = setting(1e-7, "IPOPT convergence tolerance", low=0.0, high=1.0, low_open=True, group="solver")
    max_wall_s: float = setting(120.0, "IPOPT wall-time limit per solve", unit="s", low=0.0, high=1e6, low_open=True, group="solver")
    max_makespan_factor: float = setting(8.0, "upper bound of t_f in lower bounds", low=1.0, high=1000.0, group="problem")
    output_dt_s: float = setting(0.01, "the knots are merged with a uniform grid of this spacing in the output", unit="s", low=1e-4,
                                 high=10.0, group="output")

    @classmethod
    def for_instrument(cls, instrument: Instrument) -> CentralSettings:
        """Defaults scaled to an instrument: margins and activation distance from the pitch.

        ``margin_mm = 0.002 pitch`` (DESI 0.02 mm, MOONS 0.05 mm), ``activate_mm =
        0.25 pitch``, output grid at the instrument's control period.
        """
        return cls(
            margin_mm=round(0.002 * instrument.pitch_mm, 4),
            activate_mm=round(0.25 * instrument.pitch_mm, 3),
            output_dt_s=instrument.control_dt_s,
        )

    def __post_init__(self) -> None:
        if isinstance(self.warm_start, str):
            object.__setattr__(self, "warm_start", tuple(s for s in self.warm_start.split(",") if s))
        else:
            object.__setattr__(self, "warm_start", tuple(self.warm_start))
        check_settings(self, "central")
        if not all(isinstance(w, str) for w in self.warm_start):
            raise SettingsError(f"central: warm_start must be a list of names, found {list(self.warm_start)!r}")
        if not self.warm_start:
            raise PlannerError("central: warm_start needs at least one start, e.g. ['straight'] or ['straight', 'dnf']")
        if "central" in self.warm_start:
            raise PlannerError("central: warm_start cannot name 'central' itself")


@dataclass
class Candidate:
    """One IPOPT solve sequence (with its lazy rounds) from one warm start.

    Attributes:
        source: the warm start's name.
        status: IPOPT return status of the last solve.
        converged: IPOPT reported success (or an acceptable level) on the last solve.
        objective: objective value of the last solve.
        makespan_s: final time ``t_f`` of the solution (s).
        joints: ``(T + 1, N, 2)`` knots of the solution.
        iterations: IPOPT iterations summed over the lazy rounds.
        solve_s: wall time of the IPOPT calls (s), summed.
        build_s: wall time spent building the NLPs (s), summed.
        rounds: solves done (1 + lazy re-solves).
        lines: separating lines in the last NLP.
    """

    source: str
    status: str
    converged: bool
    objective: float
    makespan_s: float
    joints: np.ndarray
    iterations: int
    solve_s: float
    build_s: float
    rounds: int
    lines: int

    def summary(self) -> dict[str, Any]:
        """JSON-ready statistics (no arrays)."""
        return {
            "source": self.source,
            "status": self.status,
            "converged": self.converged,
            "objective": self.objective,
            "makespan_s": self.makespan_s,
            "iterations": self.iterations,
            "solve_s": self.solve_s,
            "build_s": self.build_s,
            "rounds": self.rounds,
            "lines": self.lines,
        }


@dataclass
class CentralSolution:
    """Every candidate of a central solve, best first, and how the warm starts were made."""

    candidates: list[Candidate]
    warm_start_s: dict[str, float] = field(default_factory=dict)
    lower_bound_s: float = 0.0


# ---------------------------------------------------------------------------- geometry tables
@dataclass(frozen=True)
class _Points:
    """Capsule segment end points of one positioner type, as used by the NLP.

    ``arm[p]`` is 0 (alpha) or 1 (beta), ``dist[p]`` the distance along that arm, ``capsule[p]``
    the capsule it belongs to, ``radius[p]`` its radius, ``sagitta[p]`` the coefficient ``s_p``
    of the worst-case chord deviation ``s_p h^2`` (joints at full speed), and
    ``chord_alpha[p]``, ``chord_beta[p]`` the coefficients of the chord deviation from the
    joint increments of the interval, ``c_a \\Delta\alpha^2 + c_b \\Delta\beta^2``.
    """

    arm: np.ndarray
    dist: np.ndarray
    capsule: np.ndarray
    radius: np.ndarray
    sagitta: np.ndarray
    chord_alpha: np.ndarray
    chord_beta: np.ndarray


def _capsule_points(instrument: Instrument) -> _Points:
    r"""End points of every capsule and their chord-deviation coefficients.

    A point at distance ``s`` along the beta arm is ``x = e + s u(a + b)`` with the elbow
    ``e = b_0 + l_1 u(a)``. With joints linear in time over an interval of length ``h``,
    ``|x''(t)| \le l_1 \omega_a^2 + s (\omega_a + \omega_b)^2``, so the point stays within
    ``h^2 / 8`` times that of its chord (linear interpolation error bound). Alpha-arm
    points: ``s \omega_a^2``. In terms of the joint increments of the interval,
    ``|d^2 x / d\sigma^2| \le l_1 \Delta a^2 + s (|\Delta a| + |\Delta b|)^2
    \le (l_1 + 2 s) \Delta a^2 + 2 s \Delta b^2`` (smooth), used by the NLP.
    """
    wa, wb = instrument.alpha_speed_rad_s, instrument.beta_speed_rad_s
    arm, dist, capsule, radius, sag, chord_a, chord_b = [], [], [], [], [], [], []
    for c_idx, cap in enumerate(instrument.capsules):
        ends = [cap.start_mm] if cap.start_mm == cap.end_mm else [cap.start_mm, cap.end_mm]
        for s in ends:
            is_beta = cap.arm == "beta"
            arm.append(1 if is_beta else 0)
            dist.append(s)
            capsule.append(c_idx)
            radius.append(cap.radius_mm)
            curvature = instrument.alpha_arm_mm * wa**2 + abs(s) * (wa + wb) ** 2 if is_beta else abs(s) * wa**2
            sag.append(curvature / 8.0)
            chord_a.append((instrument.alpha_arm_mm + 2 * abs(s)) / 8.0 if is_beta else abs(s) / 8.0)
            chord_b.append(2 * abs(s) / 8.0 if is_beta else 0.0)
    return _Points(
        np.array(arm), np.array(dist, dtype=float), np.array(capsule), np.array(radius, dtype=float), np.array(sag, dtype=float),
        np.array(chord_a), np.array(chord_b),
    )


def _point_positions(instrument: Instrument, pts: _Points, base_xy: np.ndarray, orient: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Positions ``(..., N, P, 2)`` of the capsule end points for joints ``(..., N, 2)``."""
    a = joints[..., 0] + orient
    ab = a + joints[..., 1]
    ua = np.stack([np.cos(a), np.sin(a)], axis=-1)[..., None, :]
    uab = np.stack([np.cos(ab), np.sin(ab)], axis=-1)[..., None, :]
    base = np.broadcast_to(base_xy, (*a.shape, 2))[..., None, :]
    elbow = base + instrument.alpha_arm_mm * ua
    is_beta = (pts.arm == 1)[:, None]
    return np.where(is_beta, elbow + pts.dist[:, None] * uab, base + pts.dist[:, None] * ua)


def _motion_bound(instrument: Instrument, joints: np.ndarray) -> np.ndarray:
    """Largest distance any capsule point moves over each interval, ``(T, N)`` (verifier's bound)."""
    delta = np.abs(np.diff(joints, axis=0))
    return instrument.alpha_point_extent_mm * delta[..., 0] + instrument.beta_point_extent_mm * delta[..., 1]


def _close_intervals(scenario: Scenario, joints: np.ndarray, activate_mm: float) -> np.ndarray:
    """Boolean ``(T, P, K)``: combination ``K`` of pair ``P`` comes within ``activate_mm`` on interval ``k``.

    The clearance at the two knots minus the motion bound of the interval bounds the clearance
    anywhere in between.
    """
    inst = scenario.instrument
    clear = pair_clearance(inst, scenario.base_xy, scenario.orient, joints, scenario.pairs).clearance
    bound = _motion_bound(inst, joints)
    pairs = scenario.pairs
    move = bound[:, pairs[:, 0]] + bound[:, pairs[:, 1]]
    low = np.minimum(clear[:-1], clear[1:]) - move[..., None]
    return low < activate_mm


# ---------------------------------------------------------------------------- the NLP
@dataclass
class _Problem:
    """Everything about one scenario the NLP needs, independent of the active lines."""

    scenario: Scenario
    settings: CentralSettings
    steps: int
    lower_bound_s: float
    energy_ref: float
    tau_fixed: float | None
    points: _Points
    combos: np.ndarray  # (K, 2) capsule indices of i and j
    end_clearance: np.ndarray  # (2, P, K) clearances at the (fixed) start and target

    @property
    def n(self) -> int:
        return self.scenario.n_positioners


def _lower_bound(scenario: Scenario) -> float:
    times = move_times(scenario.instrument, scenario.start, scenario.target)
    return float(times.max()) if len(times) else 0.0


def _make_problem(scenario: Scenario, settings: CentralSettings) -> _Problem:
    lb = _lower_bound(scenario)
    delta = scenario.target - scenario.start
    energy_ref = float(np.sum(delta**2) / lb) if lb > 0 else 0.0
    tau_fixed = None
    if settings.mode == "energy":
        tf = settings.makespan_s if settings.makespan_s is not None else settings.makespan_factor * lb
        if tf < lb * (1 - 1e-9):
            raise PlannerError(
                f"central: energy mode needs makespan_s >= the lower bound {lb:.6g} s (the slowest positioner's "
                f"unobstructed move), found {tf:.6g} s"
            )
        tau_fixed = tf / lb if lb > 0 else 1.0
    return _Problem(
        scenario=scenario,
        settings=settings,
        steps=int(settings.steps),
        lower_bound_s=lb,
        energy_ref=energy_ref,
        tau_fixed=tau_fixed,
        points=_capsule_points(scenario.instrument),
        combos=np.array(scenario.instrument.capsule_pairs, dtype=np.int64).reshape(-1, 2),
        end_clearance=pair_clearance(
            scenario.instrument, scenario.base_xy, scenario.orient, np.stack([scenario.start, scenario.target]), scenario.pairs
        ).clearance,
    )


def _solve_nlp(problem: _Problem, active: np.ndarray, guess_q: np.ndarray, guess_tau: float) -> tuple[dict[str, Any], float]:
    """Build the NLP for the ``active`` lines (``(L, 3)`` rows ``k, pair, combo``) and solve it once.

    Returns the raw solution dictionary (``q``, ``tau``, ``status``, ``iterations``,
    ``objective``, ``solve_s``) and the build time.
    """
    import casadi as ca

    t_build = time.perf_counter()
    sc, st = problem.scenario, problem.settings
    inst = sc.instrument
    T, n = problem.steps, problem.n
    n_q = (T + 1) * n * 2
    n_lines = len(active)
    z = ca.SX.sym("z", n_q + 1 + 3 * n_lines)
    q = z[:n_q]
    tau = z[n_q]
    lines = z[n_q + 1 :]
    lb = problem.lower_bound_s
    h = tau * (lb / T)

    # Joint angles, flattened (k, i, joint): alpha at even, beta at odd positions.
    alpha = q[0::2]
    beta = q[1::2]
    orient = ca.DM(np.tile(sc.orient, T + 1))
    bx = ca.DM(np.tile(sc.base_xy[:, 0], T + 1))
    by = ca.DM(np.tile(sc.base_xy[:, 1], T + 1))
    a = alpha + orient
    ab = a + beta
    ca_, sa_ = ca.cos(a), ca.sin(a)
    cab, sab = ca.cos(ab), ca.sin(ab)
    ex, ey = bx + inst.alpha_arm_mm * ca_, by + inst.alpha_arm_mm * sa_
    pts = problem.points
    px_list, py_list = [], []
    for p in range(len(pts.arm)):
        if pts.arm[p] == 1:
            px_list.append(ex + pts.dist[p] * cab)
            py_list.append(ey + pts.dist[p] * sab)
        else:
            px_list.append(bx + pts.dist[p] * ca_)
            py_list.append(by + pts.dist[p] * sa_)
    px_all = ca.vertcat(*px_list)
    py_all = ca.vertcat(*py_list)
    stride = (T + 1) * n  # points are stacked (point, k, i)

    # Speed bounds and energy: dq over every interval.
    cur = np.arange(T * n * 2)
    nxt = cur + n * 2
    dq = q[nxt] - q[cur]
    omega = ca.DM(np.tile(inst.speeds_rad_s, T * n))
    g_parts = [dq - omega * h, dq + omega * h]
    lbg = [np.full(T * n * 2, -np.inf), np.zeros(T * n * 2)]
    ubg = [np.zeros(T * n * 2), np.full(T * n * 2, np.inf)]
    energy = ca.sumsqr(dq) / h

    if n_lines:
        nx, ny, cc = lines[0::3], lines[1::3], lines[2::3]
        k_l, p_l, c_l = active[:, 0], active[:, 1], active[:, 2]
        i_l, j_l = sc.pairs[p_l, 0], sc.pairs[p_l, 1]
        mid = 0.5 * (sc.base_xy[i_l] + sc.base_xy[j_l])
        rows_line, rows_point, rows_sign, rows_move = [], [], [], []
        for side, (pos, cap_col) in enumerate(((i_l, 0), (j_l, 1))):
            cap = problem.combos[c_l, cap_col]
            for p in range(len(pts.arm)):
                use = pts.capsule[p] == cap
                if not np.any(use):
                    continue
                lidx = np.flatnonzero(use)
                for dk in (0, 1):
                    rows_line.append(lidx)
                    rows_point.append(p * stride + (k_l[lidx] + dk) * n + pos[lidx])
                    rows_sign.append(np.full(len(lidx), 1.0 if side == 0 else -1.0))
                    rows_move.append((k_l[lidx] * n + pos[lidx]) * 2)  # alpha of this positioner at knot k
        r_line = np.concatenate(rows_line)
        r_point = np.concatenate(rows_point)
        r_sign = np.concatenate(rows_sign)
        r_pid = r_point // stride
        relief = _end_relief(problem, active)[r_line]
        const = pts.radius[r_pid] + 0.5 * st.margin_mm * relief
        r_move = np.concatenate(rows_move)
        d_alpha = q[r_move + 2 * n] - q[r_move]
        d_beta = q[r_move + 2 * n + 1] - q[r_move + 1]
        chord = ca.DM(pts.chord_alpha[r_pid] * relief) * d_alpha**2 + ca.DM(pts.chord_beta[r_pid] * relief) * d_beta**2
        signed = (
            nx[r_line] * (px_all[r_point] - ca.DM(mid[r_line, 0]))
            + ny[r_line] * (py_all[r_point] - ca.DM(mid[r_line, 1]))
            - cc[r_line]
        )
        g_sep = ca.DM(r_sign) * signed - ca.DM(const) - chord
        g_parts += [g_sep, nx**2 + ny**2]
        lbg += [np.zeros(len(r_line)), np.full(n_lines, -np.inf)]
        ubg += [np.full(len(r_line), np.inf), np.ones(n_lines)]

    e_ref = problem.energy_ref if problem.energy_ref > 0 else 1.0
    if problem.tau_fixed is None:
        objective = tau + st.energy_weight * energy / e_ref
    else:
        objective = energy / e_ref
    g = ca.vertcat(*g_parts)

    # Bounds: hard stops, fixed start and target, tau, unit-ball normals.
    lim = inst.limits_rad
    lo_q = np.tile(lim[:, 0], (T + 1) * n).reshape(T + 1, n, 2)
    hi_q = np.tile(lim[:, 1], (T + 1) * n).reshape(T + 1, n, 2)
    lo_q[0] = hi_q[0] = sc.start
    lo_q[T] = hi_q[T] = sc.target
    if problem.tau_fixed is None:
        tau_lo, tau_hi = 1.0 - 1e-9, st.max_makespan_factor
    else:
        tau_lo = tau_hi = problem.tau_fixed
    line_lo = np.tile([-1.0, -1.0, -np.inf], n_lines)
    line_hi = np.tile([1.0, 1.0, np.inf], n_lines)
    lbx = np.concatenate([lo_q.ravel(), [tau_lo], line_lo])
    ubx = np.concatenate([hi_q.ravel(), [tau_hi], line_hi])

    x0_q = np.clip(guess_q, lo_q, hi_q)
    x0_tau = float(np.clip(guess_tau, tau_lo, tau_hi))
    x0 = np.concatenate([x0_q.ravel(), [x0_tau], _initial_lines(problem, active, x0_q).ravel()])

    opts: dict[str, Any] = {
        "print_time": False,
        "ipopt": {
            "print_level": 0,
            "sb": "yes",
            "max_iter": int(st.max_iter),
            "tol": st.tol,
            "acceptable_tol": 1e-4,
            "acceptable_iter": 10,
            "max_wall_time": st.max_wall_s,
            "mu_strategy": "adaptive",
            "bound_relax_factor": 0.0,
        },
    }
    solver = ca.nlpsol("central", "ipopt", {"x": z, "f": objective, "g": g}, opts)
    build_s = time.perf_counter() - t_build
    t0 = time.perf_counter()
    sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=np.concatenate(lbg), ubg=np.concatenate(ubg))
    solve_s = time.perf_counter() - t0
    solver_stats = solver.stats()
    x = np.array(sol["x"]).ravel()
    return {
        "q": x[:n_q].reshape(T + 1, n, 2),
        "tau": float(x[n_q]),
        "status": str(solver_stats.get("return_status", "unknown")),
        "iterations": int(solver_stats.get("iter_count", 0)),
        "objective": float(sol["f"]),
        "solve_s": solve_s,
    }, build_s


def _end_relief(problem: _Problem, active: np.ndarray) -> np.ndarray:
    """Factor ``(L,)`` in ``[0, 1]`` on the margin and chord terms of each line.

    The start and target are fixed and only known to be collision-free, possibly by less than
    ``m`` plus the chord terms: on the first and last intervals the extra terms are scaled
    down to at most half the clearance of the fixed configuration (chord terms evaluated at
    full speed with ``h = 2 t_LB / T``), so that the NLP stays feasible (the verifier still
    judges the motion in between). Other lines get 1.
    """
    st = problem.settings
    relief = np.ones(len(active))
    if len(active) == 0:
        return relief
    k_l, p_l, c_l = active[:, 0], active[:, 1], active[:, 2]
    pts = problem.points
    cap_i, cap_j = problem.combos[c_l, 0], problem.combos[c_l, 1]
    sag_max = np.array([pts.sagitta[pts.capsule == c].max() for c in range(len(problem.scenario.instrument.capsules))])
    demand = st.margin_mm + (sag_max[cap_i] + sag_max[cap_j]) * (2.0 * problem.lower_bound_s / problem.steps) ** 2
    for end, k_end in ((0, 0), (1, problem.steps - 1)):
        at_end = k_l == k_end
        clear = np.maximum(problem.end_clearance[end, p_l, c_l], 0.0)
        factor = np.minimum(1.0, 0.5 * clear / np.maximum(demand, 1e-12))
        relief = np.where(at_end, np.minimum(relief, factor), relief)
    return relief


def _initial_lines(problem: _Problem, active: np.ndarray, guess_q: np.ndarray) -> np.ndarray:
    """Separating lines ``(L, 3)`` (``n_x, n_y, c``, with ``c`` relative to the pair's mid-base) from the guess.

    The normal is the direction between the closest points of the two capsules at the knot
    (of the two) where they are closer; the offset is half-way between the two sets of
    end points projected on it (inflated by their radii).
    """
    sc = problem.scenario
    inst = sc.instrument
    if len(active) == 0:
        return np.zeros((0, 3))
    k_l, p_l, c_l = active[:, 0], active[:, 1], active[:, 2]
    i_l, j_l = sc.pairs[p_l, 0], sc.pairs[p_l, 1]
    cap_i, cap_j = problem.combos[c_l, 0], problem.combos[c_l, 1]
    pts = problem.points
    pos = _point_positions(inst, pts, sc.base_xy, sc.orient, guess_q)  # (T+1, N, P, 2)
    normals = np.zeros((len(active), 2))
    best = np.full(len(active), np.inf)
    from fiberplan.geometry import capsule_segments

    seg_start, seg_end = capsule_segments(inst, sc.base_xy, sc.orient, guess_q)  # (T+1, N, C, 2)
    for dk in (0, 1):
        kk = k_l + dk
        p0, p1 = seg_start[kk, i_l, cap_i], seg_end[kk, i_l, cap_i]
        q0, q1 = seg_start[kk, j_l, cap_j], seg_end[kk, j_l, cap_j]
        dist, s, t = segment_distance(p0, p1, q0, q1)
        direction = (p0 + s[:, None] * (p1 - p0)) - (q0 + t[:, None] * (q1 - q0))
        better = dist < best
        normals[better] = direction[better]
        best = np.minimum(best, dist)
    norm = np.linalg.norm(normals, axis=1)
    fallback = norm < 1e-6
    normals[fallback] = sc.base_xy[i_l[fallback]] - sc.base_xy[j_l[fallback]]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    mid = 0.5 * (sc.base_xy[i_l] + sc.base_xy[j_l])
    lo_i = np.full(len(active), np.inf)
    hi_j = np.full(len(active), -np.inf)
    for p in range(len(pts.arm)):
        for dk in (0, 1):
            kk = k_l + dk
            on_i = pts.capsule[p] == cap_i
            proj_i = np.einsum("li,li->l", normals, pos[kk, i_l, p] - mid) - pts.radius[p]
            lo_i = np.where(on_i, np.minimum(lo_i, proj_i), lo_i)
            on_j = pts.capsule[p] == cap_j
            proj_j = np.einsum("li,li->l", normals, pos[kk, j_l, p] - mid) + pts.radius[p]
            hi_j = np.where(on_j, np.maximum(hi_j, proj_j), hi_j)
    return np.column_stack([normals, 0.5 * (lo_i + hi_j)])


def _activate(problem: _Problem, joints: np.ndarray, window: int) -> np.ndarray:
    """Active-line mask ``(T, P, K)`` from a guess, dilated by ``window`` intervals in time."""
    close = _close_intervals(problem.scenario, joints, problem.settings.activate_mm)
    if window > 0 and close.any():
        dilated = close.copy()
        for shift in range(1, window + 1):
            dilated[shift:] |= close[:-shift]
            dilated[:-shift] |= close[shift:]
        close = dilated
    return close


def _solve_candidate(problem: _Problem, source: str, guess_q: np.ndarray, guess_tau: float) -> Candidate:
    """Solve from one guess, adding lines the solution needs, up to ``lazy_rounds`` times."""
    st = problem.settings
    mask = _activate(problem, guess_q, st.activation_window)
    iterations, solve_s, build_s, rounds = 0, 0.0, 0.0, 0
    q, tau = guess_q, guess_tau
    raw: dict[str, Any] = {}
    for _ in range(st.lazy_rounds + 1):
        active = np.argwhere(mask)
        raw, b_s = _solve_nlp(problem, active, q, tau)
        rounds += 1
        iterations += raw["iterations"]
        solve_s += raw["solve_s"]
        build_s += b_s
        q, tau = raw["q"], raw["tau"]
        if raw["status"] not in _IPOPT_SUCCESS:
            break
        missing = _activate(problem, q, 1) & ~mask
        if not missing.any():
            break
        mask |= missing
    finite = bool(np.all(np.isfinite(q)) and np.isfinite(tau))
    converged = finite and raw["status"] in _IPOPT_SUCCESS and not (_close_intervals(problem.scenario, q, st.activate_mm) & ~mask).any()
    status = raw["status"] if raw["status"] not in _IPOPT_SUCCESS or converged else "Lazy_Rounds_Exhausted"
    if not finite:
        status = "Non_Finite_Solution"
        q = np.where(np.isfinite(q), q, 0.0)
    return Candidate(
        source=source,
        status=status,
        converged=converged,
        objective=raw["objective"],
        makespan_s=_exact_makespan(problem, q, tau),
        joints=q,
        iterations=iterations,
        solve_s=solve_s,
        build_s=build_s,
        rounds=rounds,
        lines=int(mask.sum()),
    )


def _exact_makespan(problem: _Problem, q: np.ndarray, tau: float) -> float:
    """Final time of the knots ``q``: ``tau t_LB``, lengthened if rounding left any joint too fast."""
    T = problem.steps
    tf = tau * problem.lower_bound_s
    needed = float((np.abs(np.diff(q, axis=0)) / problem.scenario.instrument.speeds_rad_s).max()) * T if T else 0.0
    return max(tf, needed * (1 + 1e-9))


# ---------------------------------------------------------------------------- warm starts
def _straight_guess(problem: _Problem, stretch: float) -> tuple[np.ndarray, float]:
    sc = problem.scenario
    s = np.linspace(0.0, 1.0, problem.steps + 1)[:, None, None]
    q = sc.start[None] + s * (sc.target - sc.start)[None]
    return q, max(stretch, 1.0) if problem.tau_fixed is None else problem.tau_fixed


def _sequential_guess(problem: _Problem) -> tuple[np.ndarray, float]:
    """One positioner after another (longest move first), each at full speed, on ``T + 1`` knots.

    Another homotopy than :func:`_straight_guess`: where two straight moves cross, the one
    that moves first passes before the other leaves. Its duration (the sum of the move
    times) is capped at ``max_makespan_factor`` lower bounds, the knots then moving too fast
    for IPOPT to repair.
    """
    sc = problem.scenario
    times = move_times(sc.instrument, sc.start, sc.target)
    order = np.argsort(-times, kind="stable")
    begin = np.zeros(len(times))
    begin[order] = np.concatenate([[0.0], np.cumsum(times[order])[:-1]])
    total = float(times.sum())
    t = np.linspace(0.0, total, problem.steps + 1)[:, None]
    frac = np.clip((t - begin[None]) / np.where(times > 0, times, 1.0)[None], 0.0, 1.0)
    q = sc.start[None] + frac[..., None] * (sc.target - sc.start)[None]
    if problem.tau_fixed is not None:
        return q, problem.tau_fixed
    return q, min(total / problem.lower_bound_s, problem.settings.max_makespan_factor)


def _trajectory_guess(problem: _Problem, result: PlanResult) -> tuple[np.ndarray, float]:
    """Resample another planner's trajectory to ``T + 1`` knots ending at the target."""
    from fiberplan.metrics import arrival_times

    sc = problem.scenario
    traj = result.trajectory
    arrivals = arrival_times(sc, traj)
    t_end = float(np.nanmax(arrivals)) if np.all(np.isfinite(arrivals[sc.has_target])) and np.any(sc.has_target) else traj.duration_s
    t_end = max(t_end, problem.lower_bound_s, 1e-9)
    T = problem.steps
    q = np.stack([traj.at(t) for t in np.linspace(0.0, t_end, T + 1)])
    q[0] = sc.start
    q[-1] = sc.target
    if problem.tau_fixed is not None:
        return q, problem.tau_fixed
    lb = problem.lower_bound_s
    needed = float((np.abs(np.diff(q, axis=0)) / sc.instrument.speeds_rad_s).max()) * T / lb
    return q, max(t_end / lb, needed)


def _hold_result(scenario: Scenario, settings: CentralSettings, stats: dict[str, Any]) -> PlanResult:
    """Every positioner holds still: safe, and ``failed`` where a target was not reached.

    The result says why in its warnings (the command line prints them).
    """
    at_target = np.all(np.abs(scenario.target - scenario.start) < 1e-12, axis=1)
    joints = np.stack([scenario.start, scenario.start])
    warnings: tuple[str, ...] = ()
    if not at_target.all():
        tried = ", ".join(f"{c['source']}: {c['status']}" for c in stats.get("candidates", [])) or "no warm start"
        rejected = stats.get("rejected") or []
        why = (f"no converged candidate passed the verifier ({len(rejected)} rejected)" if rejected
               else f"IPOPT converged from no warm start ({tried})")
        warnings = (f"central: gave up: {why}; every positioner holds still and {int((~at_target).sum())} are marked failed",)
    return PlanResult(
        scenario=scenario,
        trajectory=Trajectory(np.array([0.0, settings.output_dt_s]), joints),
        outcome=outcome_labels(scenario, scenario.start, np.zeros(scenario.n_positioners, dtype=bool), failed=~at_target),
        planner="central",
        settings=_settings_dict(settings),
        stats=stats,
        warnings=warnings,
    )


def _settings_dict(settings: CentralSettings) -> dict[str, Any]:
    out = dataclasses.asdict(settings)
    out["warm_start"] = list(settings.warm_start)
    return out


def _to_result(problem: _Problem, cand: Candidate, stats: dict[str, Any]) -> PlanResult:
    """Trajectory on the knots merged with the output grid; ``reached`` for a converged candidate."""
    sc, st = problem.scenario, problem.settings
    T = problem.steps
    tf = cand.makespan_s
    knots_t = np.linspace(0.0, tf, T + 1)
    grid = np.arange(0.0, tf, st.output_dt_s)
    close = np.min(np.abs(grid[:, None] - knots_t[None, :]), axis=1) < 1e-9 * max(tf, 1.0)
    times = np.union1d(knots_t, grid[~close])
    k = np.clip(np.searchsorted(knots_t, times, side="right") - 1, 0, T - 1)
    w = ((times - knots_t[k]) / (knots_t[k + 1] - knots_t[k]))[:, None, None]
    joints = (1 - w) * cand.joints[k] + w * cand.joints[k + 1]
    lim = sc.instrument.limits_rad
    joints = np.clip(joints, lim[:, 0], lim[:, 1])
    joints[0] = sc.start
    joints[-1] = sc.target
    outcome = outcome_labels(sc, joints[-1], np.zeros(sc.n_positioners, dtype=bool), failed=np.full(sc.n_positioners, not cand.converged))
    return PlanResult(
        scenario=sc,
        trajectory=Trajectory(times, joints),
        outcome=outcome,
        planner="central",
        settings=_settings_dict(st),
        stats=stats,
    )


def solve_central(
    scenario: Scenario,
    settings: CentralSettings,
    *,
    warm_results: Sequence[PlanResult] = (),
    progress: ProgressCallback | None = None,
) -> tuple[CentralSolution, _Problem]:
    """Solve from every warm start; candidates sorted best first (converged ones first).

    Args:
        scenario: the group to plan.
        settings: see :class:`CentralSettings`.
        warm_results: trajectories already planned for this scenario by other planners, used
            as extra warm starts (named by their planner); planners named in
            ``settings.warm_start`` that appear here are not run again.
        progress: optional callback receiving the fraction done.

    Raises:
        PlannerError: a warm-start planner is unknown, or energy mode asks for a makespan
            below the lower bound.
    """
    from fiberplan.planners import plan as run_planner

    problem = _make_problem(scenario, settings)
    solution = CentralSolution(candidates=[], lower_bound_s=problem.lower_bound_s)
    if problem.lower_bound_s <= 0:
        return solution, problem
    starts: list[tuple[str, np.ndarray, float]] = []
    given = {r.planner: r for r in warm_results}
    for name in settings.warm_start:
        if name == _STRAIGHT:
            starts.append((name, *_straight_guess(problem, settings.straight_stretch)))
            continue
        if name == _SEQUENTIAL:
            starts.append((name, *_sequential_guess(problem)))
            continue
        if name not in given:
            t0 = time.perf_counter()
            given[name] = run_planner(scenario, name)
            solution.warm_start_s[name] = time.perf_counter() - t0
    for name, result in given.items():
        if name != "central":
            starts.append((name, *_trajectory_guess(problem, result)))
    for idx, (name, q0, tau0) in enumerate(starts):
        solution.candidates.append(_solve_candidate(problem, name, q0, tau0))
        if progress is not None:
            progress((idx + 1) / len(starts))
    solution.candidates.sort(key=lambda c: (not c.converged, c.objective))
    return solution, problem


def _stats(solution: CentralSolution, chosen: Candidate | None, verified: bool | None) -> dict[str, Any]:
    stats: dict[str, Any] = {
        "lower_bound_s": solution.lower_bound_s,
        "candidates": [c.summary() for c in solution.candidates],
        "warm_start_s": dict(solution.warm_start_s),
        "chosen": None if chosen is None else chosen.source,
        "verified": verified,
    }
    if chosen is not None:
        stats.update(
            {
                "status": chosen.status,
                "iterations": chosen.iterations,
                "solve_s": chosen.solve_s,
                "objective": chosen.objective,
                "makespan_s": chosen.makespan_s,
                "lines": chosen.lines,
            }
        )
    else:
        stats.update({"status": "no_converged_candidate" if solution.candidates else "nothing_to_move"})
    stats["solve_s_total"] = float(sum(c.solve_s for c in solution.candidates))
    stats["iterations_total"] = int(sum(c.iterations for c in solution.candidates))
    return stats


def plan_central(scenario: Scenario, settings: CentralSettings, progress: ProgressCallback | None = None) -> PlanResult:
    """Plan a small group with one NLP; return the best converged candidate (not verified here).

    Every positioner is ``reached`` when IPOPT converged (the last knot is the target by
    construction); when no start converged, every positioner holds still and is ``failed``.
    Use :func:`central_reference` for a verified result.
    """
    solution, problem = solve_central(scenario, settings, progress=progress)
    if problem.lower_bound_s <= 0:
        return _hold_result(scenario, settings, _stats(solution, None, None))
    best = solution.candidates[0] if solution.candidates and solution.candidates[0].converged else None
    if best is None:
        return _hold_result(scenario, settings, _stats(solution, None, None))
    return _to_result(problem, best, _stats(solution, best, None))


def central_reference(
    scenario: Scenario,
    settings: CentralSettings | Mapping[str, Any] | None = None,
    *,
    warm_results: Sequence[PlanResult] = (),
    progress: ProgressCallback | None = None,
) -> PlanResult:
    """The verified central optimum: candidates are checked by :func:`fiberplan.verify.verify`, best first.

    The first converged candidate the independent verifier accepts is returned with
    ``stats["verified"] = True``. If none passes, every positioner holds still, is marked
    ``failed`` and ``stats["verified"]`` is False: a central solution with a collision or a
    limit violation is never reported as optimal. ``plan_wall_s`` covers the solves and
    the verification (not the runs of ``warm_results``).

    Raises:
        PlannerError: bad settings (see :func:`solve_central`).
    """
    from fiberplan.planners import make_settings
    from fiberplan.verify import verify

    chosen_settings: CentralSettings = settings if isinstance(settings, CentralSettings) else make_settings("central", scenario, settings)
    settings = chosen_settings
    t0 = time.perf_counter()
    solution, problem = solve_central(scenario, settings, warm_results=warm_results, progress=progress)
    if problem.lower_bound_s <= 0:
        result = _hold_result(scenario, settings, _stats(solution, None, True))
        return dataclasses.replace(result, plan_wall_s=time.perf_counter() - t0)
    rejected: list[dict[str, Any]] = []
    for cand in solution.candidates:
        if not cand.converged:
            continue
        result = _to_result(problem, cand, {})
        report = verify(scenario, result.trajectory)
        if report.ok:
            stats = _stats(solution, cand, True) | {"rejected": rejected, "min_clearance_mm": report.min_clearance_mm}
            return dataclasses.replace(result, stats=stats, plan_wall_s=time.perf_counter() - t0)
        rejected.append({"source": cand.source, "collisions": report.n_collisions, "limit_violations": len(report.limit_violations)})
    stats = _stats(solution, None, False) | {"rejected": rejected}
    return dataclasses.replace(_hold_result(scenario, settings, stats), plan_wall_s=time.perf_counter() - t0)
