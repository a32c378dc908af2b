"""The central NLP: capsule points, the problem, one IPOPT solve, lazy lines, one candidate."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fiberplan.errors import PlannerError
from fiberplan.geometry import motion_bound, pair_clearance, point_extents, segment_distance
from fiberplan.instrument import Instrument
from fiberplan.kinematics import move_times
from fiberplan.planners.central.settings import _IPOPT_SUCCESS, CentralSettings
from fiberplan.scenario import Scenario


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
        attempts: every IPOPT solve, round by round: ``(round, warm, status, iterations, seconds)``.
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
    attempts: list[tuple[int, bool, str, int, float]] = field(default_factory=list)

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
            "attempts": [list(a) for a in self.attempts],
        }


@dataclass
class CentralSolution:
    """Every candidate of a central solve, best first, and how the warm starts were made."""

    candidates: list[Candidate]
    warm_start_s: dict[str, float] = field(default_factory=dict)
    lower_bound_s: float = 0.0


# ---------------------------------------------------------------------------- geometry tables
@dataclass(frozen=True)
class _Bodies:
    """The convex bodies the NLP separates: a polygon zone (its edge capsules together) or a
    capsule of its own, and the body pairs the instrument checks.

    A separating line per body pair rather than per capsule pair: two convex bodies are apart
    exactly when a line separates them (every vertex of one on its side, by the radius), so a
    polygon of ``e`` edges needs one line per neighbouring body, not ``e`` x ``e'`` (MOONS' own
    model: 134 checked edge pairs, 15 zone pairs). For instruments made of capsules, bodies are
    the capsules and body pairs the capsule pairs, in the same order.
    """

    of_capsule: np.ndarray  # (C,) the body of each capsule
    combos: np.ndarray  # (B, 2) body pairs (body of i, body of j)
    of_combo: np.ndarray  # (K,) the body pair of each capsule pair of ``Instrument.capsule_pairs``

    @property
    def identity(self) -> bool:
        """Every capsule is a body of its own (nothing to group)."""
        return len(self.combos) == len(self.of_combo) and bool(np.all(self.of_combo == np.arange(len(self.of_combo))))

    def reduce(self, clearance: np.ndarray) -> np.ndarray:
        """Clearances ``(..., K)`` of capsule pairs -> ``(..., B)`` of body pairs (the smallest)."""
        if self.identity:
            return clearance
        out = np.empty((*clearance.shape[:-1], len(self.combos)))
        for b in range(len(self.combos)):
            out[..., b] = clearance[..., self.of_combo == b].min(axis=-1)
        return out


def _bodies(instrument: Instrument) -> _Bodies:
    names: list[str] = []
    of_capsule = []
    for cap in instrument.capsules:
        if cap.zone_name not in names:
            names.append(cap.zone_name)
        of_capsule.append(names.index(cap.zone_name))
    body = np.array(of_capsule, dtype=np.int64)
    combos: list[tuple[int, int]] = []
    of_combo = []
    for a, b in instrument.capsule_pairs:
        pair = (int(body[a]), int(body[b]))
        if pair not in combos:
            combos.append(pair)
        of_combo.append(combos.index(pair))
    return _Bodies(body, np.array(combos, dtype=np.int64).reshape(-1, 2), np.array(of_combo, dtype=np.int64))


@dataclass(frozen=True)
class _Points:
    """Capsule segment end points of one positioner type, as used by the NLP (a polygon's
    vertices once each).

    ``arm[p]`` is 0 (alpha) or 1 (beta), ``dist[p]`` the distance along that arm, ``body[p]``
    the body (:class:`_Bodies`) it belongs to, ``radius[p]`` its radius, ``sagitta[p]`` the coefficient ``s_p``
    of the worst-case chord deviation ``s_p h^2`` (joints at full speed), and
    ``chord_alpha[p]``, ``chord_beta[p]`` the coefficients of the chord deviation from the
    joint increments of the interval, ``c_a \\Delta\alpha^2 + c_b \\Delta\beta^2``.
    """

    arm: np.ndarray
    dist: np.ndarray
    body: np.ndarray
    lateral: np.ndarray  # offset to the arm's left (zero for a capsule on the arm's axis)
    radius: np.ndarray
    sagitta: np.ndarray
    chord_alpha: np.ndarray
    chord_beta: np.ndarray


def _capsule_points(instrument: Instrument, bodies: _Bodies) -> _Points:
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
    arm, dist, lateral, body, radius, sag, chord_a, chord_b = [], [], [], [], [], [], [], []
    seen: set[tuple[int, str, float, float]] = set()
    for c_idx, cap in enumerate(instrument.capsules):
        ends = [(cap.start_mm, cap.start_y_mm)]
        if (cap.start_mm, cap.start_y_mm) != (cap.end_mm, cap.end_y_mm):
            ends.append((cap.end_mm, cap.end_y_mm))
        for x, y in ends:
            key = (int(bodies.of_capsule[c_idx]), cap.arm, x, y)
            if key in seen:  # a polygon's vertex, shared by two of its edges
                continue
            seen.add(key)
            is_beta = cap.arm == "beta"
            arm.append(1 if is_beta else 0)
            dist.append(x)
            lateral.append(y)
            s = x if y == 0.0 else math.hypot(x, y)  # distance from the joint, for the curvature bounds
            body.append(int(bodies.of_capsule[c_idx]))
            radius.append(cap.radius_mm)
            curvature = instrument.alpha_arm_mm * wa**2 + abs(s) * (wa + wb) ** 2 if is_beta else abs(s) * wa**2
            sag.append(curvature / 8.0)
            chord_a.append((instrument.alpha_arm_mm + 2 * abs(s)) / 8.0 if is_beta else abs(s) / 8.0)
            chord_b.append(2 * abs(s) / 8.0 if is_beta else 0.0)
    return _Points(
        np.array(arm), np.array(dist, dtype=float), np.array(body), np.array(lateral, dtype=float),
        np.array(radius, dtype=float), np.array(sag, dtype=float), np.array(chord_a), np.array(chord_b),
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
    perp_ab = np.concatenate([-uab[..., 1:2], uab[..., 0:1]], axis=-1)
    perp_a = np.concatenate([-ua[..., 1:2], ua[..., 0:1]], axis=-1)
    lat = pts.lateral[:, None]
    return np.where(is_beta, elbow + pts.dist[:, None] * uab + lat * perp_ab, base + pts.dist[:, None] * ua + lat * perp_a)


def _motion_bound(instrument: Instrument, joints: np.ndarray) -> np.ndarray:
    """Largest distance any capsule point moves over each interval, ``(T, N)`` (verifier's bound)."""
    delta = np.abs(np.diff(joints, axis=0))
    return motion_bound(point_extents(instrument), delta)


def _close_intervals(problem: _Problem, joints: np.ndarray, activate_mm: float) -> np.ndarray:
    """Boolean ``(T, P, B)``: body pair ``B`` of pair ``P`` comes within ``activate_mm`` on interval ``k``.

    The clearance at the two knots minus the motion bound of the interval bounds the clearance
    anywhere in between.
    """
    scenario = problem.scenario
    inst = scenario.instrument
    clear = problem.bodies.reduce(pair_clearance(inst, scenario.base_xy, scenario.orient, joints, scenario.pairs).clearance)
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
    bodies: _Bodies
    points: _Points
    combos: np.ndarray  # (B, 2) body indices of i and j (``bodies.combos``)
    end_clearance: np.ndarray  # (2, P, B) clearances at the (fixed) start and target

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
    bodies = _bodies(scenario.instrument)
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
        bodies=bodies,
        points=_capsule_points(scenario.instrument, bodies),
        combos=bodies.combos,
        end_clearance=bodies.reduce(pair_clearance(
            scenario.instrument, scenario.base_xy, scenario.orient, np.stack([scenario.start, scenario.target]), scenario.pairs
        ).clearance),
    )


