"""Settings of the ``mpc`` planner: every field with its unit, valid range, group and doc.

The defaults a user gets are resolved in one place each: the numbers below (what every preset
runs), scaled to the instrument's control step where they are distances or times
(:meth:`MpcSettings.for_instrument`), then the instrument file's ``[planner_defaults.mpc]``
table, then the user's ``--set`` overrides. ``fiberplan planners --settings mpc --instrument
NAME`` prints the result and where each value came from.
"""

from __future__ import annotations

from dataclasses import dataclass

from fiberplan.errors import PlannerError
from fiberplan.geometry import default_safety_margin_mm, step_motion_mm
from fiberplan.instrument import Instrument
from fiberplan.planners import instrument_defaults
from fiberplan.planners.coordination.settings import RouteSettings
from fiberplan.settings import check_settings, setting

QP_SOLVERS = ("osqp", "clarabel", "proxqp", "daqp", "highs", "scs", "quadprog", "cvxopt", "piqp")


@dataclass(frozen=True)
class MpcSettings(RouteSettings):
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
    time_limit_s: float | None = setting(None, "stop here at the latest, replacing the two settings above (null: use them)", unit="s",
                                         low=0.0, high=1e5, low_open=True, optional=True, group="run", kind="float")
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
    motor_limits: bool = setting(True, "executed steps keep the instrument's motor limits (stop before reversing, speed change, ramps, "
                                 "minimum speed; no effect where the instrument states none)", group="safety")
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
    start_schedule: bool = setting(True, "before the first step, give positioners start delays so that their delayed straight "
                                   "moves keep margin_mm pairwise", group="schedule")
    schedule_delay_steps: int = setting(4, "granularity of the start delays", unit="steps", low=1, high=10000, group="schedule")
    schedule_slack: float = setting(1.2, "every delayed move must end by this many times the longest move", low=1.0, high=100.0,
                                    group="schedule")
    schedule_l_paths: bool = setting(False, "a positioner no delay fits tries the two L-shaped moves (one joint, then the other)",
                                     group="schedule")
    schedule_space_time: bool = setting(True, "a positioner still unplaced searches a timed path through its joint grid x time",
                                        group="schedule")
    schedule_cell_steps: int = setting(16, "full-speed control steps per grid cell and time layer of that search", unit="steps",
                                       low=1, high=1000, group="schedule")
    schedule_repair: bool = setting(True, "a positioner no timed path fits goes first; a placed neighbour is placed again after it",
                                    group="schedule")
    schedule_pairs: bool = setting(False, "a positioner the schedule's other passes leave unplaced searches timed paths together "
                                   "with a placed neighbour (joint grid x joint grid x time)", group="schedule")
    schedule_pairs_retry: float = setting(1.5, "with route = auto, an unfold whose reversed fold leaves positioners short or ends "
                                          "later than this many lower bounds is planned again with schedule_pairs; the shorter "
                                          "kept (0: never)", low=0.0, high=100.0, group="route")
    # --- the route (fiberplan.planners.coordination; the other route settings: RouteSettings)
    route_fallback_planner: str | None = setting("dnf", "the planner of a leg's last attempts (up to two) when this one stalls, "
                                                 "and of the whole move when this one's routes fall short (null: none, "
                                                 "for studies of this planner alone)", choices=("mpc", "dnf", None), optional=True,
                                                 group="route")
    # --- the solver
    executor: str = setting("sequential", "where the QPs are solved", choices=("sequential", "parallel"), group="solver")
    workers: int = setting(2, "processes of the parallel executor (the planning process counts as one)", low=1, high=256,
                           group="solver")
    qp_solver: str = setting("osqp", "osqp (persistent workspaces, the fast path) or a qpsolvers backend", choices=QP_SOLVERS,
                             group="solver")
    osqp_eps: float = setting(1e-3, "OSQP absolute and relative tolerance", low=0.0, high=1.0, low_open=True, group="solver")
    osqp_max_iter: int = setting(400, "OSQP iteration limit per solve", low=1, high=1_000_000, group="solver")
    qp_screen_mm: float | None = setting(0.1, "a positioner in conflict whose reference keeps every constraint of its QP, the collision "
                                         "rows by at least this much, takes the reference without solving (null: every one solves)",
                                         unit="mm", low=0.0, high=100.0, optional=True, group="solver",
                                         kind="float")

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
        step_mm = step_motion_mm(instrument, dt)
        defaults = cls(
            dt_s=dt,
            margin_mm=round(1.2 * step_mm, 4),
            priority_margin_mm=round(0.4 * step_mm, 4),
            safety_margin_mm=default_safety_margin_mm(instrument),
            conflict_radius_mm=round(4.0 * step_mm, 4),
            qp_screen_mm=round(0.4 * step_mm, 4),
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

