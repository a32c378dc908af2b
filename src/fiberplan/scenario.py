"""Scenarios: an instrument, its positioners, where they start and where they must go.

A :class:`Scenario` is validated when built: finite numbers, unique ids, starts inside the
hard stops and collision-free, targets inside the patrol region and reachable with the
requested parity, goal configuration collision-free. Its angles are kept in the file's
units (degrees) so that a scenario written and read again is bit-identical; the radian
arrays planners use are derived from them.

File format (JSON, one file; documented in the README)::

    {
      "format": "fiberplan-scenario", "version": 2,
      "name": "desi-500-random-seed1", "kind": "random", "seed": 1,
      "instrument": "desi",                      # a preset name, or the full instrument table
      "beta_convention": "extended",             # of the angles below; absent: the instrument's
      "positioners": [
        {"id": 0, "x_mm": 0.0, "y_mm": 0.0, "orient_deg": 0.0,
         "start_deg": [12.5, 140.0],
         "target": {"alpha_deg": 40.0, "beta_deg": 95.0}},      # joint-angle target
        {"id": 1, ..., "target": {"x_mm": 12.1, "y_mm": 3.0, "parity": 1}},  # fiber x/y target
        {"id": 2, ..., "target": null}                            # no target: stay put
      ]
    }

``parity`` is optional (``1`` or ``"R"``, ``-1`` or ``"L"``, or absent / ``0`` for "the faster
one"). ``beta_convention`` says how the file's beta angles are measured: ``"extended"`` (0 with the
arms in line) or ``"folded"`` (0 with the beta arm folded back, as MOONS' documents measure it);
absent, it is the instrument's (a version 1 file, written before the key existed: extended).
Scenarios are kept in the extended convention; messages print angles in the file's.
"""

from __future__ import annotations

import json
from dataclasses import InitVar, dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan._keys import check_keys
from fiberplan.errors import InstrumentError, ScenarioError
from fiberplan.geometry import min_pair_clearance
from fiberplan.instrument import Instrument
from fiberplan.instrument_io import instrument_from_dict, load_instrument
from fiberplan.kinematics import best_parity_joints, fiber_positions, inverse_kinematics, parity_of
from fiberplan.layout import neighbour_pairs

FORMAT_NAME = "fiberplan-scenario"
FORMAT_VERSION = 2
"""Version 2 added ``beta_convention`` (default: the instrument's); version 1 files are read as extended."""
READ_VERSIONS = (1, 2)
PARITY_NAMES = {"R": 1, "L": -1}
"""Parity by name: ``R`` = +1 (beta turned counterclockwise from the alpha arm: ``sin(beta) >= 0``), ``L`` = -1."""

TARGET_NONE = 0
TARGET_JOINTS = 1
TARGET_XY = 2

MAX_COORDINATE_MM = 1.0e5
"""Largest base coordinate accepted (100 m): larger values are a unit or typing error."""
MAX_SEED = 2**63 - 1
"""Seeds are stored as signed 64-bit integers (HDF5 attributes)."""

SCENARIO_KEYS = ("format", "version", "name", "kind", "seed", "instrument", "beta_convention", "meta", "positioners")
POSITIONER_KEYS = ("id", "x_mm", "y_mm", "orient_deg", "start_deg", "target", "locked")
JOINT_TARGET_KEYS = ("alpha_deg", "beta_deg", "priority")
XY_TARGET_KEYS = ("x_mm", "y_mm", "parity", "priority")


