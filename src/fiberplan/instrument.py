"""Instruments: arm lengths, speeds, hard stops and collision capsules of one positioner type.

The :class:`Instrument` object holds millimetres, radians and rad/s; it is read from a TOML
file (millimetres, degrees, rpm) by :mod:`fiberplan.instrument_io`, where the presets
``desi``, ``moons`` and ``sdss`` are found (``src/fiberplan/instruments/``).

Joint conventions (``DESIGN.md``): alpha is absolute about the positioner base, beta is
relative to the alpha arm and equal to zero with the arms in line. A file may state
``beta_convention = "folded"`` to give beta limits and datum measured from the folded arm
(MOONS documents do); they are converted by adding 180 deg.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, fields
from typing import Any, Literal

import numpy as np

from fiberplan.errors import InstrumentError

ArmName = Literal["alpha", "beta"]

_RPM_TO_RAD_S = 2.0 * math.pi / 60.0


@dataclass(frozen=True)
class Capsule:
    """A collision capsule: a segment in one arm's frame plus a radius, on one layer.

    The segment runs from ``(start_mm, start_y_mm)`` to ``(end_mm, end_y_mm)`` in the arm's
    frame: ``x`` along the arm from its joint (the base for ``alpha``, the elbow for ``beta``),
    ``y`` to the arm's left; the ``y`` offsets are zero for a capsule on the arm's axis. A
    zero-length segment is a disc. Without an interaction table, two capsules of different
    positioners collide when they share ``layer`` and their segments are closer than the sum
    of their radii. A capsule that is an edge of a :class:`Polygon` zone names it in ``zone``
    (and may have a zero radius); any other capsule is a zone of its own.
    """

    name: str
    arm: ArmName
    start_mm: float
    end_mm: float
    radius_mm: float
    layer: int = 0
    start_y_mm: float = 0.0
    end_y_mm: float = 0.0
    zone: str = ""

    def __post_init__(self) -> None:
        if self.arm not in ("alpha", "beta"):
            raise InstrumentError(f"capsule {self.name!r}: arm must be 'alpha' or 'beta', found {self.arm!r}")
        for label, value in (("start_mm", self.start_mm), ("end_mm", self.end_mm), ("radius_mm", self.radius_mm),
                             ("start_y_mm", self.start_y_mm), ("end_y_mm", self.end_y_mm)):
            if not math.isfinite(value):
                raise InstrumentError(f"capsule {self.name!r}: {label} must be finite, found {value}")
        if self.radius_mm < 0 or (self.radius_mm == 0 and not self.zone):
            raise InstrumentError(f"capsule {self.name!r}: radius_mm must be > 0, found {self.radius_mm}")

    @property
    def zone_name(self) -> str:
        """The zone this capsule belongs to: its polygon's name, else its own."""
        return self.zone or self.name

    @property
    def reach_mm(self) -> float:
        """Farthest distance of the segment from the arm's joint (mm)."""
        ends = []
        for x, y in ((self.start_mm, self.start_y_mm), (self.end_mm, self.end_y_mm)):
            ends.append(abs(x) if y == 0.0 else math.hypot(x, y))
        return max(ends)


