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
    cache: dict[Any, Any] = field(default_factory=dict)  # the NLPs' line-free part and line kernels (:func:`_base`, :func:`_kernel`)

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
    """The NLP of one set of active lines, symbolic (CasADi MX): the variables ``z`` (knots,
    ``tau``, three per line), the objective, the constraints ``g`` with their bounds, IPOPT's
    derivative functions (:func:`_expressions`), and a key per row and variable."""

    z: Any
    objective: Any
    g: Any
    lbg: np.ndarray
    ubg: np.ndarray
    functions: dict[str, Any]  # grad_f, jac_g, hess_lag
    row_keys: np.ndarray  # (n_g,) what each row of g is, the same key in every NLP of a scenario (:func:`_line_codes`)
    var_keys: np.ndarray  # (n_z,) what each variable is, likewise


def _line_codes(problem: _Problem, active: np.ndarray) -> np.ndarray:
    """``(L,)`` one integer per line (interval, pair, body pair), the same in every NLP of the problem."""
    return (active[:, 0] * len(problem.scenario.pairs) + active[:, 1]) * len(problem.combos) + active[:, 2]


_KIND = 1 << 56  # keys of rows and variables: kind * _KIND + code (speed rows and knots 0, separation 1, norm 2)


@dataclass(frozen=True)
class _Base:
    r"""The part of every NLP of a problem that does not depend on the lines, as CasADi
    functions of ``y = (q, tau)``, built once per problem: the objective and its gradient, the
    speed rows (their Jacobian is constant: ``jac_rows``, ``jac_cols``, ``jac_values``) and the
    objective's Hessian entries (``hess(y)`` at ``hess_rows``, ``hess_cols``).

    With ``S = \sum_m \Delta q_m^2`` over every joint and interval, ``h = \tau t_{LB} / T``, the
    objective is ``\tau + C S / \tau`` (time mode; energy mode: ``C S / \tau`` at a fixed
    ``\tau``), ``C = w_E T / (t_{LB} E_{ref})`` (energy mode: ``w_E`` = 1). Its Hessian:
    ``2 C / \tau`` times the chain's Laplacian in the knots (2 on the diagonal, 1 at the two ends,
    -1 between consecutive knots of a joint), ``-(C / \tau^2) dS/dq`` between ``q`` and ``\tau``,
    ``2 C S / \tau^3`` on ``\tau``. The speed rows ``\Delta q \mp \omega h`` are linear.
    """

    f_grad: Any
    g: Any
    hess: Any
    jac_rows: np.ndarray
    jac_cols: np.ndarray
    jac_values: np.ndarray
    hess_rows: np.ndarray
    hess_cols: np.ndarray

    @property
    def n_rows(self) -> int:
        return int(self.g.size1_out(0))