@dataclass(frozen=True)
class _Expressions:
    """The NLP of one set of active lines, symbolic: the variables ``z`` (knots, ``tau``, three
    per line), the objective, the constraint blocks ``g_parts`` with their bounds, and the
    entries of the constraints' Jacobian and of the Lagrangian's Hessian (:func:`_derivatives`)."""

    z: Any
    objective: Any
    g_parts: list[Any]
    lbg: list[np.ndarray]
    ubg: list[np.ndarray]
    jac: _Derivative
    hess: _Derivative
    row_keys: np.ndarray  # (n_g,) what each row of g is, the same key in every NLP of a scenario (:func:`_line_codes`)
    var_keys: np.ndarray  # (n_z,) what each variable is, likewise


def _line_codes(problem: _Problem, active: np.ndarray) -> np.ndarray:
    """``(L,)`` one integer per line (interval, pair, body pair), the same in every NLP of the problem."""
    return (active[:, 0] * len(problem.scenario.pairs) + active[:, 1]) * len(problem.combos) + active[:, 2]


_KIND = 1 << 56  # keys of rows and variables: kind * _KIND + code (speed rows and knots 0, separation 1, norm 2)


def _expressions(problem: _Problem, active: np.ndarray) -> _Expressions:
    r"""The NLP's expressions for the ``active`` lines (``(L, 3)`` rows ``k, pair, body pair``),
    with their derivatives written out.

    With ``S = \sum_m \Delta q_m^2`` over every joint and interval, ``h = \tau t_{LB} / T``, the
    objective is ``\tau + C S / \tau`` (time mode; energy mode: ``C S / \tau`` at a fixed
    ``\tau``), ``C = w_E T / (t_{LB} E_{ref})`` (energy mode: ``w_E`` = 1). Its Hessian:
    ``2 C / \tau`` times the chain's Laplacian in the knots (2 on the diagonal, 1 at the two ends,
    -1 between consecutive knots of a joint), ``-(C / \tau^2) dS/dq`` between ``q`` and ``\tau``,
    ``2 C S / \tau^3`` on ``\tau``. The speed rows ``\Delta q \mp \omega h`` are linear; a
    line's norm row ``n_x^2 + n_y^2`` has ``2 n_x``, ``2 n_y`` and ``2`` on its diagonal.
    """
    import casadi as ca

    st = problem.settings
    inst = problem.scenario.instrument
    T, n = problem.steps, problem.n
    n_q = (T + 1) * n * 2
    n_lines = len(active)
    z = ca.SX.sym("z", n_q + 1 + 3 * n_lines)
    q = z[:n_q]
    tau = z[n_q]
    lines = z[n_q + 1 :]
    lb = problem.lower_bound_s
    h = tau * (lb / T)
    jac, hess = _Derivative(), _Derivative()

    kin = _point_kinematics(problem, q)

    # Speed bounds and energy: dq over every interval.
    m = T * n * 2
    cur = np.arange(m)
    nxt = cur + n * 2
    dq = q[nxt] - q[cur]
    omega = np.tile(inst.speeds_rad_s, T * n)
    g_parts = [dq - ca.DM(omega) * h, dq + ca.DM(omega) * h]
    lbg = [np.full(m, -np.inf), np.zeros(m)]
    ubg = [np.zeros(m), np.full(m, np.inf)]
    for block, sign in ((0, -1.0), (1, 1.0)):
        rows = block * m + cur
        jac.add(ca.DM.ones(m), rows, nxt)
        jac.add(-ca.DM.ones(m), rows, cur)
        jac.add(ca.DM(sign * omega * (lb / T)), rows, np.full(m, n_q))
    energy = ca.sumsqr(dq) / h

    codes = _line_codes(problem, active)
    row_keys = [np.arange(2 * m)]
    var_keys = [np.arange(n_q + 1), _KIND + (3 * codes[:, None] + np.arange(3)).ravel()]
    if n_lines:
        g_sep, sep_keys = _separation(problem, active, q, lines, kin, 2 * m, jac, hess)
        row_keys += [_KIND + sep_keys, 2 * _KIND + codes]
        norm_row = 2 * m + g_sep.shape[0] + np.arange(n_lines)
        nx, ny = lines[0::3], lines[1::3]
        g_parts += [g_sep, nx**2 + ny**2]
        lbg += [np.zeros(g_sep.shape[0]), np.full(n_lines, -np.inf)]
        ubg += [np.full(g_sep.shape[0], np.inf), np.ones(n_lines)]
        first = n_q + 1 + 3 * np.arange(n_lines)
        jac.add(2 * nx, norm_row, first)
        jac.add(2 * ny, norm_row, first + 1)
        for var in (first, first + 1):
            hess.add(ca.DM(np.full(n_lines, 2.0)), var, var, norm_row)

    e_ref = problem.energy_ref if problem.energy_ref > 0 else 1.0
    if problem.tau_fixed is None:
        objective = tau + st.energy_weight * energy / e_ref
        c = st.energy_weight * T / (lb * e_ref)
    else:
        objective = energy / e_ref
        c = T / (lb * e_ref)
    ends = np.zeros((T + 1, n * 2))
    ends[[0, -1]] = 1.0  # the first and last knots are in one interval, the others in two
    hess.add((2 * c / tau) * ca.DM(2.0 - ends.ravel()), np.arange(n_q), np.arange(n_q))
    hess.add(ca.DM.ones(m) * (-2 * c / tau), cur, nxt)
    zeros = ca.SX.zeros(n * 2)
    hess.add((-2 * c / tau**2) * (ca.vertcat(zeros, dq) - ca.vertcat(dq, zeros)), np.arange(n_q), np.full(n_q, n_q))
    hess.add(2 * c * ca.sumsqr(dq) / tau**3, [n_q], [n_q])
    return _Expressions(z, objective, g_parts, lbg, ubg, jac, hess, np.concatenate(row_keys), np.concatenate(var_keys))