@dataclass(frozen=True, eq=False)
class Scenario:
    """An instrument, N positioners, their start configuration and their targets.

    Attributes:
        instrument: positioner geometry and limits.
        ids: ``(N,)`` positioner ids (unique integers).
        base_xy: ``(N, 2)`` base positions (mm).
        orient_deg: ``(N,)`` base orientations (deg).
        start_deg: ``(N, 2)`` start joint angles ``(alpha, beta)`` (deg).
        target_kind: ``(N,)`` 0 no target, 1 joint-angle target, 2 fiber x/y target.
        target_values: ``(N, 2)`` joint angles (deg) or fiber x/y (mm) by ``target_kind``;
            ignored rows hold zeros.
        target_parity: ``(N,)`` 0 (faster one), +1 or -1; used for x/y targets.
        name, kind, seed: provenance.
        instrument_preset: the preset name when the instrument is a preset (files then
            store the name); ``None`` stores the full geometry.
        meta: free-form, JSON-serialisable.
        locked: ``(N,)`` positioners that cannot move (static obstacles for everyone);
            default none.
        target_priority: ``(N,)`` 1 first, 2, 3, ...; 0 (default) after every numbered one.
            Where two targets cannot both be reached, the more important one keeps its target.
        angle_convention: the beta convention of the user's file (``"extended"`` or
            ``"folded"``): messages print angles in it. The arrays are always extended.
        validate_collisions: check that the start configuration is collision-free (default);
            the verifier turns it off to check a file against another geometry.

    Targets that cannot be reached at all do not reject the scenario: they are listed in
    :attr:`infeasible` with the reason (and the other positioner's id), and those positioners
    hold still while everyone else is planned.

    Raises:
        ScenarioError: on any invalid positioner; the message names its id and the fix.
    """

    instrument: Instrument
    ids: np.ndarray
    base_xy: np.ndarray
    orient_deg: np.ndarray
    start_deg: np.ndarray
    target_kind: np.ndarray
    target_values: np.ndarray
    target_parity: np.ndarray
    name: str = ""
    kind: str = "custom"
    seed: int | None = None
    instrument_preset: str | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    locked: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    target_priority: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    angle_convention: str = "extended"
    validate_collisions: InitVar[bool] = True

    def __post_init__(self, validate_collisions: bool) -> None:
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer))
                                      or not 0 <= int(self.seed) <= MAX_SEED):
            raise ScenarioError(f"scenario seed must be an integer from 0 to 2**63 - 1 or null, found {self.seed!r}")
        if not isinstance(self.meta, dict):
            raise ScenarioError(f"scenario meta must be a JSON object (a dict), found {type(self.meta).__name__}")
        for attr, dtype in (
            ("ids", np.int64),
            ("base_xy", float),
            ("orient_deg", float),
            ("start_deg", float),
            ("target_kind", np.int64),
            ("target_values", float),
            ("target_parity", np.int64),
            ("locked", bool),
            ("target_priority", np.int64),
        ):
            if attr in ("locked", "target_priority") and np.size(getattr(self, attr)) == 0:  # default: none locked, no priorities
                object.__setattr__(self, attr, np.zeros(len(np.atleast_1d(self.ids)), dtype=dtype))
            try:
                value = np.array(getattr(self, attr), dtype=dtype)
            except (TypeError, ValueError, OverflowError) as e:
                raise ScenarioError(f"scenario array {attr} must hold numbers ({e})") from e
            value.setflags(write=False)
            object.__setattr__(self, attr, value)
        self._validate(validate_collisions)

    # ------------------------------------------------------------------ derived arrays
    @property
    def n_positioners(self) -> int:
        """Number of positioners."""
        return len(self.ids)

    @cached_property
    def orient(self) -> np.ndarray:
        """Base orientations (rad)."""
        return np.radians(self.orient_deg)

    @cached_property
    def start(self) -> np.ndarray:
        """Start joint angles ``(N, 2)`` (rad)."""
        return np.radians(self.start_deg)

    @cached_property
    def pairs(self) -> np.ndarray:
        """Neighbour pairs ``(P, 2)`` whose capsules can ever touch."""
        return neighbour_pairs(self.instrument, self.base_xy)

    @cached_property
    def wants_target(self) -> np.ndarray:
        """Which positioners were given a target (feasible or not)."""
        return self.target_kind != TARGET_NONE

    @cached_property
    def has_target(self) -> np.ndarray:
        """Which positioners have a feasible target (the others hold still: no target, locked, infeasible)."""
        return self.wants_target & ~self.locked & ~np.isin(np.arange(self.n_positioners), list(self.infeasible))

    @cached_property
    def target(self) -> np.ndarray:
        """Goal joint angles ``(N, 2)`` (rad); the start for positioners without a feasible target."""
        return self._goals[0]

    @cached_property
    def infeasible(self) -> dict[int, str]:
        """Rows whose target cannot be reached at all, with the reason (naming the other positioner)."""
        return self._goals[1]

    @cached_property
    def _goals(self) -> tuple[np.ndarray, dict[int, str]]:
        goal = self._resolve_targets()
        return goal, self._feasibility(goal)

    @cached_property
    def target_xy(self) -> np.ndarray:
        """Goal fiber positions ``(N, 2)`` (mm)."""
        return fiber_positions(self.instrument, self.base_xy, self.orient, self.target)

    def index_of(self, positioner_id: int) -> int:
        """Row index of a positioner id."""
        rows = np.flatnonzero(self.ids == positioner_id)
        if len(rows) == 0:
            raise ScenarioError(f"positioner {positioner_id} is not in this scenario")
        return int(rows[0])

    # ------------------------------------------------------------------ validation
    def _resolve_targets(self) -> np.ndarray:
        inst = self.instrument
        goal = self.start.copy()
        joints_rows = self.target_kind == TARGET_JOINTS
        goal[joints_rows] = np.radians(self.target_values[joints_rows])
        xy_rows = np.flatnonzero(self.target_kind == TARGET_XY)
        if len(xy_rows):
            base, orient = self.base_xy[xy_rows], self.orient[xy_rows]
            xy = self.target_values[xy_rows]
            parity = self.target_parity[xy_rows]
            fixed = inverse_kinematics(inst, base, orient, xy, np.where(parity == 0, 1, parity))
            best = best_parity_joints(inst, base, orient, xy, self.start[xy_rows])
            goal[xy_rows] = np.where((parity == 0)[:, None], best, fixed)
            self._untangle_free_parities(goal, xy_rows[parity == 0])
        return goal

    def _feasibility(self, goal: np.ndarray) -> dict[int, str]:
        """Mark, in place on ``goal`` (set back to the start), every target that cannot be reached
        at all, and return the reasons: a locked positioner given a target; a target beyond a hard
        stop, outside the patrol region or unreachable with its parity; a goal that collides with
        another goal (both of the pair), or with a positioner that holds at its start (locked,
        without a target, or infeasible itself; repeated until no goal collides)."""
        inst = self.instrument
        reasons: dict[int, str] = {}
        ids = self.ids
        for k in np.flatnonzero(self.wants_target & self.locked):
            reasons[int(k)] = "locked: it cannot move"
        for k in np.flatnonzero((self.target_kind == TARGET_JOINTS) & ~inst.within_limits(goal)):
            reasons.setdefault(int(k), f"target joints {self.angles_text(self.target_values[k])} are beyond a hard stop "
                                       f"({self.limits_text()})")
        for k in np.flatnonzero((self.target_kind == TARGET_XY) & np.isnan(goal).any(axis=1)):
            radius = float(np.hypot(*(self.target_values[k] - self.base_xy[k])))
            lo, hi = inst.reach_min_mm, inst.reach_max_mm
            if not (lo - 1e-9 <= radius <= hi + 1e-9):
                why = f"target is {radius:.4f} mm from its base, outside the patrol region [{lo:.4f}, {hi:.4f}] mm"
            else:
                why = f"target cannot be reached with parity {self.target_parity[k]} inside the hard stops"
            reasons.setdefault(int(k), why)
        rows = list(reasons)
        goal[rows] = self.start[rows]
        pairs = self.pairs
        for _ in range(self.n_positioners + 1):
            if len(pairs) == 0:
                break
            clearance = min_pair_clearance(inst, self.base_xy, self.orient, goal, pairs)
            hit = np.flatnonzero(clearance < 0.0)
            if len(hit) == 0:
                break
            moving = self.wants_target & ~self.locked & ~np.isin(np.arange(self.n_positioners), list(reasons))
            new: dict[int, str] = {}
            for r in hit.tolist():
                i, j = int(pairs[r, 0]), int(pairs[r, 1])
                if moving[i] and moving[j]:
                    rank_i, rank_j = self.priority_rank[i], self.priority_rank[j]
                    losers = ((i, j), (j, i)) if rank_i == rank_j else (((j, i),) if rank_i < rank_j else ((i, j),))
                    for a, b in losers:
                        more = "" if rank_i == rank_j else " of higher priority"
                        new.setdefault(a, f"target collides with positioner {ids[b]}'s target{more} (overlap {-clearance[r]:.4f} mm)")
                else:
                    for a, b in ((i, j), (j, i)):
                        if moving[a]:
                            what = "locked" if self.locked[b] else ("without a target" if not self.wants_target[b] else "itself held")
                            new.setdefault(a, f"target collides with positioner {ids[b]} ({what}, holding at its start; "
                                              f"overlap {-clearance[r]:.4f} mm)")
            if not new:  # two positioners both holding at their starts: a start collision, refused elsewhere
                break
            reasons.update(new)
            goal[list(new)] = self.start[list(new)]
        return dict(sorted(reasons.items()))

    def angles_text(self, alpha_beta_deg: Any) -> str:
        """``[alpha, beta] deg`` (extended) as the user wrote them: in the file's convention, rounded."""
        alpha, beta = (float(v) for v in alpha_beta_deg)
        if self.angle_convention == "folded":
            beta -= 180.0
        return f"[{_deg(alpha)}, {_deg(beta)}] deg" + (" (beta from the folded arm)" if self.angle_convention == "folded" else "")

    def limits_text(self) -> str:
        """The hard stops in the file's convention, rounded: ``alpha in [..], beta in [..] deg``."""
        (a_lo, a_hi), (b_lo, b_hi) = np.degrees(self.instrument.limits_rad).tolist()
        shift = 180.0 if self.angle_convention == "folded" else 0.0
        return f"alpha in [{_deg(a_lo)}, {_deg(a_hi)}], beta in [{_deg(b_lo - shift)}, {_deg(b_hi - shift)}] deg"

    @cached_property
    def priority_rank(self) -> np.ndarray:
        """Priority as a rank: smaller goes first; no priority (0) after every numbered one."""
        return np.where(self.target_priority > 0, self.target_priority, np.iinfo(np.int64).max)

    def _untangle_free_parities(self, goal: np.ndarray, free_rows: np.ndarray) -> None:
        """Flip free-parity targets whose faster solution collides with a neighbour's goal.

        The faster parity is chosen per positioner; where two such goals collide, the other
        parity of a free positioner is tried (each at most once), in place on ``goal``.
        """
        if len(free_rows) == 0 or len(self.pairs) == 0:
            return
        inst = self.instrument
        flippable = np.zeros(self.n_positioners, dtype=bool)
        flippable[free_rows] = True
        for _ in range(8):
            clearance = min_pair_clearance(inst, self.base_xy, self.orient, goal, self.pairs)
            rows = np.unique(self.pairs[clearance < 0.0].ravel())
            rows = rows[flippable[rows]]
            if len(rows) == 0:
                return
            other = inverse_kinematics(
                inst, self.base_xy[rows], self.orient[rows], self.target_values[rows], -parity_of(goal[rows, 1])
            )
            ok = ~np.isnan(other[:, 0])
            goal[rows[ok]] = other[ok]
            flippable[rows] = False

    def _validate(self, validate_collisions: bool = True) -> None:
        inst = self.instrument
        n = len(self.ids)
        shapes = {
            "base_xy": (n, 2),
            "orient_deg": (n,),
            "start_deg": (n, 2),
            "target_kind": (n,),
            "target_values": (n, 2),
            "target_parity": (n,),
        }
        if n == 0:
            raise ScenarioError("a scenario needs at least one positioner")
        for attr, shape in shapes.items():
            if getattr(self, attr).shape != shape:
                raise ScenarioError(f"scenario array {attr} has shape {getattr(self, attr).shape}, expected {shape}")
        unique, counts = np.unique(self.ids, return_counts=True)
        if np.any(counts > 1):
            dup = unique[counts > 1]
            raise ScenarioError(f"positioner ids must be unique; id {dup[0]} appears {counts[counts > 1][0]} times")
        for attr in ("base_xy", "orient_deg", "start_deg", "target_values"):
            values = getattr(self, attr).reshape(n, -1)
            bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
            if len(bad):
                raise ScenarioError(
                    f"positioner {self.ids[bad[0]]}: {attr} holds a non-finite value {values[bad[0]].tolist()}; "
                    "every number must be finite"
                )
        far = np.flatnonzero(np.abs(self.base_xy).max(axis=1) > MAX_COORDINATE_MM)
        if len(far):
            raise ScenarioError(
                f"positioner {self.ids[far[0]]}: base ({self.base_xy[far[0], 0]:.6g}, {self.base_xy[far[0], 1]:.6g}) mm lies more than "
                f"{MAX_COORDINATE_MM:.0f} mm from the centre; base coordinates are millimetres"
            )
        turned = np.flatnonzero(np.abs(self.orient_deg) > 360.0)
        if len(turned):
            raise ScenarioError(f"positioner {self.ids[turned[0]]}: orient_deg {self.orient_deg[turned[0]]:.6g} must lie in [-360, 360] deg")
        self._validate_spacing()
        bad = np.flatnonzero(~np.isin(self.target_kind, (TARGET_NONE, TARGET_JOINTS, TARGET_XY)))
        if len(bad):
            raise ScenarioError(f"positioner {self.ids[bad[0]]}: unknown target kind {self.target_kind[bad[0]]}")
        bad = np.flatnonzero(~np.isin(self.target_parity, (-1, 0, 1)))
        if len(bad):
            raise ScenarioError(
                f"positioner {self.ids[bad[0]]}: parity must be 1, -1 or 0 (either), found {self.target_parity[bad[0]]}"
            )
        bad = np.flatnonzero(~inst.within_limits(self.start))
        if len(bad):
            k = bad[0]
            raise ScenarioError(
                f"positioner {self.ids[k]}: start joints {self.angles_text(self.start_deg[k])} are beyond a hard stop "
                f"({self.limits_text()})"
            )
        if self.locked.shape != (n,):
            raise ScenarioError(f"scenario array locked has shape {self.locked.shape}, expected {(n,)}")
        if self.target_priority.shape != (n,):
            raise ScenarioError(f"scenario array target_priority has shape {self.target_priority.shape}, expected {(n,)}")
        bad = np.flatnonzero(self.target_priority < 0)
        if len(bad):
            raise ScenarioError(f"positioner {self.ids[bad[0]]}: target priority must be 1, 2, ... (or 0: none), "
                                f"found {self.target_priority[bad[0]]}")
        if self.angle_convention not in ("extended", "folded"):
            raise ScenarioError(f"scenario angle_convention must be 'extended' or 'folded', found {self.angle_convention!r}")
        if validate_collisions:
            self._validate_collisions(self.start, "start configuration")

    def _validate_spacing(self) -> None:
        """Bases closer than the instrument allows (two positioners on one base among them)."""
        if self.n_positioners < 2:
            return
        from scipy.spatial import cKDTree

        limit = self.instrument.base_spacing_mm
        close = cKDTree(self.base_xy).query_pairs(limit, output_type="ndarray")
        if len(close):
            gaps = np.linalg.norm(self.base_xy[close[:, 0]] - self.base_xy[close[:, 1]], axis=1)
            k = int(np.argmin(gaps))
            i, j = sorted(close[k].tolist())
            raise ScenarioError(
                f"positioners {self.ids[i]} and {self.ids[j]}: bases {gaps[k]:.4g} mm apart, closer than the "
                f"{limit:.4g} mm instrument {self.instrument.name!r} allows ({len(close)} such pair(s)); "
                "check the layout (duplicated rows, units) or set [geometry] min_base_distance_mm in the instrument file"
            )

    def _validate_collisions(self, joints: np.ndarray, what: str) -> None:
        pairs = self.pairs
        if len(pairs) == 0:
            return
        clearance = min_pair_clearance(self.instrument, self.base_xy, self.orient, joints, pairs)
        bad = np.flatnonzero(clearance < 0.0)
        if len(bad):
            k = bad[np.argmin(clearance[bad])]
            i, j = pairs[k]
            fix = "move one of them first or change a start angle" if what.startswith("start") else "change one of their targets"
            if len(bad) > max(2, 0.1 * len(pairs)):
                # Many pairs at once is rarely a few bad angles: a frame or convention is off.
                fix += (f"; {len(bad)} of {len(pairs)} neighbour pairs collide, which suggests a wrong orient_deg (the angle, in degrees, "
                        "that turns each positioner's x axis into the focal plane's), a wrong beta convention of the angles "
                        "(beta = 0 with the arms stretched out unless the file says otherwise) or base positions in the wrong unit")
            raise ScenarioError(
                f"positioners {self.ids[i]} and {self.ids[j]} collide in the {what} "
                f"(capsules overlap by {-clearance[k]:.4f} mm; {len(bad)} colliding pair(s) in all); {fix}"
            )

    # ------------------------------------------------------------------ file format
    def to_dict(self) -> dict[str, Any]:
        """The scenario in the JSON file layout."""
        positioners = []
        for k in range(self.n_positioners):
            kind = int(self.target_kind[k])
            target: dict[str, Any] | None
            if kind == TARGET_NONE:
                target = None
            elif kind == TARGET_JOINTS:
                target = {"alpha_deg": float(self.target_values[k, 0]), "beta_deg": float(self.target_values[k, 1])}
            else:
                target = {"x_mm": float(self.target_values[k, 0]), "y_mm": float(self.target_values[k, 1])}
                if self.target_parity[k] != 0:
                    target["parity"] = int(self.target_parity[k])
            if target is not None and self.target_priority[k] != 0:
                target["priority"] = int(self.target_priority[k])
            positioners.append(
                {
                    "id": int(self.ids[k]),
                    "x_mm": float(self.base_xy[k, 0]),
                    "y_mm": float(self.base_xy[k, 1]),
                    "orient_deg": float(self.orient_deg[k]),
                    "start_deg": [float(self.start_deg[k, 0]), float(self.start_deg[k, 1])],
                    "target": target,
                    **({"locked": True} if self.locked[k] else {}),
                }
            )
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "name": self.name,
            "kind": self.kind,
            "seed": self.seed,
            "instrument": self.instrument_preset if self.instrument_preset else self.instrument.to_dict(),
            "beta_convention": "extended",  # the angles as kept: a round trip is bit-identical
            "meta": self.meta,
            "positioners": positioners,
        }

    def save(self, path: str | Path) -> Path:
        """Write the scenario as JSON, atomically. Returns the path."""
        path = Path(path)
        text = json.dumps(self.to_dict(), indent=1)
        with atomic_path(path) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")
        return path

    def subset(self, rows: Any, name: str | None = None) -> Scenario:
        """The scenario of the positioners at ``rows`` only (indices or a mask), validated again."""
        r = np.arange(self.n_positioners)[np.asarray(rows)]
        return _replace(
            self, ids=self.ids[r], base_xy=self.base_xy[r], orient_deg=self.orient_deg[r], start_deg=self.start_deg[r],
            target_kind=self.target_kind[r], target_values=self.target_values[r], target_parity=self.target_parity[r],
            locked=self.locked[r], target_priority=self.target_priority[r], name=self.name if name is None else name,
        )

    def with_instrument(self, instrument: Instrument, preset: str | None = None) -> Scenario:
        """The same positioners, starts and targets on another instrument (validated again).

        Raises:
            ScenarioError: a start or target does not fit the new instrument (named).
        """
        try:
            return _replace(self, instrument=instrument, instrument_preset=preset)
        except ScenarioError as e:
            raise ScenarioError(f"on instrument {instrument.name!r}: {e}") from e