def _base(problem: _Problem) -> _Base:
    import casadi as ca

    if "base" in problem.cache:
        return problem.cache["base"]
    st, inst = problem.settings, problem.scenario.instrument
    T, n = problem.steps, problem.n
    n_q = (T + 1) * n * 2
    y = ca.SX.sym("y", n_q + 1)
    q, tau = y[:n_q], y[n_q]
    lb = problem.lower_bound_s
    h = tau * (lb / T)
    m = T * n * 2
    cur = np.arange(m)
    nxt = cur + n * 2
    dq = q[nxt] - q[cur]
    omega = np.tile(inst.speeds_rad_s, T * n)
    g_speed = ca.vertcat(dq - ca.DM(omega) * h, dq + ca.DM(omega) * h)
    jac_rows, jac_cols, jac_values = [], [], []
    for block, sign in ((0, -1.0), (1, 1.0)):
        rows = block * m + cur
        jac_rows += [rows, rows, rows]
        jac_cols += [nxt, cur, np.full(m, n_q)]
        jac_values += [np.ones(m), -np.ones(m), sign * omega * (lb / T)]
    energy = ca.sumsqr(dq) / h
    e_ref = problem.energy_ref if problem.energy_ref > 0 else 1.0
    if problem.tau_fixed is None:
        objective = tau + st.energy_weight * energy / e_ref
        c = st.energy_weight * T / (lb * e_ref)
    else:
        objective = energy / e_ref
        c = T / (lb * e_ref)
    ends = np.zeros((T + 1, n * 2))
    ends[[0, -1]] = 1.0  # the first and last knots are in one interval, the others in two
    zeros = ca.SX.zeros(n * 2)
    hess_values = ca.vertcat(
        (2 * c / tau) * ca.DM(2.0 - ends.ravel()),
        ca.DM.ones(m) * (-2 * c / tau),
        (-2 * c / tau**2) * (ca.vertcat(zeros, dq) - ca.vertcat(dq, zeros)),
        2 * c * ca.sumsqr(dq) / tau**3,
    )
    base = _Base(
        f_grad=ca.Function("base_f", [y], [objective, ca.gradient(objective, y)]),
        g=ca.Function("base_g", [y], [g_speed]),
        hess=ca.Function("base_h", [y], [hess_values]),
        jac_rows=np.concatenate(jac_rows), jac_cols=np.concatenate(jac_cols), jac_values=np.concatenate(jac_values),
        hess_rows=np.concatenate([np.arange(n_q), cur, np.arange(n_q), [n_q]]),
        hess_cols=np.concatenate([np.arange(n_q), nxt, np.full(n_q, n_q), [n_q]]),
    )
    problem.cache["base"] = base
    return base


@dataclass(frozen=True)
class _Kernel:
    """The rows of one line of one body pair, and their derivatives, as CasADi functions of the
    line's 11 variables ``v`` (:data:`_LINE_VARS`) and 9 constants ``p`` (the pair's mid-base,
    each positioner's base and orientation, the line's end relief): built once per body pair and
    mapped over the lines of an NLP (:func:`_expressions`).

    ``rows`` rows per line: the separation rows (``side``, ``point``, ``dk`` each) then the norm
    row; ``g(v, p)`` gives the rows, ``g_jac(v, p)`` the rows and the nonzeros of their Jacobian
    in ``v`` (at ``jac_rows``, ``jac_cols``), ``hess(v, p, lam)`` the nonzeros of the upper
    triangle of the Hessian of ``lam' g`` in ``v`` (at ``hess_a <= hess_b``).
    """

    rows: int
    side: np.ndarray
    point: np.ndarray
    dk: np.ndarray
    g: Any
    g_jac: Any
    hess: Any
    jac_rows: np.ndarray
    jac_cols: np.ndarray
    hess_a: np.ndarray
    hess_b: np.ndarray


_LINE_VARS = 11
"""A line's variables, in this order: alpha, beta of ``i`` at knots ``k`` and ``k + 1``, the same of ``j``, then ``n_x, n_y, c``."""