def _solve_nlp(
    problem: _Problem, active: np.ndarray, guesses: list[tuple[np.ndarray, float]], warm: dict[str, np.ndarray] | None = None,
) -> tuple[dict[str, Any], float]:
    """Build the NLP for the ``active`` lines (``(L, 3)`` rows ``k, pair, body pair``) once and solve it
    from each guess ``(q, tau)`` in turn until IPOPT succeeds.

    With ``warm`` (a previous solve's ``raw["warm"]``: its variables and multipliers, keyed), the
    first guess is solved first from that solution and its multipliers, the rows and lines it did
    not have starting at zero multipliers (IPOPT's warm start: a lazy round's NLP is the last one
    with a few lines more; :data:`_WARM_IPOPT`), and, if that fails, cold; the other guesses cold.

    Returns the raw solution dictionary of the last solve (``q``, ``tau``, ``status``,
    ``objective``; ``iterations`` and ``solve_s`` summed over the solves; ``warm``; ``attempts``:
    per solve, warm or not, status, iterations, seconds) and the build time.
    """
    import casadi as ca

    t_build = time.perf_counter()
    sc, st = problem.scenario, problem.settings
    inst = sc.instrument
    T, n = problem.steps, problem.n
    n_q = (T + 1) * n * 2
    n_lines = len(active)
    ex = _expressions(problem, active)

    # Bounds: hard stops, fixed start and target, tau, unit-ball normals.
    lim = inst.limits_rad
    lo_q = np.tile(lim[:, 0], (T + 1) * n).reshape(T + 1, n, 2)
    hi_q = np.tile(lim[:, 1], (T + 1) * n).reshape(T + 1, n, 2)
    lo_q[0] = hi_q[0] = sc.start
    lo_q[T] = hi_q[T] = sc.target
    lo_q[:, sc.locked] = hi_q[:, sc.locked] = sc.start[sc.locked]  # locked positioners never move
    if problem.tau_fixed is None:
        tau_lo, tau_hi = 1.0 - 1e-9, st.max_makespan_factor
    else:
        tau_lo = tau_hi = problem.tau_fixed
    line_lo = np.tile([-1.0, -1.0, -np.inf], n_lines)
    line_hi = np.tile([1.0, 1.0, np.inf], n_lines)
    lbx = np.concatenate([lo_q.ravel(), [tau_lo], line_lo])
    ubx = np.concatenate([hi_q.ravel(), [tau_hi], line_hi])

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
    # The derivatives IPOPT needs, assembled here (:func:`_derivatives`).
    opts |= _derivatives(ex)
    nlp = {"x": ex.z, "f": ex.objective, "g": ca.vertcat(*ex.g_parts)}
    solvers: dict[bool, Any] = {}

    def solver_for(warm_start: bool) -> Any:
        if warm_start not in solvers:
            ipopt = opts["ipopt"] | ({**_WARM_IPOPT, "max_iter": min(_WARM_IPOPT["max_iter"], int(st.max_iter))} if warm_start else {})
            solvers[warm_start] = ca.nlpsol("central", "ipopt", nlp, opts | {"ipopt": ipopt})
        return solvers[warm_start]

    solver_for(warm is not None)
    build_s = time.perf_counter() - t_build
    raw: dict[str, Any] = {"iterations": 0, "solve_s": 0.0, "attempts": []}
    tries = ([(0, True)] if warm is not None else []) + [(g, False) for g in range(len(guesses))]  # (guess, warm)
    for g_idx, warm_start in tries if guesses else []:
        guess_q, guess_tau = guesses[g_idx]
        t_start = time.perf_counter()  # the start point (lines from the guess) is set-up too
        x0_q = np.clip(guess_q, lo_q, hi_q)
        x0_tau = float(np.clip(guess_tau, tau_lo, tau_hi))
        x0 = np.concatenate([x0_q.ravel(), [x0_tau], _initial_lines(problem, active, x0_q).ravel()])
        start: dict[str, Any] = {"x0": x0}
        if warm_start:
            assert warm is not None
            had, x_old = _carried(warm["var_keys"], warm["x"], ex.var_keys)
            start = {
                "x0": np.where(had, np.clip(x_old, lbx, ubx), x0),
                "lam_x0": _carried(warm["var_keys"], warm["lam_x"], ex.var_keys)[1],
                "lam_g0": _carried(warm["row_keys"], warm["lam_g"], ex.row_keys)[1],
            }
        solver = solver_for(warm_start)
        t0 = time.perf_counter()
        build_s += t0 - t_start
        sol = solver(**start, lbx=lbx, ubx=ubx, lbg=np.concatenate(ex.lbg), ubg=np.concatenate(ex.ubg))
        solver_stats = solver.stats()
        x = np.array(sol["x"]).ravel()
        raw |= {
            "warm": {"x": x, "lam_x": np.array(sol["lam_x"]).ravel(), "lam_g": np.array(sol["lam_g"]).ravel(),
                     "var_keys": ex.var_keys, "row_keys": ex.row_keys},
            "q": x[:n_q].reshape(T + 1, n, 2),
            "tau": float(x[n_q]),
            "status": str(solver_stats.get("return_status", "unknown")),
            "iterations": raw["iterations"] + int(solver_stats.get("iter_count", 0)),
            "objective": float(sol["f"]),
            "solve_s": raw["solve_s"] + time.perf_counter() - t0,
        }
        raw["attempts"].append((warm_start, raw["status"], int(solver_stats.get("iter_count", 0)), time.perf_counter() - t0))
        if raw["status"] in _IPOPT_SUCCESS:
            break
    return raw, build_s


