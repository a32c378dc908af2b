"""Instruments: arm lengths, speeds, hard stops and collision capsules of one positioner type.

An instrument is read from a TOML file (the presets ``desi``, ``moons`` and ``sdss`` ship
inside the package; see ``src/fiberplan/instruments/``). File values are in millimetres,
degrees and rpm; the :class:`Instrument` object holds millimetres, radians and rad/s.

Joint conventions (``DESIGN.md``): alpha is absolute about the positioner base, beta is
relative to the alpha arm and equal to zero with the arms in line. A file may state
``beta_convention = "folded"`` to give beta limits and datum measured from the folded arm
(MOONS documents do); they are converted by adding 180 deg.
"""

from __future__ import annotations

import copy
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np

from fiberplan._keys import check_keys
from fiberplan.errors import InstrumentError

ArmName = Literal["alpha", "beta"]

_RPM_TO_RAD_S = 2.0 * math.pi / 60.0

TOP_KEYS = ("name", "description", "beta_convention", "geometry", "motion", "capsules", "planner_defaults", "sources")
GEOMETRY_KEYS = ("pitch_mm", "alpha_arm_mm", "beta_arm_mm", "min_base_distance_mm")
MOTION_KEYS = ("alpha_speed_rpm", "beta_speed_rpm", "alpha_limits_deg", "beta_limits_deg", "datum_deg", "tolerance_mm")
CAPSULE_KEYS = ("name", "arm", "start_mm", "end_mm", "radius_mm", "layer")
BETA_CONVENTIONS = ("extended", "folded")