def _kernel(problem: _Problem, combo: int) -> _Kernel:
    r"""The separating-line rows of body pair ``combo`` for one line (each capsule end point of
    both sides at both knots of the interval, on its side of the line by its radius, half the
    margin and the chord allowance), its norm row, and their derivatives: CasADi's own
    differentiation of these few rows in the line's 11 variables, common subexpressions merged.

    Separation row: ``g = s (n_x (x_p - m_x) + n_y (y_p - m_y) - c) - r_p - m \rho / 2 - \rho (c_a
    (\alpha_1 - \alpha_0)^2 + c_b (\beta_1 - \beta_0)^2)`` with ``x_p`` the point at its knot,
    ``s`` = +1 on ``i``'s side and -1 on ``j``'s, ``\rho`` the line's end relief
    (:func:`_end_relief`); norm row: ``n_x^2 + n_y^2``.
    """
    import casadi as ca

    key = ("kernel", combo)
    if key in problem.cache:
        return problem.cache[key]
    inst, st, pts = problem.scenario.instrument, problem.settings, problem.points
    v = ca.SX.sym("v", _LINE_VARS)
    p = ca.SX.sym("p", 9)
    nx, ny, cc = v[8], v[9], v[10]
    mid_x, mid_y, relief = p[0], p[1], p[8]
    rows, side_of, point_of, dk_of = [], [], [], []
    for side in (0, 1):
        body = problem.combos[combo, side]
        a0, b0, a1, b1 = (v[4 * side + t] for t in range(4))
        bx, by, orient = p[2 + 3 * side], p[3 + 3 * side], p[4 + 3 * side]
        sign = 1.0 if side == 0 else -1.0
        trig = []  # cos, sin of alpha + orient and of alpha + orient + beta at both knots, once each
        for al, be in ((a0, b0), (a1, b1)):
            a = al + orient
            trig.append((ca.cos(a), ca.sin(a), ca.cos(a + be), ca.sin(a + be)))
        for pt in np.flatnonzero(pts.body == body):
            x, y = pts.dist[pt], pts.lateral[pt]
            chord = relief * (pts.chord_alpha[pt] * (a1 - a0) ** 2 + pts.chord_beta[pt] * (b1 - b0) ** 2)
            const = pts.radius[pt] + 0.5 * st.margin_mm * relief
            for dk, (c_a, s_a, c_ab, s_ab) in enumerate(trig):
                if pts.arm[pt] == 1:
                    px = bx + inst.alpha_arm_mm * c_a + x * c_ab - y * s_ab
                    py = by + inst.alpha_arm_mm * s_a + x * s_ab + y * c_ab
                else:
                    px = bx + x * c_a - y * s_a
                    py = by + x * s_a + y * c_a
                rows.append(sign * (nx * (px - mid_x) + ny * (py - mid_y) - cc) - const - chord)
                side_of.append(side)
                point_of.append(pt)
                dk_of.append(dk)
    rows.append(nx**2 + ny**2)
    g = ca.vertcat(*rows)
    jac = ca.jacobian(g, v)
    lam = ca.SX.sym("lam", g.shape[0])
    hess = ca.triu(ca.hessian(ca.dot(lam, g), v)[0])
    jac_rows, jac_cols = jac.sparsity().get_triplet()
    hess_a, hess_b = hess.sparsity().get_triplet()
    kernel = _Kernel(
        rows=g.shape[0], side=np.array(side_of), point=np.array(point_of), dk=np.array(dk_of),
        g=ca.Function("line_g", [v, p], [ca.cse(g)]),
        g_jac=ca.Function("line_g_jac", [v, p], ca.cse([g, ca.vertcat(*jac.nonzeros())])),
        hess=ca.Function("line_h", [v, p, lam], [ca.cse(ca.vertcat(*hess.nonzeros()))]),
        jac_rows=np.array(jac_rows), jac_cols=np.array(jac_cols), hess_a=np.array(hess_a), hess_b=np.array(hess_b),
    )
    problem.cache[key] = kernel
    return kernel