def _point_kinematics(problem: _Problem, q: Any) -> dict[str, Any]:
    r"""Every capsule end point at every knot, stacked ``(point, k, i)``: its position ``x``,
    ``y`` and their derivatives in the positioner's joints (``x_a`` = dx/dalpha, ``y_ab`` =
    d2y/dalpha dbeta, ...; zero in beta for a point on the alpha arm), for the separation rows
    and their derivatives (:func:`_separation`).

    With ``(u, w)`` the point's offset from its arm's joint (``d u(theta) + l u_perp(theta)``,
    ``theta`` = ``alpha + orient`` (+ ``beta`` on the beta arm)), ``d/dtheta (u, w) = (-w, u)``;
    on the beta arm the elbow ``l_1 u(alpha + orient)`` adds its own terms in alpha.
    """
    import casadi as ca

    sc, inst, pts = problem.scenario, problem.scenario.instrument, problem.points
    T = problem.steps
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
    lc, ls = inst.alpha_arm_mm * ca_, inst.alpha_arm_mm * sa_
    ex, ey = bx + lc, by + ls
    zero = ca.SX.zeros(alpha.shape[0])
    keys = ("x", "y", "x_a", "y_a", "x_b", "y_b", "x_aa", "y_aa", "x_ab", "y_ab", "x_bb", "y_bb")
    stacks: dict[str, list[Any]] = {key: [] for key in keys}
    for p in range(len(pts.arm)):
        x, y = pts.dist[p], pts.lateral[p]
        if pts.arm[p] == 1:
            u, w = x * cab - y * sab, x * sab + y * cab
            parts = (ex + x * cab - y * sab, ey + x * sab + y * cab, -ls - w, lc + u, -w, u, -lc - u, -ls - w, -u, -w, -u, -w)
        else:
            u, w = x * ca_ - y * sa_, x * sa_ + y * ca_
            parts = (bx + x * ca_ - y * sa_, by + x * sa_ + y * ca_, -w, u, zero, zero, -u, -w, zero, zero, zero, zero)
        for key, part in zip(keys, parts, strict=True):
            stacks[key].append(part)
    return {key: ca.vertcat(*parts) for key, parts in stacks.items()}


