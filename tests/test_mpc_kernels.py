"""The mpc control loop's compiled per-step loops and its route book answer as the numpy forms
they replace, bit for bit (so that no trajectory changes)."""

from __future__ import annotations

import numpy as np
import pytest

from fiberplan.errors import PlannerError
from fiberplan.kinematics import straight_path
from fiberplan.planners.mpc.grid import dilate
from fiberplan.planners.mpc.kernels import holds_at_goal, straight_reference, time_to_go
from fiberplan.planners.mpc.routes import ROUTE_PASS, Route, RouteBook, route_path
from fiberplan.planners.mpc.schedule import space_time_path

STEP = np.array([0.0101, 0.0173])


def _configurations(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Starts and goals with every case a step meets: goals far, within a step, equal, and signed zeros."""
    q = rng.uniform(-3.0, 3.0, (n, 2))
    goal = q + rng.choice([0.0, 1e-12, 0.003, 0.02, 0.5, -0.5], size=(n, 2)) * rng.uniform(0.5, 1.5, (n, 2))
    q[: n // 10] = -0.0
    goal[n // 20: n // 10] = 0.0
    return q, goal


@pytest.mark.parametrize("n_steps", [1, 4, 9])
def test_straight_reference_is_straight_path_bit_for_bit(n_steps):
    q, goal = _configurations(np.random.default_rng(n_steps), 2000)
    out = np.empty((len(q), n_steps, 2))
    straight_reference(q, goal, STEP, out)
    assert out.tobytes() == straight_path(q, goal, STEP, n_steps).tobytes()


def test_time_to_go_and_the_resting_test_are_the_numpy_forms_bit_for_bit():
    rng = np.random.default_rng(3)
    q, goal = _configurations(rng, 2000)
    speeds = np.array([0.3, 0.45])
    odd = q.copy()
    odd[rng.random(q.shape) < 0.05] = np.nan  # a NaN in either joint stays one, as np.max keeps it
    odd[rng.random(q.shape) < 0.02] = np.inf
    for config in (q, odd):
        assert time_to_go(config, goal, speeds).tobytes() == np.max(np.abs(goal - config) / speeds, axis=1).tobytes()
    plan = np.repeat(q[:, None, :], 4, axis=1)
    moving = np.flatnonzero(rng.random(len(q)) < 0.3)
    plan[moving, rng.integers(0, 4, len(moving)), rng.integers(0, 2, len(moving))] += 1e-9  # one joint at one step
    home = rng.random(len(q)) < 0.5
    goal[home] = q[home]  # at the goal: resting unless the plan moves
    goal[np.flatnonzero(home)[::7], 1] += 1e-12  # at the goal in alpha only
    expected = np.all(q == goal, axis=1) & np.all(plan == q[:, None, :], axis=(1, 2))
    assert 0 < expected.sum() < home.sum()
    np.testing.assert_array_equal(holds_at_goal(q, goal, plan), expected)


class _RouteBookBefore:
    """The route book as it was (``0b16285``): each route asked alone, in Python."""

    def __init__(self) -> None:
        self._routes: dict[int, Route] = {}

    def __iter__(self):
        return iter(self._routes)

    def follow(self, who, waypoints, depart=None) -> None:
        self._routes[who] = Route(waypoints, 0, depart)

    def drop(self, who) -> None:
        self._routes.pop(who, None)

    def heading(self, who) -> np.ndarray:
        route = self._routes[who]
        return route.waypoints[route.pos]

    def waits_for_departure(self, who, step) -> bool:
        route = self._routes[who]
        return route.depart is not None and route.pos + 1 < len(route.waypoints) and step < route.depart[route.pos + 1]

    def holding(self, step, q, step_rad, holding) -> None:
        for who, route in self._routes.items():
            depart = route.depart
            if depart is None:
                continue
            pos = route.pos
            if pos + 1 < len(depart) and step < depart[pos + 1] and np.all(np.abs(q[who] - route.waypoints[pos]) <= ROUTE_PASS * step_rad):
                holding[who] = True

    def time_to_go(self, q, goal, speeds, ttg) -> np.ndarray:
        out = ttg.copy()
        for who, route in self._routes.items():
            pos = route.pos
            out[who] = np.max(np.abs(route.waypoints[pos] - q[who]) / speeds) + route.tail_s(goal[who], speeds)[pos]
        return out

    def reference(self, ref, q, unstarted, step_rad, step) -> None:
        n_steps = ref.shape[1]
        for who, route in self._routes.items():
            if not unstarted[who]:
                ref[who] = route_path(q[who], route.waypoints, route.pos, step_rad, n_steps, route.depart, step)

    def passed(self, step, q, step_rad, leaving) -> list[int]:
        out = []
        for who in list(self._routes):
            route = self._routes[who]
            if leaving[who]:
                del self._routes[who]
            elif self.waits_for_departure(who, step):
                continue
            elif np.all(np.abs(q[who] - route.waypoints[route.pos]) <= ROUTE_PASS * step_rad):
                route.pos += 1
                out.append(who)
                if route.pos == len(route.waypoints):
                    del self._routes[who]
        return out


def _route(rng: np.random.Generator) -> tuple[object, object]:
    """Waypoints (float, coarse, float32 or a list) and departures (none, int, an int32 list or float)."""
    m = int(rng.integers(1, 6))
    way = np.cumsum(rng.uniform(-2.5, 2.5, (m, 2)) * STEP, axis=0) + rng.uniform(-1, 1, 2)
    kind = int(rng.integers(0, 4))
    if kind == 1:
        way = np.round(way, 2)
    way = way.astype(np.float32) if kind == 2 else way.tolist() if kind == 3 else way
    r = rng.random()
    dep = (np.sort(rng.integers(0, 40, m)) if r < 0.3 else np.sort(rng.integers(0, 40, m)).astype(np.int32).tolist() if r < 0.4
           else np.sort(rng.uniform(0, 40, m)) if r < 0.5 else None)
    return way, dep


@pytest.mark.parametrize("seed", range(8))
def test_the_route_book_answers_as_it_did_route_by_route(seed):
    # Routes start, are replaced and are dropped between the steps, after the packed arrays were
    # built; some positioners sit exactly on a waypoint or exactly half a step from one.
    rng = np.random.default_rng(seed)
    n, n_steps = 150, 4
    book, before = RouteBook(), _RouteBookBefore()
    goal = rng.uniform(-1, 1, (n, 2))
    speeds = STEP / 0.1
    q = rng.uniform(-1, 1, (n, 2))
    passes = holds = 0
    for step in range(40):
        for _ in range(int(rng.integers(0, 8 if step else 60))):
            who = int(rng.integers(n))
            if rng.random() < 0.2:
                book.drop(who)
                before.drop(who)
                continue
            way, dep = _route(rng)
            first = np.asarray(way, dtype=float)[0]
            q[who] = first + rng.choice([0.0, 0.5, -0.5, 1.5]) * STEP * rng.choice([0.0, 1.0], 2)  # on, at the pass boundary, or off
            book.follow(np.int64(who) if rng.random() < 0.5 else who, way, dep)
            before.follow(who, way, dep)
        unstarted = rng.random(n) < 0.1
        held, held_before = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        book.holding(step, q, STEP, held)
        before.holding(step, q, STEP, held_before)
        np.testing.assert_array_equal(held, held_before)
        holds += int(held.sum())
        ttg = rng.random(n)
        assert book.time_to_go(q, goal, speeds, ttg).tobytes() == before.time_to_go(q, goal, speeds, ttg).tobytes()
        wide = np.repeat(q[:, None, :], 2 * n_steps, axis=1)
        ref = wide[:, ::2]  # not contiguous: the columns between stay as they were
        ref_before = ref.copy()
        book.reference(ref, q, unstarted, STEP, step)
        before.reference(ref_before, q, unstarted, STEP, step)
        assert ref.tobytes() == ref_before.tobytes()
        assert np.all(wide[:, 1::2] == q[:, None, :])
        heading, heading_before = goal.copy(), goal.copy()
        book.headings(heading, held)
        for who in before:
            if not held_before[who]:
                heading_before[who] = before.heading(who)
        assert heading.tobytes() == heading_before.tobytes()
        leaving = rng.random(n) < 0.02
        passed = book.passed(step, q, STEP, leaving)
        assert passed == before.passed(step, q, STEP, leaving)
        assert list(book) == list(before)
        passes += len(passed)
        q = ref[:, 0].copy()  # everyone on a route moves along it
    assert passes > 40 and holds > 0  # the cases were met


def test_the_route_book_passes_a_waypoint_exactly_half_a_step_away_as_it_did():
    # The pass test (|q - waypoint| <= ROUTE_PASS x step) at its boundary, where the arithmetic is
    # exact: waypoints on the origin, positioners exactly half a step (or a hair more) away.
    half = ROUTE_PASS * STEP
    offsets = [half, -half, half * np.array([1.0, 0.0]), np.nextafter(half, 1.0), np.zeros(2)]
    book, before = RouteBook(), _RouteBookBefore()
    q = np.zeros((2 * len(offsets), 2))
    for k, off in enumerate(offsets):
        way = np.array([[0.0, 0.0], [0.05, -0.03], [0.05, 0.02]])
        for who, dep in ((2 * k, None), (2 * k + 1, np.array([0, 3, 5]))):
            q[who] = off
            book.follow(who, way, dep)
            before.follow(who, way, dep)
    unstarted = np.zeros(len(q), dtype=bool)
    for step in range(6):
        ref, ref_before = np.zeros((len(q), 4, 2)), np.zeros((len(q), 4, 2))
        book.reference(ref, q, unstarted, STEP, step)
        before.reference(ref_before, q, unstarted, STEP, step)
        assert ref.tobytes() == ref_before.tobytes()
        held, held_before = np.zeros(len(q), dtype=bool), np.zeros(len(q), dtype=bool)
        book.holding(step, q, STEP, held)
        before.holding(step, q, STEP, held_before)
        np.testing.assert_array_equal(held, held_before)
        leaving = np.zeros(len(q), dtype=bool)
        assert book.passed(step, q, STEP, leaving) == before.passed(step, q, STEP, leaving)
    assert ref[0, 0].tobytes() != ref[6, 0].tobytes()  # on the boundary it went on, a hair beyond it did not


def test_a_route_is_refused_unless_its_shape_and_departures_fit():
    with pytest.raises(PlannerError, match="positioner 7: a timed route needs one departure step per waypoint"):
        RouteBook().follow(7, np.zeros((3, 2)), np.zeros(2, dtype=np.int64))
    with pytest.raises(PlannerError, match=r"positioner 8: a route needs waypoints of shape \(M >= 1, 2\)"):
        RouteBook().follow(8, np.zeros((0, 2)))
    with pytest.raises(PlannerError, match="positioner 9"):
        RouteBook().follow(9, np.zeros(2))


def _space_time_path_numpy(free, start, goal):
    """The numpy form :func:`space_time_path` compiled (its code before)."""
    n_layers = free.shape[0]
    if not free[0][start]:
        return None
    reach = np.zeros_like(free)
    reach[0][start] = True
    stay = np.flip(np.logical_and.accumulate(np.flip(free[:, goal[0], goal[1]])))
    if not stay.any():
        return None
    arrive = 0
    while not (reach[arrive][goal] and stay[arrive]):
        arrive += 1
        if arrive == n_layers:
            return None
        reach[arrive] = dilate(reach[arrive - 1]) & free[arrive]
        if not reach[arrive].any():
            return None
    moves = np.array([(da, db) for da in (-1, 0, 1) for db in (-1, 0, 1)])
    cells = [np.array(goal)]
    s = np.array(start)
    for layer in range(arrive, 0, -1):
        cand = cells[-1] + moves
        inside = np.all((cand >= 0) & (cand < free.shape[1:]), axis=1)
        cand = cand[inside]
        cand = cand[reach[layer - 1][cand[:, 0], cand[:, 1]]]
        cells.append(cand[np.argmin(np.max(np.abs(cand - s), axis=1))])
    return np.array(cells[::-1])


def test_space_time_path_is_the_numpy_search_cell_for_cell():
    rng = np.random.default_rng(5)
    found = missed = 0
    for trial in range(400):
        layers, a, b = int(rng.integers(2, 40)), int(rng.integers(1, 14)), int(rng.integers(1, 14))
        free = rng.random((layers, a, b)) > rng.uniform(0.0, 0.6)
        start = (int(rng.integers(a)), int(rng.integers(b)))
        goal = (int(rng.integers(a)), int(rng.integers(b)))
        if trial % 4 == 0:
            free[:, start[0], start[1]] = True  # sometimes a way to wait and a goal to hold
            free[layers // 2:, goal[0], goal[1]] = True
        expected, got = _space_time_path_numpy(free, start, goal), space_time_path(free, start, goal)
        if expected is None:
            assert got is None
            missed += 1
        else:
            assert got is not None and got.dtype == expected.dtype
            np.testing.assert_array_equal(got, expected)
            found += 1
    assert found > 50 and missed > 50