def _expressions(problem: _Problem, active: np.ndarray) -> _Expressions:
    """The NLP for the ``active`` lines (``(L, 3)`` rows ``k, pair, body pair``) and IPOPT's
    derivative functions (``grad_f``, ``jac_g``, ``hess_lag``: the Hessian of ``lam_f f +
    lam_g' g``, upper triangle).

    Nothing is differentiated or expanded per NLP: the lines of each body pair are one call of
    its kernel (:func:`_kernel`, built once per problem) mapped over them, on their variables
    gathered from ``z``, and the line-free part is :func:`_base`'s; each derivative's nonzeros
    are summed into place by one constant sparse product (a line's variables are distinct, and
    different lines' entries meet on the joints). An NLP of a lazy round is therefore a few
    index arrays and graph nodes, not a new expression graph (SDSS 7: 0.1-0.25 s against 0.5-0.9 s
    when its rows and derivatives were written out as expressions). Rows: the speed rows, the
    separation rows by side, point, knot and line, then the norm rows by line (the order of the
    keys, :data:`_KIND`).
    """
    import casadi as ca

    sc = problem.scenario
    T, n = problem.steps, problem.n
    n_q = (T + 1) * n * 2
    n_lines = len(active)
    n_z = n_q + 1 + 3 * n_lines
    base = _base(problem)
    z = ca.MX.sym("z", n_z)
    y = z[: n_q + 1]
    k_l, p_l, c_l = active[:, 0], active[:, 1], active[:, 2]
    i_l, j_l = sc.pairs[p_l, 0], sc.pairs[p_l, 1]
    codes = _line_codes(problem, active)
    relief = _end_relief(problem, active)
    n_points = len(problem.points.arm)

    # Each line's variables in z (_LINE_VARS order) and constants.
    def knot(k: np.ndarray, i: np.ndarray) -> np.ndarray:
        return (k * n + i) * 2

    var = np.stack([knot(k_l, i_l), knot(k_l, i_l) + 1, knot(k_l + 1, i_l), knot(k_l + 1, i_l) + 1,
                    knot(k_l, j_l), knot(k_l, j_l) + 1, knot(k_l + 1, j_l), knot(k_l + 1, j_l) + 1,
                    *(n_q + 1 + 3 * np.arange(n_lines) + t for t in range(3))])  # (11, L)
    mid = 0.5 * (sc.base_xy[i_l] + sc.base_xy[j_l])
    const = np.stack([mid[:, 0], mid[:, 1], sc.base_xy[i_l, 0], sc.base_xy[i_l, 1], sc.orient[i_l],
                      sc.base_xy[j_l, 0], sc.base_xy[j_l, 1], sc.orient[j_l], relief])  # (9, L)

    # Line by line ("lm" order): each body pair's lines are one mapped call of its kernel.
    g_lm, g_jac_lm, jnz_lm, jac_r, jac_c, hess_a, hess_b = [], [], [], [], [], [], []
    side, point, dk, line_of, kind = [], [], [], [], []
    groups = []
    first = 0
    for combo in np.unique(c_l):
        lines = np.flatnonzero(c_l == combo)
        kern = _kernel(problem, int(combo))
        count = len(lines)
        v_c = ca.reshape(z[var[:, lines].ravel(order="F").tolist()], _LINE_VARS, count)
        p_c = ca.DM(const[:, lines])
        args = (v_c, p_c)
        g_lm.append(ca.vec(kern.g.map(count)(*args)))
        g_c, jnz_c = kern.g_jac.map(count)(*args)
        g_jac_lm.append(ca.vec(g_c))
        jnz_lm.append(ca.vec(jnz_c))
        jac_r.append((first + np.arange(count)[None, :] * kern.rows + kern.jac_rows[:, None]).ravel(order="F"))
        jac_c.append(var[:, lines][kern.jac_cols].ravel(order="F"))
        a_glob, b_glob = var[:, lines][kern.hess_a], var[:, lines][kern.hess_b]
        hess_a.append(np.minimum(a_glob, b_glob).ravel(order="F"))
        hess_b.append(np.maximum(a_glob, b_glob).ravel(order="F"))
        for out, local in ((side, kern.side), (point, kern.point), (dk, kern.dk)):
            out.append(np.tile(np.append(local, 0), count))
        line_of.append(np.repeat(lines, kern.rows))
        kind.append(np.tile(np.append(np.ones(kern.rows - 1, np.int64), 2), count))
        groups.append((kern, count, args, first))
        first += kern.rows * count
    side, point, dk, line_of, kind, jac_r, jac_c = (_cat(x) for x in (side, point, dk, line_of, kind, jac_r, jac_c))
    # The rows in the order of every NLP before (and of the warm starts' keys): the separation
    # rows by side, point, knot, then line; then the norm rows by line.
    perm = np.lexsort((line_of, dk, point, side, kind))  # canonical row -> lm row
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    n_g = base.n_rows + len(perm)
    codes_r = codes[line_of]
    sep_keys = _KIND + ((codes_r * 2 + side) * n_points + point) * 2 + dk
    row_keys = np.concatenate([np.arange(base.n_rows), np.where(kind == 1, sep_keys, 2 * _KIND + codes_r)[perm]])
    half = base.n_rows // 2  # the speed rows: dq - omega h <= 0, then dq + omega h >= 0
    lbg = np.concatenate([np.full(half, -np.inf), np.zeros(half), np.where(kind == 1, 0.0, -np.inf)[perm]])
    ubg = np.concatenate([np.zeros(half), np.full(half, np.inf), np.where(kind == 1, np.inf, 1.0)[perm]])
    reorder = perm.tolist()
    g = ca.vertcat(base.g(y), ca.vertcat(*g_lm)[reorder]) if len(perm) else base.g(y)
    g_of_jac = ca.vertcat(base.g(y), ca.vertcat(*g_jac_lm)[reorder]) if len(perm) else base.g(y)
    jac = _scatter(ca.vertcat(ca.DM(base.jac_values), *jnz_lm), np.concatenate([base.jac_rows, base.n_rows + inv[jac_r]]),
                   np.concatenate([base.jac_cols, jac_c]), (n_g, n_z))
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_g)
    hess_values = [lam_f * base.hess(y)]
    for kern, count, args, start in groups:
        lam_c = ca.reshape(lam_g[(base.n_rows + inv[start : start + kern.rows * count]).tolist()], kern.rows, count)
        hess_values.append(ca.vec(kern.hess.map(count)(*args, lam_c)))
    hess = _scatter(ca.vertcat(*hess_values), np.concatenate([base.hess_rows, *hess_a]), np.concatenate([base.hess_cols, *hess_b]),
                    (n_z, n_z))
    objective, grad = base.f_grad(y)
    no_p = ca.MX.sym("p", 0)
    functions = {
        "grad_f": ca.Function("nlp_grad_f", [z, no_p], [objective, ca.vertcat(grad, ca.DM.zeros(3 * n_lines))]),
        "jac_g": ca.Function("nlp_jac_g", [z, no_p], [g_of_jac, jac]),
        "hess_lag": ca.Function("nlp_hess_l", [z, no_p, lam_f, lam_g], [hess]),
    }
    var_keys = np.concatenate([np.arange(n_q + 1), _KIND + (3 * codes[:, None] + np.arange(3)).ravel()])
    return _Expressions(z, objective, g, lbg, ubg, functions, row_keys, var_keys)