@dataclass
class _Derivative:
    """Sparse entries of a derivative as parallel lists: values (CasADi column vectors or
    constants), rows and columns (index arrays); for the Hessian of the Lagrangian, ``rows`` and
    ``cols`` are the two variables (each unordered pair once) and ``weights`` the multiplier of
    each entry (its row of ``g``, or -1 for the objective's)."""

    values: list[Any] = field(default_factory=list)
    rows: list[np.ndarray] = field(default_factory=list)
    cols: list[np.ndarray] = field(default_factory=list)
    weights: list[np.ndarray] = field(default_factory=list)

    def add(self, value: Any, row: np.ndarray, col: np.ndarray, weight: np.ndarray | None = None) -> None:
        self.values.append(value)
        self.rows.append(np.asarray(row, dtype=np.int64))
        self.cols.append(np.asarray(col, dtype=np.int64))
        self.weights.append(np.full(len(self.rows[-1]), -1, dtype=np.int64) if weight is None else np.asarray(weight, dtype=np.int64))


_WARM_MAX_NEW = 0.1
"""A lazy round starts warm when it adds at most this share of the last NLP's lines: where a
round added a third more (MOONS 7 seed 0: 2,444 -> 3,329; MOONS 19 seed 0: 5,196 -> 6,984), the
warm solve failed where the cold one converged; rounds that added 2-6 % (SDSS 7, MOONS 7 and 19)
converged warm in 10-90 iterations, against 30-340 cold."""

_WARM_IPOPT = {"warm_start_init_point": "yes", "mu_init": 1e-4, "warm_start_bound_push": 1e-6, "warm_start_mult_bound_push": 1e-6,
               "max_iter": 150}
"""IPOPT options for a lazy round started from the last round's solution and multipliers. A warm
start that has not converged in 150 iterations is given up for the cold solves: where a round
added many lines (MOONS 7 seed 0: 885 lines more, many of them violated at the start), the warm
solve ran into the wall-time limit (300 s) where the cold one took 110 s; where it helps, it
converges in 10-90 iterations (SDSS 7, MOONS 7 and 19)."""