def _replace(scenario: Scenario, **changes: Any) -> Scenario:
    fields = {
        name: getattr(scenario, name)
        for name in (
            "instrument", "ids", "base_xy", "orient_deg", "start_deg", "target_kind", "target_values",
            "target_parity", "name", "kind", "seed", "instrument_preset", "meta", "locked", "target_priority", "angle_convention",
        )
    }
    fields.update(changes)
    return Scenario(**fields)


def scenario_from_dict(data: Any, origin: str = "scenario") -> Scenario:
    """Build a :class:`Scenario` from the JSON layout.

    Every key is checked: an unknown key (a misspelling such as ``"targett"``) is an error
    naming it and the closest valid key, never ignored.

    Raises:
        ScenarioError: a key is missing or unknown, a value has the wrong type, or validation fails.
    """
    if not isinstance(data, dict):
        raise ScenarioError(f"{origin}: the top level must be a JSON object")
    check_keys(data, SCENARIO_KEYS, origin, ScenarioError)
    if data.get("format") != FORMAT_NAME:
        raise ScenarioError(f"{origin}: 'format' must be {FORMAT_NAME!r}, found {data.get('format')!r}")
    version = data.get("version")
    if isinstance(version, bool) or version not in READ_VERSIONS:
        raise ScenarioError(f"{origin}: unsupported version {version!r}; this fiberplan reads versions {', '.join(map(str, READ_VERSIONS))}")
    raw_instrument = data.get("instrument")
    try:
        if isinstance(raw_instrument, str):
            instrument = load_instrument(raw_instrument)
            # A preset is stored by name; an instrument file's table is embedded (the scenario stands alone).
            preset: str | None = raw_instrument if _is_preset(raw_instrument) and not Path(raw_instrument).is_file() else None
        elif isinstance(raw_instrument, dict):
            instrument = instrument_from_dict(raw_instrument, origin=f"{origin}: instrument")
            preset = None
        else:
            raise ScenarioError(f"{origin}: 'instrument' must be a preset name or an instrument table")
    except InstrumentError as e:
        raise ScenarioError(f"{origin}: {e}") from e
    convention = data.get("beta_convention", "extended" if version == 1 else instrument.beta_convention)
    if convention not in ("extended", "folded"):
        raise ScenarioError(f"{origin}: 'beta_convention' must be 'extended' or 'folded', found {convention!r}")
    beta_shift = 180.0 if convention == "folded" else 0.0  # the arrays are extended
    rows = data.get("positioners")
    if not isinstance(rows, list) or not rows:
        raise ScenarioError(f"{origin}: 'positioners' must be a non-empty list")
    n = len(rows)
    ids = np.zeros(n, dtype=np.int64)
    base = np.zeros((n, 2))
    orient = np.zeros(n)
    start = np.zeros((n, 2))
    kind = np.zeros(n, dtype=np.int64)
    values = np.zeros((n, 2))
    parity = np.zeros(n, dtype=np.int64)
    locked = np.zeros(n, dtype=bool)
    priority = np.zeros(n, dtype=np.int64)
    for k, row in enumerate(rows):
        if not isinstance(row, dict):
            raise ScenarioError(f"{origin}: positioner #{k}: each entry of 'positioners' must be an object")
        label = f"positioner {row.get('id', f'#{k}')}"
        check_keys(row, POSITIONER_KEYS, f"{origin}: {label}", ScenarioError)
        try:
            ids[k] = _as_int(row["id"])
            base[k] = (_as_float(row["x_mm"]), _as_float(row["y_mm"]))
            orient[k] = _as_float(row.get("orient_deg", 0.0))
            start_row = row["start_deg"]
            if not isinstance(start_row, list) or len(start_row) != 2:
                raise ValueError("start_deg must be a list [alpha_deg, beta_deg]")
            start[k] = (_as_float(start_row[0]), _as_float(start_row[1]) + beta_shift)
            lock = row.get("locked", False)
            if not isinstance(lock, bool):
                raise ValueError(f"locked must be true or false, found {lock!r}")
            locked[k] = lock
            target = row.get("target")
            if target is None:
                kind[k] = TARGET_NONE
            elif not isinstance(target, dict):
                raise ValueError("target must be an object or null")
            elif "alpha_deg" in target or "beta_deg" in target:
                check_keys(target, JOINT_TARGET_KEYS, f"{origin}: {label}: joint-angle target", ScenarioError)
                kind[k] = TARGET_JOINTS
                values[k] = (_as_float(target["alpha_deg"]), _as_float(target["beta_deg"]) + beta_shift)
            elif "x_mm" in target or "y_mm" in target:
                check_keys(target, XY_TARGET_KEYS, f"{origin}: {label}: fiber x/y target", ScenarioError)
                kind[k] = TARGET_XY
                values[k] = (_as_float(target["x_mm"]), _as_float(target["y_mm"]))
                named = target.get("parity", 0)
                if isinstance(named, str) and named.upper() not in PARITY_NAMES:
                    raise ValueError(f"parity must be 1 or 'R', -1 or 'L', or 0 (the faster one), found {named!r}")
                parity[k] = PARITY_NAMES[named.upper()] if isinstance(named, str) else _as_int(named)
            else:
                check_keys(target, (*JOINT_TARGET_KEYS, *XY_TARGET_KEYS), f"{origin}: {label}: target", ScenarioError)
                raise ValueError("target needs alpha_deg/beta_deg or x_mm/y_mm (or null for no target)")
            if isinstance(target, dict) and "priority" in target:
                priority[k] = _as_int(target["priority"])
                if priority[k] < 1:
                    raise ValueError(f"target priority must be an integer >= 1 (1 = first), found {target['priority']!r}")
        except KeyError as e:
            raise ScenarioError(f"{origin}: {label}: missing key {e.args[0]!r}") from e
        except (TypeError, ValueError, AttributeError, OverflowError) as e:
            if isinstance(e, ScenarioError):
                raise
            raise ScenarioError(f"{origin}: {label}: {e}") from e
    seed = data.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED):
        raise ScenarioError(f"{origin}: 'seed' must be an integer from 0 to 2**63 - 1 or null, found {seed!r}")
    meta = data.get("meta")
    if meta is not None and not isinstance(meta, dict):
        raise ScenarioError(f"{origin}: 'meta' must be an object (or absent), found {type(meta).__name__} {meta!r}")
    for key in ("name", "kind"):
        if key in data and not isinstance(data[key], str):
            raise ScenarioError(f"{origin}: {key!r} must be a string, found {data[key]!r}")
    try:
        return Scenario(
            instrument=instrument,
            ids=ids,
            base_xy=base,
            orient_deg=orient,
            start_deg=start,
            target_kind=kind,
            target_values=values,
            target_parity=parity,
            name=str(data.get("name", "")),
            kind=str(data.get("kind", "custom")),
            seed=seed,
            instrument_preset=preset,
            meta=dict(meta or {}),
            locked=locked,
            target_priority=priority,
            angle_convention=convention,
        )
    except ScenarioError as e:
        raise ScenarioError(f"{origin}: {e}") from e


def _deg(value: float) -> str:
    """An angle rounded to 1e-6 deg, without trailing zeros (``330.00000000000006`` -> ``330``)."""
    text = f"{round(value, 6):.6f}".rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def _is_preset(name: str) -> bool:
    from fiberplan.instrument_io import preset_names

    return name in preset_names()


def _as_float(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"expected a number, found {value!r}")
    return float(value)


def _as_int(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"expected an integer, found {value!r}")
    if not -MAX_SEED - 1 <= value <= MAX_SEED:
        raise ValueError(f"integer {value} does not fit in 64 bits")
    return int(value)


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario JSON file.

    Raises:
        ScenarioError: the file is missing, truncated, not JSON, or describes an invalid scenario.
    """
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"scenario file {str(path)!r} does not exist")
    text = path.read_text(encoding="utf-8")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ScenarioError(
            f"scenario file {str(path)!r} is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg}); "
            "is it truncated? Regenerate it with `fiberplan scenario`"
        ) from e
    return scenario_from_dict(data, origin=f"scenario file {str(path)!r}")