def _cat(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


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
    if st.max_cpu_s is not None:
        opts["ipopt"]["max_cpu_time"] = st.max_cpu_s
    # The derivatives IPOPT needs, assembled by :func:`_expressions`; only those.
    opts |= ex.functions | {"no_nlp_grad": True, "calc_lam_p": False}
    nlp = {"x": ex.z, "f": ex.objective, "g": ex.g}
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
        sol = solver(**start, lbx=lbx, ubx=ubx, lbg=ex.lbg, ubg=ex.ubg)
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


def _scatter(values: Any, row: np.ndarray, col: np.ndarray, shape: tuple[int, int]) -> Any:
    """The sparse matrix of ``shape`` whose entry ``(row[e], col[e])`` is the sum of the
    ``values[e]`` that land on it (one constant sparse product)."""
    import casadi as ca

    keys, slot = np.unique(col * shape[0] + row, return_inverse=True)  # CasADi's order: by column, then row
    gather = ca.DM(ca.Sparsity.triplet(len(keys), len(row), slot.tolist(), list(range(len(row)))), 1.0)
    pattern = ca.Sparsity.triplet(shape[0], shape[1], (keys % shape[0]).tolist(), (keys // shape[0]).tolist())
    return ca.MX(pattern, ca.mtimes(gather, values))


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
