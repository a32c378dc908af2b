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

from fiberplan.errors import PlannerError
from fiberplan.planners.mpc.kernels import route_paths

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


@dataclass(frozen=True)
class _Packed:
    """Every route of a :class:`RouteBook` in flat arrays, in the book's order, for the per-step
    questions asked of all of them at once.

    Attributes:
        who: ``(R,)`` the positioners.
        n_way: ``(R,)`` waypoints per route.
        offsets: ``(R + 1,)`` where each route's waypoints start in ``way``.
        way: ``(W, 2)`` every route's waypoints, one route after the other.
        depart: ``(W,)`` the departure steps of the timed routes (float; 0 for the others).
        timed: ``(R,)`` whether a route has departure steps.
    """

    who: np.ndarray
    n_way: np.ndarray
    offsets: np.ndarray
    way: np.ndarray
    depart: np.ndarray
    timed: np.ndarray


class RouteBook:
    """The routes of every positioner that follows one (at most one each).

    The questions asked at every control step (who holds, the time-to-go, the references, who
    passed a waypoint, where each heads) are answered for every route at once from flat arrays
    (:class:`_Packed`, rebuilt when a route starts or ends); the answers are those of asking
    each route alone, bit for bit (``tests/test_mpc_kernels.py``). With 50,000 DESI positioners about
    500 follow a route at any step.
    """

    def __init__(self) -> None:
        self._routes: dict[int, Route] = {}
        self._packed: _Packed | None = None

    def __contains__(self, who: int) -> bool:
        return who in self._routes

    def __len__(self) -> int:
        return len(self._routes)

    def __iter__(self) -> Iterator[int]:
        return iter(self._routes)

    def __getitem__(self, who: int) -> Route:
        """``who``'s route, to read: a route changes only through :meth:`follow`, :meth:`drop`
        and :meth:`passed` (the packed arrays would not see another change)."""
        return self._routes[who]

    def follow(self, who: int, waypoints: np.ndarray, depart: np.ndarray | None = None) -> None:
        """``who`` follows ``waypoints`` ``(M >= 1, 2)`` from the first one, leaving waypoint ``m``
        no earlier than control step ``depart[m]`` if given (replacing any route it had).

        Raises:
            PlannerError: ``waypoints`` is not ``(M >= 1, 2)``, or ``depart`` has not ``M`` steps.
        """
        shape = np.shape(waypoints)
        if len(shape) != 2 or shape[0] < 1 or shape[1] != 2:
            raise PlannerError(f"positioner {who}: a route needs waypoints of shape (M >= 1, 2), got {shape}")
        if depart is not None and len(depart) != shape[0]:
            raise PlannerError(f"positioner {who}: a timed route needs one departure step per waypoint "
                               f"({len(depart)} for {shape[0]} waypoints)")
        self._routes[who] = Route(waypoints, 0, depart)
        self._packed = None

    def drop(self, who: int) -> None:
        """``who`` follows no route any more (nothing happens if it had none)."""
        if self._routes.pop(who, None) is not None:
            self._packed = None

    # ------------------------------------------------------------------ every route at once
    def _pack(self) -> _Packed:
        """The routes packed (:class:`_Packed`), built again after a route starts (not empty)."""
        if self._packed is None:
            routes = list(self._routes.values())
            n = len(routes)
            n_way = np.fromiter((len(r.waypoints) for r in routes), np.int64, n)
            offsets = np.zeros(n + 1, dtype=np.int64)
            np.cumsum(n_way, out=offsets[1:])
            way = np.concatenate([np.asarray(r.waypoints, dtype=float) for r in routes])
            depart = np.concatenate([np.zeros(len(r.waypoints)) if r.depart is None else np.asarray(r.depart, dtype=float) for r in routes])
            timed = np.fromiter((r.depart is not None for r in routes), bool, n)
            self._packed = _Packed(np.fromiter(self._routes, np.int64, n), n_way, offsets, way, depart, timed)
        return self._packed

    def _state(self) -> tuple[_Packed, np.ndarray, np.ndarray]:
        """``(packed, pos, heading)``: each route's waypoint index and the waypoint it heads for."""
        pk = self._pack()
        pos = np.fromiter((r.pos for r in self._routes.values()), np.int64, len(pk.who))
        return pk, pos, pk.way[pk.offsets[:-1] + pos]

    @staticmethod
    def _waits(pk: _Packed, pos: np.ndarray, step: int) -> np.ndarray:
        """Whether each route is a timed one whose next departure is later than ``step``."""
        at = pk.offsets[:-1] + pos
        has_next = pos + 1 < pk.n_way
        return pk.timed & has_next & (step < pk.depart[np.where(has_next, at + 1, at)])

    def holding(self, step: int, q: np.ndarray, step_rad: np.ndarray, holding: np.ndarray) -> None:
        """Mark (in ``holding``) the positioners at a waypoint of a timed route until its next departure."""
        if not self._routes:
            return
        pk, pos, heading = self._state()
        waits = self._waits(pk, pos, step)
        at = np.all(np.abs(q[pk.who] - heading) <= ROUTE_PASS * step_rad, axis=1)
        holding[pk.who[waits & at]] = True

    def time_to_go(self, q: np.ndarray, goal: np.ndarray, speeds: np.ndarray, ttg: np.ndarray) -> np.ndarray:
        """``ttg`` (straight time-to-go) with each positioner on a route measured along it instead."""
        out = ttg.copy()
        if not self._routes:
            return out
        pk, _, heading = self._state()
        tails = np.fromiter((r.tail_s(goal[w], speeds)[r.pos] for w, r in self._routes.items()), float, len(pk.who))
        out[pk.who] = np.max(np.abs(heading - q[pk.who]) / speeds, axis=1) + tails
        return out

    def reference(self, ref: np.ndarray, q: np.ndarray, unstarted: np.ndarray, step_rad: np.ndarray, step: int) -> None:
        """Overwrite the reference ``ref`` (N, H, 2) of every started positioner on a route with
        its path along it (:func:`route_path`). (A timed route holding at a waypoint follows its
        route: it shows the departure ahead.)"""
        if not self._routes:
            return
        pk, pos, _ = self._state()
        route_paths(np.ascontiguousarray(q, dtype=float), pk.who, pos, pk.offsets, pk.way, pk.depart, pk.timed, unstarted,
                     np.asarray(step_rad, dtype=float), np.asarray(ROUTE_PASS * step_rad, dtype=float), step, ref)

    def headings(self, goal: np.ndarray, skip: np.ndarray) -> None:
        """Set ``goal`` of every positioner on a route, unless ``skip``-ped, to the waypoint it heads for."""
        if not self._routes:
            return
        pk, _, heading = self._state()
        keep = ~skip[pk.who]
        goal[pk.who[keep]] = heading[keep]

    def passed(self, step: int, q: np.ndarray, step_rad: np.ndarray, leaving: np.ndarray) -> list[int]:
        """Advance the routes whose waypoint is passed; drop the routes of ``leaving`` positioners
        and the routes that end. Returns who passed a waypoint (progress)."""
        if not self._routes:
            return []
        pk, pos, heading = self._state()
        waits = self._waits(pk, pos, step)
        leave = leaving[pk.who]
        # A waypoint passed (within half a step: the QP rounds the corners of the reference,
        # which runs through the waypoints) counts as progress; a timed route whose next
        # departure is later does not pass on.
        passing = ~leave & ~waits & np.all(np.abs(q[pk.who] - heading) <= ROUTE_PASS * step_rad, axis=1)
        for who in pk.who[leave].tolist():
            del self._routes[who]
        out = pk.who[passing].tolist()
        for who in out:
            self._routes[who].pos += 1
        ended = passing & (pos + 1 == pk.n_way)
        for who in pk.who[ended].tolist():
            del self._routes[who]
        gone = leave | ended
        if gone.any():  # the packed routes without those that ended (the book's order is kept)
            keep = ~gone
            n_way = pk.n_way[keep]
            offsets = np.zeros(len(n_way) + 1, dtype=np.int64)
            np.cumsum(n_way, out=offsets[1:])
            rows = np.repeat(keep, pk.n_way)
            self._packed = _Packed(pk.who[keep], n_way, offsets, pk.way[rows], pk.depart[rows], pk.timed[keep])
        return out
