"""The mpc control loop's compiled per-step loops and its route book answer as the numpy forms
they replace, bit for bit (so that no trajectory changes)."""

from __future__ import annotations

import numpy as np
import pytest

from fiberplan.kinematics import straight_path
from fiberplan.planners.mpc.grid import dilate
from fiberplan.planners.mpc.kernels import resting, straight_reference, time_to_go
from fiberplan.planners.mpc.routes import ROUTE_PASS, RouteBook, route_path
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


def test_time_to_go_and_resting_are_the_numpy_forms_bit_for_bit():
    rng = np.random.default_rng(3)
    q, goal = _configurations(rng, 2000)
    speeds = np.array([0.3, 0.45])
    assert time_to_go(q, goal, speeds).tobytes() == np.max(np.abs(goal - q) / speeds, axis=1).tobytes()
    plan = np.repeat(q[:, None, :], 4, axis=1)
    moving = rng.random(len(q)) < 0.3
    plan[moving, rng.integers(0, 4, moving.sum())] += 1e-9
    home = rng.random(len(q)) < 0.5
    goal[home] = q[home]  # at the goal: resting unless the plan moves
    expected = np.all(q == goal, axis=1) & np.all(plan == q[:, None, :], axis=(1, 2))
    np.testing.assert_array_equal(resting(q, goal, plan), expected)


class _OneByOne:
    """The route book's answers asked of each route alone (its form before the packed arrays)."""

    def __init__(self, routes: dict[int, tuple[np.ndarray, np.ndarray | None]]) -> None:
        self.routes = {w: [way, 0, dep] for w, (way, dep) in routes.items()}

    def waits(self, w: int, step: int) -> bool:
        way, pos, dep = self.routes[w]
        return dep is not None and pos + 1 < len(way) and step < dep[pos + 1]

    def holding(self, step, q, holding):
        for w, (way, pos, dep) in self.routes.items():
            if self.waits(w, step) and np.all(np.abs(q[w] - way[pos]) <= ROUTE_PASS * STEP):
                holding[w] = True

    def time_to_go(self, q, goal, speeds, ttg):
        out = ttg.copy()
        for w, (way, pos, _) in self.routes.items():
            legs = np.max(np.abs(np.diff(np.vstack([way, goal[w]]), axis=0)) / speeds, axis=1)
            tail = np.append(np.cumsum(legs[::-1])[::-1], 0.0)
            out[w] = np.max(np.abs(way[pos] - q[w]) / speeds) + tail[pos]
        return out

    def reference(self, ref, q, unstarted, step):
        for w, (way, pos, dep) in self.routes.items():
            if not unstarted[w]:
                ref[w] = route_path(q[w], way, pos, STEP, ref.shape[1], dep, step)

    def passed(self, step, q, leaving):
        out = []
        for w in list(self.routes):
            way, pos, _ = self.routes[w]
            if leaving[w]:
                del self.routes[w]
            elif self.waits(w, step):
                continue
            elif np.all(np.abs(q[w] - way[pos]) <= ROUTE_PASS * STEP):
                self.routes[w][1] += 1
                out.append(w)
                if self.routes[w][1] == len(way):
                    del self.routes[w]
        return out


def test_the_route_book_answers_as_each_route_asked_alone():
    rng = np.random.default_rng(11)
    n, n_steps = 300, 4
    routes: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
    for w in rng.choice(n, 120, replace=False).tolist():
        m = int(rng.integers(1, 6))
        way = np.cumsum(rng.uniform(-2.5, 2.5, (m, 2)) * STEP, axis=0) + rng.uniform(-1, 1, 2)
        dep = np.sort(rng.integers(0, 30, m)) if rng.random() < 0.5 else None
        routes[w] = (way, dep)
    book, alone = RouteBook(), _OneByOne(routes)
    for w, (way, dep) in routes.items():
        book.follow(w, way, dep)
    goal = rng.uniform(-1, 1, (n, 2))
    speeds = STEP / 0.1
    q = rng.uniform(-1, 1, (n, 2))
    for w, (way, _) in routes.items():
        q[w] = way[0] + rng.uniform(-1.5, 1.5, 2) * STEP
    passes, holds = 0, 0
    for step in range(40):
        unstarted = rng.random(n) < 0.1
        held_a, held_b = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        book.holding(step, q, STEP, held_a)
        alone.holding(step, q, held_b)
        np.testing.assert_array_equal(held_a, held_b)
        holds += int(held_a.sum())
        ttg = rng.random(n)
        assert book.time_to_go(q, goal, speeds, ttg).tobytes() == alone.time_to_go(q, goal, speeds, ttg).tobytes()
        ref_a = np.repeat(q[:, None, :], n_steps, axis=1)
        ref_b = ref_a.copy()
        book.reference(ref_a, q, unstarted, STEP, step)
        alone.reference(ref_b, q, unstarted, step)
        assert ref_a.tobytes() == ref_b.tobytes()
        heading_a = goal.copy()
        book.headings(heading_a, held_a)
        heading_b = goal.copy()
        for w, (way, pos, _) in alone.routes.items():
            if not held_b[w]:
                heading_b[w] = way[pos]
        np.testing.assert_array_equal(heading_a, heading_b)
        leaving = rng.random(n) < 0.02
        passed = book.passed(step, q, STEP, leaving)
        assert passed == alone.passed(step, q, leaving)
        passes += len(passed)
        assert list(book) == list(alone.routes)
        q = ref_a[:, 0]  # everyone on a route moves along it
    assert passes > len(routes) and holds > 0 and len(book) < len(routes)  # the cases were met


def test_a_timed_route_needs_a_departure_per_waypoint():
    with pytest.raises(ValueError, match="positioner 7"):
        RouteBook().follow(7, np.zeros((3, 2)), np.zeros(2, dtype=np.int64))


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