@dataclass(frozen=True)
class Polygon:
    """A convex polygon zone in one arm's frame (``x`` along the arm from its joint, ``y`` to its
    left), padded by ``radius_mm`` (0: the polygon itself, as MOONS pads its zones by enlarging
    them). Two zones collide when they overlap; the planners and the verifier measure the
    distance between a polygon's edges (:meth:`edges`, capsules of the polygon's radius) and
    the verifier also finds a zone lying wholly inside a polygon."""

    name: str
    arm: ArmName
    vertices_mm: tuple[tuple[float, float], ...]
    radius_mm: float = 0.0
    layer: int = 0

    def __post_init__(self) -> None:
        if self.arm not in ("alpha", "beta"):
            raise InstrumentError(f"zone {self.name!r}: arm must be 'alpha' or 'beta', found {self.arm!r}")
        pts = np.asarray(self.vertices_mm, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3:
            raise InstrumentError(f"zone {self.name!r}: a polygon needs at least 3 vertices [x_mm, y_mm], found {self.vertices_mm!r}")
        if not np.all(np.isfinite(pts)) or not (math.isfinite(self.radius_mm) and self.radius_mm >= 0):
            raise InstrumentError(f"zone {self.name!r}: vertices and radius_mm must be finite (radius >= 0)")
        edge = np.roll(pts, -1, axis=0) - pts
        nxt = np.roll(edge, -1, axis=0)
        cross = edge[:, 0] * nxt[:, 1] - edge[:, 1] * nxt[:, 0]
        if not (np.all(cross > 1e-12) or np.all(cross < -1e-12)):
            raise InstrumentError(
                f"zone {self.name!r}: the vertices {self.vertices_mm!r} are not a convex polygon with distinct corners, in order "
                "around it; a concave zone is given as several convex ones"
            )

    @property
    def counterclockwise(self) -> np.ndarray:
        """The vertices ``(V, 2)`` in counterclockwise order."""
        pts = np.asarray(self.vertices_mm, dtype=float)
        area = float(np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1]))
        return pts if area > 0 else pts[::-1].copy()

    def edges(self) -> tuple[Capsule, ...]:
        """The polygon's edges as capsules of its radius, named ``<name>#<k>``."""
        pts = self.counterclockwise
        out = []
        for k in range(len(pts)):
            (x0, y0), (x1, y1) = pts[k], pts[(k + 1) % len(pts)]
            out.append(Capsule(f"{self.name}#{k}", self.arm, float(x0), float(x1), self.radius_mm, self.layer, float(y0), float(y1),
                               zone=self.name))
        return tuple(out)


@dataclass(frozen=True)
class MotorLimits:
    """What an instrument's motor controllers accept beyond the top speeds; ``None`` (or false)
    means unconstrained. The verifier reports violations of these separately from the safety
    checks: a planner's samples are not yet motor commands (that is the profiles' job).

    Attributes:
        min_speed_rad_s: ``(alpha, beta)`` slowest a moving joint may turn.
        max_speed_change: largest relative speed change between consecutive commands of a moving
            joint (0.4: by at most 40 % of the previous speed); starting and stopping are exempt.
        max_segments: most constant-speed segments per joint in one move.
        stop_before_reversing: a joint must stop (a zero-speed command) before turning back.
        command_period_s: the controller's command period: every segment lasts a multiple of it
            (used by :mod:`fiberplan.profiles`).
        max_start_stops: most start-stop cycles per joint in one move (reference 003's nSSC): a
            joint may start moving from rest at most this many times.
        ramp_time_s: how long the controller takes to change a joint's speed: each commanded
            speed change is a linear ramp over this time, starting at the command (a start from
            rest to the top speed takes it whole; the acceleration limit is the top speed over
            it). From the file's ``ramp_time_s``, or from ``max_acceleration_rpm_per_s`` as the
            longest of the joints' top speed over acceleration (:mod:`fiberplan.ramps`).
    """

    min_speed_rad_s: tuple[float, float] | None = None
    max_speed_change: float | None = None
    max_segments: int | None = None
    stop_before_reversing: bool = False
    command_period_s: float | None = None
    max_start_stops: int | None = None
    ramp_time_s: float | None = None

    def unstated(self) -> list[str]:
        """The limits not stated (unconstrained), by their file key."""
        given = {"min_speed_rpm": self.min_speed_rad_s, "max_speed_change": self.max_speed_change,
                 "max_segments": self.max_segments, "stop_before_reversing": self.stop_before_reversing or None,
                 "command_period_s": self.command_period_s, "max_start_stops": self.max_start_stops,
                 "ramp_time_s": self.ramp_time_s}
        return [key for key, value in given.items() if value is None]

    @property
    def stated(self) -> bool:
        """Whether any limit is given."""
        return (self.min_speed_rad_s is not None or self.max_speed_change is not None or self.max_segments is not None
                or self.stop_before_reversing or self.command_period_s is not None or self.max_start_stops is not None
                or self.ramp_time_s is not None)


