"""Routes: waypoints a positioner follows instead of its straight move.

A route comes from the start schedule (an L-shaped move's corner, a timed path with a
departure step per waypoint) or from the deadlock resolution (a detour, a pair resolution's
way to and from a waiting place). :class:`RouteBook` holds every positioner's current route;
the loop asks it where each positioner is heading, whether one holds at a waypoint until its
departure, and the time-to-go along a route (so that an L-shaped move's first leg, which need
not bring the slower joint closer to its target, is not taken for a deadlock).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

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
    # Two joints: plain floats, the same IEEE operations as the numpy form (``p + clip(r - p,
    # -s, s)``, the pass test ``|p - r| <= ROUTE_PASS * s``), without numpy's per-call overhead
    # on 2-element arrays (this runs for every positioner on a route at every step).
    out = np.empty((n_steps, 2))
    p0, p1 = float(q[0]), float(q[1])
    s0, s1 = float(step_rad[0]), float(step_rad[1])
    pass0, pass1 = float(ROUTE_PASS * step_rad[0]), float(ROUTE_PASS * step_rad[1])
    way = np.asarray(route, dtype=float).tolist()
    times = None if depart is None else np.asarray(depart).tolist()
    last = len(way) - 1
    for k in range(n_steps):
        while pos < last and abs(p0 - way[pos][0]) <= pass0 and abs(p1 - way[pos][1]) <= pass1 and (times is None or step + k >= times[pos + 1]):
            pos += 1
        if times is None or step + k >= times[pos]:
            r0, r1 = way[pos]
            p0 = p0 + min(max(r0 - p0, -s0), s0)
            p1 = p1 + min(max(r1 - p1, -s1), s1)
        out[k, 0] = p0
        out[k, 1] = p1
    return out


@dataclass
class Route:
    """One positioner's route.

    Attributes:
        waypoints: ``(W, 2)`` joint configurations, the last one where the route ends.
        pos: index of the waypoint it heads for.
        depart: timed routes only: control step at which it may leave for each waypoint.
    """

    waypoints: np.ndarray
    pos: int = 0
    depart: np.ndarray | None = None
    _tail: np.ndarray | None = field(default=None, repr=False)

    def tail_s(self, goal: np.ndarray, speeds: np.ndarray) -> np.ndarray:
        """Time from each waypoint on to ``goal`` along the route, every joint at full speed (cached)."""
        if self._tail is None:
            legs = np.max(np.abs(np.diff(np.vstack([self.waypoints, goal]), axis=0)) / speeds, axis=1)
            self._tail = np.append(np.cumsum(legs[::-1])[::-1], 0.0)
        return self._tail


class RouteBook:
    """The routes of every positioner that follows one (at most one each)."""

    def __init__(self) -> None:
        self._routes: dict[int, Route] = {}

    def __contains__(self, who: int) -> bool:
        return who in self._routes

    def __len__(self) -> int:
        return len(self._routes)

    def __iter__(self) -> Iterator[int]:
        return iter(self._routes)

    def __getitem__(self, who: int) -> Route:
        return self._routes[who]

    def follow(self, who: int, waypoints: np.ndarray, depart: np.ndarray | None = None) -> None:
        """``who`` follows ``waypoints`` from the first one (replacing any route it had)."""
        self._routes[who] = Route(waypoints, 0, depart)

    def drop(self, who: int) -> None:
        """``who`` follows no route any more (nothing happens if it had none)."""
        self._routes.pop(who, None)

    def heading(self, who: int) -> np.ndarray:
        """The waypoint ``who`` heads for."""
        route = self._routes[who]
        return route.waypoints[route.pos]

    def waits_for_departure(self, who: int, step: int) -> bool:
        """A timed route whose next departure is later than ``step``."""
        route = self._routes[who]
        return route.depart is not None and route.pos + 1 < len(route.waypoints) and step < route.depart[route.pos + 1]

    def holding(self, step: int, q: np.ndarray, step_rad: np.ndarray, holding: np.ndarray) -> None:
        """Mark (in ``holding``) the positioners at a waypoint of a timed route until its next departure."""
        for who, route in self._routes.items():
            depart = route.depart
            if depart is None:
                continue
            pos = route.pos
            if pos + 1 < len(depart) and step < depart[pos + 1] and np.all(np.abs(q[who] - route.waypoints[pos]) <= ROUTE_PASS * step_rad):
                holding[who] = True

    def time_to_go(self, q: np.ndarray, goal: np.ndarray, speeds: np.ndarray, ttg: np.ndarray) -> np.ndarray:
        """``ttg`` (straight time-to-go) with each positioner on a route measured along it instead."""
        out = ttg.copy()
        for who, route in self._routes.items():
            pos = route.pos
            out[who] = np.max(np.abs(route.waypoints[pos] - q[who]) / speeds) + route.tail_s(goal[who], speeds)[pos]
        return out

    def reference(self, ref: np.ndarray, q: np.ndarray, unstarted: np.ndarray, step_rad: np.ndarray, step: int) -> None:
        """Overwrite the reference ``ref`` (N, H, 2) of every started positioner on a route with its path along it."""
        n_steps = ref.shape[1]
        for who, route in self._routes.items():
            # (A timed route holding at a waypoint follows its route: it shows the departure ahead.)
            if not unstarted[who]:
                ref[who] = route_path(q[who], route.waypoints, route.pos, step_rad, n_steps, route.depart, step)

    def passed(self, step: int, q: np.ndarray, step_rad: np.ndarray, leaving: np.ndarray) -> list[int]:
        """Advance the routes whose waypoint is passed; drop the routes of ``leaving`` positioners
        and the routes that end. Returns who passed a waypoint (progress)."""
        out = []
        for who in list(self._routes):
            route = self._routes[who]
            if leaving[who]:
                del self._routes[who]
            elif self.waits_for_departure(who, step):
                continue  # its next departure is later
            elif np.all(np.abs(q[who] - route.waypoints[route.pos]) <= ROUTE_PASS * step_rad):
                # A waypoint passed (within half a step: the QP rounds the corners of the
                # reference, which runs through the waypoints) counts as progress.
                route.pos += 1
                out.append(who)
                if route.pos == len(route.waypoints):
                    del self._routes[who]
        return out