def _carried(old_keys: np.ndarray, old_values: np.ndarray, new_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values of a previous NLP's rows or variables carried to a new one by key: ``(found, values)``,
    zero where the new NLP has a key the old one did not."""
    order = np.argsort(old_keys, kind="stable")
    sorted_keys = old_keys[order]
    pos = np.clip(np.searchsorted(sorted_keys, new_keys), 0, max(len(sorted_keys) - 1, 0))
    found = sorted_keys[pos] == new_keys if len(sorted_keys) else np.zeros(len(new_keys), dtype=bool)
    values = np.zeros(len(new_keys))
    values[found] = old_values[order][pos[found]]
    return found, values


def _separation(problem: _Problem, active: np.ndarray, q: Any, lines: Any, kin: dict[str, Any], first_row: int, jac: _Derivative,
                hess: _Derivative) -> tuple[Any, np.ndarray]:
    """The separating-line constraints of the ``active`` lines (each capsule end point of both
    sides at both knots of the interval, on its side of the line by its radius, half the margin and
    the chord allowance), rows ``first_row`` on of ``g``, and a key per row (its line, side,
    point and knot); their derivatives are added to ``jac`` and ``hess``.

    Row ``r``: ``g = s (n_x (x_p - m_x) + n_y (y_p - m_y) - c) - const - c_a (alpha_1 - alpha_0)^2
    - c_b (beta_1 - beta_0)^2`` with ``x_p`` the point at its knot (joints ``alpha_p, beta_p``, one
    of the interval's two knots). Its nonzero first derivatives: ``s (x_p - m_x)``, ``s (y_p -
    m_y)``, ``-s`` in the line's variables, ``s (n_x x_a + n_y y_a)`` (and in beta) in the
    point's joints, ``+-2 c_a (alpha_1 - alpha_0)`` (and beta) in the interval's; second:
    ``s x_a`` for (n_x, alpha_p) and the like, ``s (n_x x_aa + n_y y_aa)`` for (alpha_p, alpha_p)
    and the like, ``-+2 c_a`` for the interval's alphas (and betas).
    """
    import casadi as ca

    sc, st, pts = problem.scenario, problem.settings, problem.points
    n = problem.n
    n_q = (problem.steps + 1) * n * 2
    stride = (problem.steps + 1) * n  # points are stacked (point, k, i)
    nx, ny, cc = lines[0::3], lines[1::3], lines[2::3]
    k_l, p_l, c_l = active[:, 0], active[:, 1], active[:, 2]
    i_l, j_l = sc.pairs[p_l, 0], sc.pairs[p_l, 1]
    mid = 0.5 * (sc.base_xy[i_l] + sc.base_xy[j_l])
    rows_line, rows_point, rows_sign, rows_move = [], [], [], []
    for side, (pos, cap_col) in enumerate(((i_l, 0), (j_l, 1))):
        cap = problem.combos[c_l, cap_col]
        for p in range(len(pts.arm)):
            use = pts.body[p] == cap
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
    c_a, c_b = ca.DM(pts.chord_alpha[r_pid] * relief), ca.DM(pts.chord_beta[r_pid] * relief)
    chord = c_a * d_alpha**2 + c_b * d_beta**2
    at = r_point.tolist()
    px, py = kin["x"][at], kin["y"][at]
    nx_r, ny_r = nx[r_line.tolist()], ny[r_line.tolist()]
    dx, dy = px - ca.DM(mid[r_line, 0]), py - ca.DM(mid[r_line, 1])
    signed = nx_r * dx + ny_r * dy - cc[r_line.tolist()]
    sign = ca.DM(r_sign)
    g_sep = sign * signed - ca.DM(const) - chord

    # The variables of each row in z, and its derivatives.
    row = np.arange(len(r_line))
    line_var = n_q + 1 + 3 * r_line
    knot = r_point % stride  # (k + dk) * n + positioner: the point's joints are z[2 knot], z[2 knot + 1]
    var = {"nx": line_var, "ny": line_var + 1, "c": line_var + 2, "ap": 2 * knot, "bp": 2 * knot + 1,
           "a0": r_move, "b0": r_move + 1, "a1": r_move + 2 * n, "b1": r_move + 2 * n + 1}
    on_beta = np.flatnonzero(pts.arm[r_pid] == 1)
    d = {key: kin[key][at] for key in ("x_a", "y_a", "x_b", "y_b", "x_aa", "y_aa", "x_ab", "y_ab", "x_bb", "y_bb")}

    def entry(value: Any, first: str | None, second: str, beta_only: bool = False) -> None:
        """A Jacobian entry (``first`` None) or a Hessian entry of every row (of the rows whose
        point is on the beta arm)."""
        pick = on_beta if beta_only else row
        value = value[pick.tolist()] if beta_only else value
        if first is None:
            jac.add(value, first_row + pick, var[second][pick])
        else:
            hess.add(value, var[first][pick], var[second][pick], first_row + pick)

    entry(sign * dx, None, "nx")
    entry(sign * dy, None, "ny")
    entry(-sign, None, "c")
    entry(sign * (nx_r * d["x_a"] + ny_r * d["y_a"]), None, "ap")
    entry(sign * (nx_r * d["x_b"] + ny_r * d["y_b"]), None, "bp", beta_only=True)
    entry(2 * c_a * d_alpha, None, "a0")
    entry(-2 * c_a * d_alpha, None, "a1")
    entry(2 * c_b * d_beta, None, "b0")
    entry(-2 * c_b * d_beta, None, "b1")
    entry(sign * d["x_a"], "nx", "ap")
    entry(sign * d["y_a"], "ny", "ap")
    entry(sign * d["x_b"], "nx", "bp", beta_only=True)
    entry(sign * d["y_b"], "ny", "bp", beta_only=True)
    entry(sign * (nx_r * d["x_aa"] + ny_r * d["y_aa"]), "ap", "ap")
    entry(sign * (nx_r * d["x_ab"] + ny_r * d["y_ab"]), "ap", "bp", beta_only=True)
    entry(sign * (nx_r * d["x_bb"] + ny_r * d["y_bb"]), "bp", "bp", beta_only=True)
    entry(-2 * c_a, "a0", "a0")
    entry(-2 * c_a, "a1", "a1")
    entry(2 * c_a, "a0", "a1")
    entry(-2 * c_b, "b0", "b0")
    entry(-2 * c_b, "b1", "b1")
    entry(2 * c_b, "b0", "b1")
    dk = knot // n - k_l[r_line]
    side = (r_sign < 0).astype(np.int64)
    keys = ((_line_codes(problem, active)[r_line] * 2 + side) * len(pts.arm) + r_pid) * 2 + dk
    return g_sep, keys


def _derivatives(ex: _Expressions) -> dict[str, Any]:
    """IPOPT's derivative functions (``grad_f``, ``jac_g``, ``hess_lag``: the Hessian of
    ``lam_f f + lam_g' g``, upper triangle) of the NLP ``ex``, and the nlpsol options that use
    them.

    CasADi's own differentiation of the whole problem colours the Hessian (each line's variables
    meet the joints of two positioners at two knots: over a hundred colours) and sweeps the whole
    expression graph once per colour; with the Jacobian and a gradient of the Lagrangian for
    multipliers fiberplan does not read (``no_nlp_grad``), that was most of the set-up of each NLP
    (0.2-0.4 s on SDSS 7). Here the entries are written out (:func:`_expressions`,
    :func:`_separation`) and summed into place by one sparse product each; only the objective's
    gradient is CasADi's.
    """
    import casadi as ca

    z, objective, g = ex.z, ex.objective, ca.vertcat(*ex.g_parts)
    n_z, n_g = z.shape[0], g.shape[0]
    lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", n_g)
    jac = _scatter(ca.vertcat(*ex.jac.values), np.concatenate(ex.jac.rows), np.concatenate(ex.jac.cols), (n_g, n_z))
    a, b = np.concatenate(ex.hess.rows), np.concatenate(ex.hess.cols)
    weights = ca.vertcat(lam_f, lam_g)[(np.concatenate(ex.hess.weights) + 1).tolist()]
    hess = _scatter(ca.vertcat(*ex.hess.values) * weights, np.minimum(a, b), np.maximum(a, b), (n_z, n_z))
    no_p = ca.SX.sym("p", 0)
    return {
        "grad_f": ca.Function("nlp_grad_f", [z, no_p], [objective, ca.gradient(objective, z)]),
        "jac_g": ca.Function("nlp_jac_g", [z, no_p], [g, jac]),
        "hess_lag": ca.Function("nlp_hess_l", [z, no_p, lam_f, lam_g], [hess]),
        "no_nlp_grad": True,
        "calc_lam_p": False,
    }


def _scatter(values: Any, row: np.ndarray, col: np.ndarray, shape: tuple[int, int]) -> Any:
    """The sparse matrix of ``shape`` whose entry ``(row[e], col[e])`` is the sum of the
    ``values[e]`` that land on it (one constant sparse product)."""
    import casadi as ca

    keys, slot = np.unique(col * shape[0] + row, return_inverse=True)  # CasADi's order: by column, then row
    gather = ca.DM(ca.Sparsity.triplet(len(keys), len(row), slot.tolist(), list(range(len(row)))), 1.0)
    pattern = ca.Sparsity.triplet(shape[0], shape[1], (keys % shape[0]).tolist(), (keys // shape[0]).tolist())
    return ca.SX(pattern, ca.mtimes(gather, values))


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
    sag_max = np.array([pts.sagitta[pts.body == c].max() for c in range(int(problem.bodies.of_capsule.max()) + 1)])
    demand = st.margin_mm + (sag_max[cap_i] + sag_max[cap_j]) * (2.0 * problem.lower_bound_s / problem.steps) ** 2
    for end, k_end in ((0, 0), (1, problem.steps - 1)):
        at_end = k_l == k_end
        clear = np.maximum(problem.end_clearance[end, p_l, c_l], 0.0)
        factor = np.minimum(1.0, 0.5 * clear / np.maximum(demand, 1e-12))
        relief = np.where(at_end, np.minimum(relief, factor), relief)
    return relief


def _initial_lines(problem: _Problem, active: np.ndarray, guess_q: np.ndarray) -> np.ndarray:
    """Separating lines ``(L, 3)`` (``n_x, n_y, c``, with ``c`` relative to the pair's mid-base) from the guess.

    The normal is the direction between the closest points of the two bodies at the knot
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
    # The capsule pairs of each line's body pair (a body's capsules share one radius, so the
    # closest segments are the closest pair of the bodies' edges).
    capsule_combos = np.array(inst.capsule_pairs, dtype=np.int64).reshape(-1, 2)
    members = [np.flatnonzero(problem.bodies.of_combo == b) for b in range(len(problem.combos))]
    for dk in (0, 1):
        kk = k_l + dk
        for r in range(max(len(m) for m in members)):  # the r-th capsule pair of every line's body pair
            combo_r = np.array([m[r] if len(m) > r else -1 for m in members])[c_l]
            rows = np.flatnonzero(combo_r >= 0)
            ca, cb = capsule_combos[combo_r[rows], 0], capsule_combos[combo_r[rows], 1]
            p0, p1 = seg_start[kk[rows], i_l[rows], ca], seg_end[kk[rows], i_l[rows], ca]
            q0, q1 = seg_start[kk[rows], j_l[rows], cb], seg_end[kk[rows], j_l[rows], cb]
            dist, s, t = segment_distance(p0, p1, q0, q1)
            direction = (p0 + s[:, None] * (p1 - p0)) - (q0 + t[:, None] * (q1 - q0))
            better = dist < best[rows]
            normals[rows[better]] = direction[better]
            best[rows] = np.minimum(best[rows], dist)
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
            on_i = pts.body[p] == cap_i
            proj_i = np.einsum("li,li->l", normals, pos[kk, i_l, p] - mid) - pts.radius[p]
            lo_i = np.where(on_i, np.minimum(lo_i, proj_i), lo_i)
            on_j = pts.body[p] == cap_j
            proj_j = np.einsum("li,li->l", normals, pos[kk, j_l, p] - mid) + pts.radius[p]
            hi_j = np.where(on_j, np.maximum(hi_j, proj_j), hi_j)
    return np.column_stack([normals, 0.5 * (lo_i + hi_j)])


def _activate(problem: _Problem, joints: np.ndarray, window: int) -> np.ndarray:
    """Active-line mask ``(T, P, B)`` from a guess, dilated by ``window`` intervals in time."""
    close = _close_intervals(problem, joints, problem.settings.activate_mm)
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
    attempts: list[tuple[int, bool, str, int, float]] = []
    previous_lines = 0
    q, tau = guess_q, guess_tau
    raw: dict[str, Any] = {}
    for _ in range(st.lazy_rounds + 1):
        active = np.argwhere(mask)
        # A lazy round starts from the last solution, where the bodies of its new lines may touch
        # or overlap; if IPOPT finds no way out from there, the same NLP is solved from the
        # candidate's warm start (a planner's verified trajectory is apart everywhere) before
        # the candidate is given up.
        guesses = [(q, tau)] if rounds == 0 else [(q, tau), (guess_q, guess_tau)]
        # Warm only when the round adds few lines (_WARM_MAX_NEW of the last NLP's).
        warm = raw.get("warm") if rounds and st.warm_rounds and len(active) <= (1 + _WARM_MAX_NEW) * previous_lines else None
        previous_lines = len(active)
        raw, b_s = _solve_nlp(problem, active, guesses, warm)
        attempts += [(rounds, *attempt) for attempt in raw["attempts"]]
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
        if rounds > st.lazy_rounds:  # no round left: the last solve did not have these lines
            break
        mask = mask | missing
    finite = bool(np.all(np.isfinite(q)) and np.isfinite(tau))
    # Converged: IPOPT succeeded with every line the solution needs (the mask of the last solve).
    converged = finite and raw["status"] in _IPOPT_SUCCESS and not (_close_intervals(problem, q, st.activate_mm) & ~mask).any()
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
        attempts=attempts,
    )


def _exact_makespan(problem: _Problem, q: np.ndarray, tau: float) -> float:
    """Final time of the knots ``q``: ``tau t_LB``, lengthened if rounding left any joint too fast."""
    T = problem.steps
    tf = tau * problem.lower_bound_s
    needed = float((np.abs(np.diff(q, axis=0)) / problem.scenario.instrument.speeds_rad_s).max()) * T if T else 0.0
    return max(tf, needed * (1 + 1e-9))