@dataclass(frozen=True)
class Instrument:
    """Geometry and motion limits shared by every positioner of an instrument.

    Angles are in radians, speeds in rad/s, lengths in millimetres.
    """

    name: str
    pitch_mm: float
    alpha_arm_mm: float
    beta_arm_mm: float
    alpha_speed_rad_s: float
    beta_speed_rad_s: float
    alpha_limits_rad: tuple[float, float]
    beta_limits_rad: tuple[float, float]
    datum_rad: tuple[float, float]
    tolerance_mm: float
    capsules: tuple[Capsule, ...]
    description: str = ""
    polygons: tuple[Polygon, ...] = ()
    interactions: tuple[tuple[str, str], ...] | None = None
    min_base_distance_mm: float | None = None
    sources: dict[str, str] = field(default_factory=dict, compare=False, hash=False)
    planner_defaults: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)
    motors: MotorLimits = field(default_factory=MotorLimits)
    spec: dict[str, Any] | None = field(default=None, compare=False, hash=False, repr=False)

    def __post_init__(self) -> None:
        positive = {
            "pitch_mm": self.pitch_mm,
            "alpha_arm_mm": self.alpha_arm_mm,
            "beta_arm_mm": self.beta_arm_mm,
            "alpha_speed": self.alpha_speed_rad_s,
            "beta_speed": self.beta_speed_rad_s,
            "tolerance_mm": self.tolerance_mm,
        }
        for label, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise InstrumentError(f"instrument {self.name!r}: {label} must be a finite number > 0, found {value}")
        for label, (lo, hi) in (("alpha_limits", self.alpha_limits_rad), ("beta_limits", self.beta_limits_rad)):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise InstrumentError(
                    f"instrument {self.name!r}: {label} must be two finite angles with lower < upper, "
                    f"found [{math.degrees(lo)}, {math.degrees(hi)}] deg"
                )
            if hi - lo > 2 * math.pi + 1e-12:
                raise InstrumentError(
                    f"instrument {self.name!r}: {label} span more than 360 deg; a joint range must fit in one turn"
                )
        if not self.capsules:
            raise InstrumentError(f"instrument {self.name!r}: at least one collision capsule is needed")
        if self.min_base_distance_mm is not None and not (math.isfinite(self.min_base_distance_mm) and self.min_base_distance_mm >= 0):
            raise InstrumentError(f"instrument {self.name!r}: min_base_distance_mm must be a finite number >= 0, found {self.min_base_distance_mm}")
        self._check_zones()
        for capsule in self.capsules:
            if capsule.zone:
                continue  # a polygon's edge: the polygon is checked as drawn by the instrument's maker
            arm = self.alpha_arm_mm if capsule.arm == "alpha" else self.beta_arm_mm
            longest = capsule.reach_mm
            if longest > arm + capsule.radius_mm + 1e-9:
                raise InstrumentError(
                    f"instrument {self.name!r}: capsule {capsule.name!r} reaches {longest:g} mm along the {capsule.arm} arm, beyond the "
                    f"arm's {arm:g} mm plus its {capsule.radius_mm:g} mm radius; shorten the capsule or check the arm length"
                )
        if not (self.within_limits(np.array(self.datum_rad))):
            raise InstrumentError(f"instrument {self.name!r}: datum {np.degrees(self.datum_rad)} deg is outside the joint limits")

    def __hash__(self) -> int:
        """The hash of the fields ``==`` compares, computed once per object. The geometry's
        tables are cached per instrument (``functools.lru_cache``), so an instrument is hashed
        at every distance call: the generated hash walks every capsule, polygon and motor field
        each time, 10 us on MOONS' zones (34 capsules and polygons; about a million calls in
        a MOONS 7 plan, ~4 % of its CPU time). Not pickled (:meth:`__getstate__`): string
        hashes differ between processes."""
        cached = self.__dict__.get("_hash")
        if cached is None:
            cached = hash(tuple(getattr(self, f.name) for f in fields(self) if (f.compare if f.hash is None else f.hash)))
            object.__setattr__(self, "_hash", cached)
        return cached

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_hash", None)
        return state

    def _check_zones(self) -> None:
        names = [c.name for c in self.capsules if not c.zone] + [p.name for p in self.polygons]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InstrumentError(f"instrument {self.name!r}: zone names must be unique, found {', '.join(dup)} more than once")
        edges = {c.zone for c in self.capsules if c.zone}
        polygons = {p.name for p in self.polygons}
        if edges != polygons:
            raise InstrumentError(f"instrument {self.name!r}: the polygon edges ({sorted(edges)}) and polygons ({sorted(polygons)}) differ")
        if self.interactions is not None:
            known = set(names)
            for a, b in self.interactions:
                for z in (a, b):
                    if z not in known:
                        raise InstrumentError(
                            f"instrument {self.name!r}: [interactions] names zone {z!r}, which is not a zone of the instrument "
                            f"({', '.join(sorted(known))})"
                        )

    @property
    def zone_names(self) -> list[str]:
        """Names of the collision zones: every capsule that is not a polygon's edge, then every polygon."""
        return [c.name for c in self.capsules if not c.zone] + [p.name for p in self.polygons]

    @property
    def zone_pairs(self) -> tuple[tuple[str, str], ...]:
        """Ordered zone-name pairs ``(a, b)`` checked between positioners ``i`` (zone ``a``) and
        ``j`` (zone ``b``): the interaction table both ways round, else every pair of zones on one layer."""
        if self.interactions is None:
            layer = {c.zone_name: c.layer for c in self.capsules}
            names = self.zone_names
            return tuple((a, b) for a in names for b in names if layer[a] == layer[b])
        out: list[tuple[str, str]] = []
        for a, b in self.interactions:
            for pair in ((a, b), (b, a)):
                if pair not in out:
                    out.append(pair)
        return tuple(out)

    # ------------------------------------------------------------------ derived values
    @property
    def control_dt_s(self) -> float:
        """Default control / sample period of planners for this instrument (s).

        Read from ``[planner_defaults] dt_s``; otherwise the time in which the fiber tip,
        both joints at full speed, moves 0.25 mm (rounded to 5 ms steps).
        """
        if "dt_s" in self.planner_defaults:
            return float(self.planner_defaults["dt_s"])
        tip_speed = self.alpha_arm_mm * self.alpha_speed_rad_s + self.beta_arm_mm * (self.alpha_speed_rad_s + self.beta_speed_rad_s)
        return max(0.005, round(0.25 / tip_speed / 0.005) * 0.005)

    @property
    def base_spacing_mm(self) -> float:
        """Smallest distance allowed between two bases (mm): ``[geometry] min_base_distance_mm``,
        else half the pitch (lattice focal planes never come closer than the pitch)."""
        return 0.5 * self.pitch_mm if self.min_base_distance_mm is None else float(self.min_base_distance_mm)

    @property
    def speeds_rad_s(self) -> np.ndarray:
        """Maximum joint speeds ``[alpha, beta]`` in rad/s."""
        return np.array([self.alpha_speed_rad_s, self.beta_speed_rad_s])

    @property
    def full_turn_s(self) -> float:
        """Time of one full turn of the slower joint at full speed (s).

        The planners' default time budget beyond ``4 x`` the lower bound (DNF and MPC alike,
        so that their comparisons run with the same budget).
        """
        return 2.0 * math.pi / float(min(self.alpha_speed_rad_s, self.beta_speed_rad_s))

    @property
    def limits_rad(self) -> np.ndarray:
        """Hard stops as a ``(2, 2)`` array: row 0 alpha ``[lo, hi]``, row 1 beta ``[lo, hi]``."""
        return np.array([self.alpha_limits_rad, self.beta_limits_rad], dtype=float)

    @property
    def reach_min_mm(self) -> float:
        """Smallest fiber distance from the base the beta range allows."""
        lo, hi = self.beta_limits_rad
        # |l1 + l2 e^{ib}| is smallest where cos(b) is smallest inside [lo, hi].
        cos_min = -1.0 if _contains_angle(lo, hi, math.pi) else min(math.cos(lo), math.cos(hi))
        return math.sqrt(max(self.alpha_arm_mm**2 + self.beta_arm_mm**2 + 2 * self.alpha_arm_mm * self.beta_arm_mm * cos_min, 0.0))

    @property
    def reach_max_mm(self) -> float:
        """Largest fiber distance from the base the beta range allows."""
        lo, hi = self.beta_limits_rad
        cos_max = 1.0 if _contains_angle(lo, hi, 0.0) else max(math.cos(lo), math.cos(hi))
        return math.sqrt(self.alpha_arm_mm**2 + self.beta_arm_mm**2 + 2 * self.alpha_arm_mm * self.beta_arm_mm * cos_max)

    @property
    def extent_mm(self) -> float:
        """Largest distance from the base any capsule surface can reach."""
        extents = []
        for capsule in self.capsules:
            arm_offset = self.alpha_arm_mm if capsule.arm == "beta" else 0.0
            extents.append(arm_offset + capsule.reach_mm + capsule.radius_mm)
        return max(extents)

    @property
    def beta_point_extent_mm(self) -> float:
        """Largest distance from the elbow of any capsule segment point on the beta arm."""
        values = [c.reach_mm for c in self.capsules if c.arm == "beta"]
        return max(values, default=0.0)

    @property
    def alpha_point_extent_mm(self) -> float:
        """Largest distance from the base of any capsule segment point (either arm)."""
        values = [c.reach_mm for c in self.capsules if c.arm == "alpha"]
        values.append(self.alpha_arm_mm + self.beta_point_extent_mm if any(c.arm == "beta" for c in self.capsules) else 0.0)
        return max(values)

    @property
    def capsule_pairs(self) -> tuple[tuple[int, int], ...]:
        """Index pairs ``(a, b)`` of capsules that can touch: capsule ``a`` of one positioner and
        ``b`` of the other, of zones the interaction table pairs (without one: on the same layer)."""
        if self.interactions is None:
            return tuple(
                (a, b)
                for a, ca in enumerate(self.capsules)
                for b, cb in enumerate(self.capsules)
                if ca.layer == cb.layer
            )
        checked = set(self.zone_pairs)
        return tuple(
            (a, b)
            for a, ca in enumerate(self.capsules)
            for b, cb in enumerate(self.capsules)
            if (ca.zone_name, cb.zone_name) in checked
        )

    def within_limits(self, joints: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether joint angles ``(..., 2)`` lie inside the hard stops (with tolerance ``tol`` rad)."""
        joints = np.asarray(joints, dtype=float)
        lim = self.limits_rad
        return np.all((joints >= lim[:, 0] - tol) & (joints <= lim[:, 1] + tol), axis=-1)

    @property
    def beta_convention(self) -> str:
        """How this instrument's own documents measure beta: ``"extended"`` (0 with the arms in
        line, fiberplan's convention) or ``"folded"`` (0 with the beta arm folded back: MOONS)."""
        return str((self.spec or {}).get("beta_convention", "extended"))

    def to_dict(self) -> dict[str, Any]:
        """Full description in file units (mm, deg, rpm).

        An instrument read from a file returns that file's content, so that writing and
        reading it again gives bit-identical numbers; one built in code is converted.
        """
        if self.spec is not None:
            return copy.deepcopy(self.spec)
        return {
            "name": self.name,
            "description": self.description,
            "beta_convention": "extended",
            "geometry": {
                "pitch_mm": self.pitch_mm,
                "alpha_arm_mm": self.alpha_arm_mm,
                "beta_arm_mm": self.beta_arm_mm,
            },
            "motion": {
                "alpha_speed_rpm": self.alpha_speed_rad_s / _RPM_TO_RAD_S,
                "beta_speed_rpm": self.beta_speed_rad_s / _RPM_TO_RAD_S,
                "alpha_limits_deg": [math.degrees(v) for v in self.alpha_limits_rad],
                "beta_limits_deg": [math.degrees(v) for v in self.beta_limits_rad],
                "datum_deg": [math.degrees(v) for v in self.datum_rad],
                "tolerance_mm": self.tolerance_mm,
            },
            "capsules": [
                {
                    "name": c.name,
                    "arm": c.arm,
                    "start_mm": c.start_mm,
                    "end_mm": c.end_mm,
                    "radius_mm": c.radius_mm,
                    "layer": c.layer,
                }
                for c in self.capsules
            ],
            "sources": dict(self.sources),
        }


def _contains_angle(lo: float, hi: float, angle: float) -> bool:
    """Whether ``angle + 2 pi k`` lies in ``[lo, hi]`` for some integer k."""
    k = math.ceil((lo - angle) / (2 * math.pi))
    return angle + 2 * math.pi * k <= hi