@dataclass(frozen=True)
class Capsule:
    """A collision capsule: a segment along one arm plus a radius, on one layer.

    The segment runs along the arm's axis from ``start_mm`` to ``end_mm``, measured from the
    arm's joint (the base for ``alpha``, the elbow for ``beta``). A zero-length segment is a
    disc. Two capsules of different positioners collide only when they share ``layer`` and
    their segments are closer than the sum of their radii.
    """

    name: str
    arm: ArmName
    start_mm: float
    end_mm: float
    radius_mm: float
    layer: int = 0

    def __post_init__(self) -> None:
        if self.arm not in ("alpha", "beta"):
            raise InstrumentError(f"capsule {self.name!r}: arm must be 'alpha' or 'beta', found {self.arm!r}")
        for label, value in (("start_mm", self.start_mm), ("end_mm", self.end_mm), ("radius_mm", self.radius_mm)):
            if not math.isfinite(value):
                raise InstrumentError(f"capsule {self.name!r}: {label} must be finite, found {value}")
        if self.radius_mm <= 0:
            raise InstrumentError(f"capsule {self.name!r}: radius_mm must be > 0, found {self.radius_mm}")


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
    min_base_distance_mm: float | None = None
    sources: dict[str, str] = field(default_factory=dict, compare=False, hash=False)
    planner_defaults: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)
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
        for capsule in self.capsules:
            arm = self.alpha_arm_mm if capsule.arm == "alpha" else self.beta_arm_mm
            longest = max(abs(capsule.start_mm), abs(capsule.end_mm))
            if longest > arm + capsule.radius_mm + 1e-9:
                raise InstrumentError(
                    f"instrument {self.name!r}: capsule {capsule.name!r} reaches {longest:g} mm along the {capsule.arm} arm, beyond the "
                    f"arm's {arm:g} mm plus its {capsule.radius_mm:g} mm radius; shorten the capsule or check the arm length"
                )
        if not (self.within_limits(np.array(self.datum_rad))):
            raise InstrumentError(f"instrument {self.name!r}: datum {np.degrees(self.datum_rad)} deg is outside the joint limits")
        self._check_datum()

    def _check_datum(self) -> None:
        """Refuse a datum at which neighbours on the lattice collide: it must be safe for everyone."""
        from fiberplan.geometry import min_pair_clearance  # geometry imports this module

        third = math.sqrt(3.0) / 2.0
        ring = self.pitch_mm * np.array([[0.0, 0.0], [1, 0], [0.5, third], [-0.5, third], [-1, 0], [-0.5, -third], [0.5, -third]])
        pairs = np.array([(i, j) for i in range(7) for j in range(i + 1, 7)])
        joints = np.tile(np.array(self.datum_rad), (7, 1))
        clearance = min_pair_clearance(self, ring, np.zeros(7), joints, pairs)
        if np.any(clearance < 0.0):
            raise InstrumentError(
                f"instrument {self.name!r}: at the datum {np.round(np.degrees(self.datum_rad), 6).tolist()} deg (extended convention) "
                f"neighbours {self.pitch_mm:g} mm apart collide (overlap {-float(clearance.min()):.4g} mm); the datum must be "
                "collision-free for every neighbour pair: check datum_deg, beta_convention and the capsules"
            )

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
            far = max(abs(capsule.start_mm), abs(capsule.end_mm))
            arm_offset = self.alpha_arm_mm if capsule.arm == "beta" else 0.0
            extents.append(arm_offset + far + capsule.radius_mm)
        return max(extents)

    @property
    def beta_point_extent_mm(self) -> float:
        """Largest distance from the elbow of any capsule segment point on the beta arm."""
        values = [max(abs(c.start_mm), abs(c.end_mm)) for c in self.capsules if c.arm == "beta"]
        return max(values, default=0.0)

    @property
    def alpha_point_extent_mm(self) -> float:
        """Largest distance from the base of any capsule segment point (either arm)."""
        values = [max(abs(c.start_mm), abs(c.end_mm)) for c in self.capsules if c.arm == "alpha"]
        values.append(self.alpha_arm_mm + self.beta_point_extent_mm if any(c.arm == "beta" for c in self.capsules) else 0.0)
        return max(values)

    @property
    def capsule_pairs(self) -> tuple[tuple[int, int], ...]:
        """Index pairs ``(a, b)`` of capsules that can touch: same layer (ordered, both ways)."""
        return tuple(
            (a, b)
            for a, ca in enumerate(self.capsules)
            for b, cb in enumerate(self.capsules)
            if ca.layer == cb.layer
        )

    def within_limits(self, joints: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether joint angles ``(..., 2)`` lie inside the hard stops (with tolerance ``tol`` rad)."""
        joints = np.asarray(joints, dtype=float)
        lim = self.limits_rad
        return np.all((joints >= lim[:, 0] - tol) & (joints <= lim[:, 1] + tol), axis=-1)

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


def preset_names() -> list[str]:
    """Names of the instrument presets shipped with fiberplan."""
    folder = resources.files("fiberplan") / "instruments"
    return sorted(p.name[: -len(".toml")] for p in folder.iterdir() if p.name.endswith(".toml"))


def instrument_source(name_or_path: str | Path) -> tuple[str, str | None]:
    """How :func:`load_instrument` reads ``name_or_path``: ``("file", path)``, ``("preset", name)``.

    An argument that is an existing *file* is read as a file; otherwise a preset name is the
    preset (a folder named ``moons`` in the working directory does not hide the preset).

    Raises:
        InstrumentError: neither an existing file nor a preset name.
    """
    text = str(name_or_path)
    if "\x00" in text or not text:
        raise InstrumentError(f"instrument {text!r}: not a preset name or a file path")
    path = Path(name_or_path)
    if path.is_file():
        return "file", str(path)
    if text in preset_names():
        return "preset", text
    if path.suffix == ".toml" or any(sep in text for sep in ("/", "\\")):
        what = "is not a file" if path.exists() else "does not exist"
        raise InstrumentError(f"instrument file {text!r} {what}; give an instrument .toml file or a preset ({', '.join(preset_names())})")
    raise InstrumentError(
        f"unknown instrument preset {text!r}; choose one of {', '.join(preset_names())} or give the path of an instrument .toml file"
    )


def load_instrument(name_or_path: str | Path) -> Instrument:
    """Load a preset by name (``desi``, ``moons``, ``sdss``) or an instrument TOML file by path.

    An existing file wins over a preset of the same name (:func:`instrument_source`).

    Raises:
        InstrumentError: the preset is unknown, the file is missing or malformed, or a value
            is out of range. The message names the key and what to fix.
    """
    kind, where = instrument_source(name_or_path)
    if kind == "file":
        try:
            raw = Path(str(where)).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise InstrumentError(f"instrument file {where!r} cannot be read ({e})") from e
        origin = f"instrument file {where!r}"
    else:
        raw = (resources.files("fiberplan") / "instruments" / f"{where}.toml").read_text(encoding="utf-8")
        origin = f"preset {where}"
    try:
        data = tomllib.loads(raw)
    except tomllib.TOMLDecodeError as e:
        raise InstrumentError(f"{origin}: not valid TOML ({e})") from e
    return instrument_from_dict(data, origin=origin)


def _table(data: dict[str, Any], key: str, origin: str) -> dict[str, Any]:
    if key not in data:
        raise InstrumentError(f"{origin}: missing key {key!r} (a [{key}] table); see src/fiberplan/instruments/desi.toml for the layout")
    value = data[key]
    if not isinstance(value, dict):
        raise InstrumentError(f"{origin}: [{key}] must be a table; see src/fiberplan/instruments/desi.toml for the layout")
    return value


def _number(table: dict[str, Any], key: str, where: str) -> float:
    if key not in table:
        raise InstrumentError(f"{where}: missing key {key!r}; see src/fiberplan/instruments/desi.toml for the layout")
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InstrumentError(f"{where}: {key} must be a number, found {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise InstrumentError(f"{where}: {key} must be finite, found {value!r}")
    return out


def _pair(table: dict[str, Any], key: str, where: str) -> tuple[float, float]:
    value = table.get(key)
    if not isinstance(value, list) or len(value) != 2:
        raise InstrumentError(f"{where}: {key} must be a pair [first, second] in degrees, found {value!r}")
    first, second = (_number({key: v}, key, where) for v in value)
    return first, second


def instrument_from_dict(data: dict[str, Any], origin: str = "instrument") -> Instrument:
    """Build an :class:`Instrument` from the file layout (mm, deg, rpm).

    Every key is checked: an unknown key (a misspelling such as ``beta_convension``) is an
    error naming it and the closest valid key.

    Raises:
        InstrumentError: a key is missing, unknown, or has the wrong type or value.
    """
    from fiberplan.planners import planner_names  # the registry imports this module

    if not isinstance(data, dict):
        raise InstrumentError(f"{origin}: an instrument must be a table")
    check_keys(data, TOP_KEYS, origin, InstrumentError)
    convention = data.get("beta_convention", "extended")
    if convention not in BETA_CONVENTIONS:
        raise InstrumentError(f"{origin}: beta_convention must be 'extended' or 'folded', found {convention!r}")
    beta_shift = math.pi if convention == "folded" else 0.0
    geometry = _table(data, "geometry", origin)
    motion = _table(data, "motion", origin)
    check_keys(geometry, GEOMETRY_KEYS, f"{origin}: [geometry]", InstrumentError)
    check_keys(motion, MOTION_KEYS, f"{origin}: [motion]", InstrumentError)
    where_m = f"{origin}: [motion]"
    alpha_limits = tuple(math.radians(v) for v in _pair(motion, "alpha_limits_deg", where_m))
    beta_limits = tuple(math.radians(v) + beta_shift for v in _pair(motion, "beta_limits_deg", where_m))
    datum_deg = _pair(motion, "datum_deg", where_m)
    datum = (math.radians(datum_deg[0]), math.radians(datum_deg[1]) + beta_shift)
    raw_capsules = data.get("capsules")
    if not isinstance(raw_capsules, list) or not all(isinstance(c, dict) for c in raw_capsules):
        raise InstrumentError(f"{origin}: [[capsules]] must be a list of tables (name, arm, start_mm, end_mm, radius_mm, layer)")
    capsules = []
    for k, c in enumerate(raw_capsules):
        where_c = f"{origin}: capsule #{k} ({c.get('name', '?')!r})"
        check_keys(c, CAPSULE_KEYS, where_c, InstrumentError)
        layer = c.get("layer", 0)
        if isinstance(layer, bool) or not isinstance(layer, int):
            raise InstrumentError(f"{where_c}: layer must be an integer, found {layer!r}")
        if "name" not in c or "arm" not in c:
            raise InstrumentError(f"{where_c}: missing key {'name' if 'name' not in c else 'arm'!r}")
        capsules.append(
            Capsule(
                name=str(c["name"]), arm=c["arm"], start_mm=_number(c, "start_mm", where_c), end_mm=_number(c, "end_mm", where_c),
                radius_mm=_number(c, "radius_mm", where_c), layer=layer,
            )
        )
    defaults = data.get("planner_defaults", {})
    if not isinstance(defaults, dict):
        raise InstrumentError(f"{origin}: [planner_defaults] must be a table")
    check_keys(defaults, ("dt_s", *planner_names()), f"{origin}: [planner_defaults]", InstrumentError)
    for key, value in defaults.items():
        if key != "dt_s" and not isinstance(value, dict):
            raise InstrumentError(f"{origin}: [planner_defaults.{key}] must be a table of {key} settings")
    if "dt_s" in defaults:
        _number(defaults, "dt_s", f"{origin}: [planner_defaults]")
    sources = data.get("sources", {})
    if not isinstance(sources, dict):
        raise InstrumentError(f"{origin}: [sources] must be a table of strings")
    for key in ("name", "description"):
        if key in data and not isinstance(data[key], str):
            raise InstrumentError(f"{origin}: {key} must be a string, found {data[key]!r}")
    if "name" not in data:
        raise InstrumentError(f"{origin}: missing key 'name'; see src/fiberplan/instruments/desi.toml for the layout")
    where_g = f"{origin}: [geometry]"
    try:
        return Instrument(
            name=str(data["name"]),
            description=str(data.get("description", "")),
            pitch_mm=_number(geometry, "pitch_mm", where_g),
            alpha_arm_mm=_number(geometry, "alpha_arm_mm", where_g),
            beta_arm_mm=_number(geometry, "beta_arm_mm", where_g),
            min_base_distance_mm=_number(geometry, "min_base_distance_mm", where_g) if "min_base_distance_mm" in geometry else None,
            alpha_speed_rad_s=_number(motion, "alpha_speed_rpm", where_m) * _RPM_TO_RAD_S,
            beta_speed_rad_s=_number(motion, "beta_speed_rpm", where_m) * _RPM_TO_RAD_S,
            alpha_limits_rad=(alpha_limits[0], alpha_limits[1]),
            beta_limits_rad=(beta_limits[0], beta_limits[1]),
            datum_rad=datum,
            tolerance_mm=_number(motion, "tolerance_mm", where_m),
            capsules=tuple(capsules),
            sources={str(k): str(v) for k, v in sources.items()},
            planner_defaults=copy.deepcopy(dict(defaults)),
            spec=copy.deepcopy(data),
        )
    except InstrumentError as e:
        if str(e).startswith(origin):
            raise
        raise InstrumentError(f"{origin}: {e}") from e
