"""Instrument files: presets, TOML reading, and every check a file must pass.

Presets ship inside the package (``src/fiberplan/instruments/*.toml``). A file is read key
by key: an unknown key is an error naming the closest valid one, every number is checked,
and the instrument must make physical sense (see :func:`check_instrument`: capsules within
their arms, a datum at which neighbours on the lattice do not collide).

Joint conventions (``DESIGN.md``): alpha is absolute about the positioner base, beta is
relative to the alpha arm and equal to zero with the arms in line. A file may state
``beta_convention = "folded"`` to give beta limits and datum measured from the folded arm
(MOONS documents do); they are converted by adding 180 deg.
"""

from __future__ import annotations

import copy
import math
import tomllib
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan._keys import check_keys
from fiberplan._registry import planner_names
from fiberplan.errors import InstrumentError
from fiberplan.geometry import min_pair_clearance
from fiberplan.instrument import _RPM_TO_RAD_S, Capsule, Instrument, MotorLimits, Polygon

TOP_KEYS = ("name", "description", "beta_convention", "geometry", "motion", "motors", "capsules", "zones", "interactions",
            "planner_defaults", "sources")
GEOMETRY_KEYS = ("pitch_mm", "alpha_arm_mm", "beta_arm_mm", "min_base_distance_mm")
MOTION_KEYS = ("alpha_speed_rpm", "beta_speed_rpm", "alpha_limits_deg", "beta_limits_deg", "datum_deg", "tolerance_mm")
CAPSULE_KEYS = ("name", "arm", "start_mm", "end_mm", "radius_mm", "layer")
ZONE_KEYS = ("name", "arm", "shape", "vertices_mm", "from_mm", "to_mm", "width_mm", "offset_mm", "radius_mm", "layer")
ZONE_SHAPES = ("polygon", "rectangle")
INTERACTION_KEYS = ("pairs",)
BETA_CONVENTIONS = ("extended", "folded")
MOTOR_KEYS = ("min_speed_rpm", "max_speed_change", "max_segments", "stop_before_reversing", "command_period_s",
              "max_start_stops", "ramp_time_s", "max_acceleration_rpm_per_s")


def check_instrument(instrument: Instrument) -> None:
    """Refuse a datum at which neighbours on the lattice collide: it must be safe for everyone.

    Raises:
        InstrumentError: naming the pitch, the overlap and what to check.
    """
    third = math.sqrt(3.0) / 2.0
    ring = instrument.pitch_mm * np.array([[0.0, 0.0], [1, 0], [0.5, third], [-0.5, third], [-1, 0], [-0.5, -third], [0.5, -third]])
    pairs = np.array([(i, j) for i in range(7) for j in range(i + 1, 7)])
    joints = np.tile(np.array(instrument.datum_rad), (7, 1))
    clearance = min_pair_clearance(instrument, ring, np.zeros(7), joints, pairs)
    if np.any(clearance < 0.0):
        raise InstrumentError(
            f"instrument {instrument.name!r}: at the datum {np.round(np.degrees(instrument.datum_rad), 6).tolist()} deg (extended convention) "
            f"neighbours {instrument.pitch_mm:g} mm apart collide (overlap {-float(clearance.min()):.4g} mm); the datum must be "
            "collision-free for every neighbour pair: check datum_deg, beta_convention and the capsules"
        )



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


def instrument_text(name_or_path: str | Path) -> str:
    """The text of a preset's file (or of an instrument file): a complete file to copy and edit.

    Raises:
        InstrumentError: neither a preset nor a readable file.
    """
    kind, where = instrument_source(name_or_path)
    if kind == "preset":
        return (resources.files("fiberplan") / "instruments" / f"{where}.toml").read_text(encoding="utf-8")
    try:
        return Path(str(where)).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InstrumentError(f"instrument file {where!r} cannot be read ({e})") from e


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
        raise InstrumentError(f"{origin}: missing key {key!r} (a [{key}] table); see a complete file with: fiberplan instruments desi --toml")
    value = data[key]
    if not isinstance(value, dict):
        raise InstrumentError(f"{origin}: [{key}] must be a table; see a complete file with: fiberplan instruments desi --toml")
    return value


def _number(table: dict[str, Any], key: str, where: str) -> float:
    if key not in table:
        raise InstrumentError(f"{where}: missing key {key!r}; see a complete file with: fiberplan instruments desi --toml")
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InstrumentError(f"{where}: {key} must be a number, found {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise InstrumentError(f"{where}: {key} must be finite, found {value!r}")
    return out


def _pair(table: dict[str, Any], key: str, where: str, unit: str = "degrees") -> tuple[float, float]:
    value = table.get(key)
    if not isinstance(value, list) or len(value) != 2:
        raise InstrumentError(f"{where}: {key} must be a pair [first, second] in {unit}, found {value!r}")
    first, second = (_number({key: v}, key, where) for v in value)
    return first, second


def _table_list(raw: Any, key: str, item: str, keys: tuple[str, ...], origin: str) -> Iterator[tuple[str, dict[str, Any]]]:
    """``(where, table)`` of each entry of an array of tables (``[[capsules]]``, ``[[zones]]``), its keys checked."""
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        raise InstrumentError(f"{origin}: [[{key}]] must be a list of tables ({', '.join(keys)})")
    for k, table in enumerate(raw):
        where = f"{origin}: {item} #{k} ({table.get('name', '?')!r})"
        check_keys(table, keys, where, InstrumentError)
        yield where, table


def _zones(raw: Any, origin: str) -> tuple[Polygon, ...]:
    """The ``[[zones]]`` list: convex polygons in an arm's frame, given by their vertices or as
    a rectangle along the arm (``from_mm`` to ``to_mm`` from the arm's joint, ``width_mm`` wide,
    centred ``offset_mm`` to the arm's left)."""
    out = []
    for where, z in _table_list(raw, "zones", "zone", ZONE_KEYS, origin):
        for key in ("name", "arm", "shape"):
            if key not in z:
                raise InstrumentError(f"{where}: missing key {key!r}; see a complete file with: fiberplan instruments moons --toml")
        shape = z["shape"]
        if shape not in ZONE_SHAPES:
            raise InstrumentError(f"{where}: shape must be one of {', '.join(ZONE_SHAPES)}, found {shape!r}")
        allowed = {"polygon": ("vertices_mm",), "rectangle": ("from_mm", "to_mm", "width_mm", "offset_mm")}[shape]
        extra = [key for key in ("vertices_mm", "from_mm", "to_mm", "width_mm", "offset_mm") if key in z and key not in allowed]
        if extra:
            raise InstrumentError(f"{where}: a {shape} takes {', '.join(allowed)}, not {', '.join(extra)}")
        if shape == "polygon":
            verts = z.get("vertices_mm")
            if not isinstance(verts, list) or not all(isinstance(v, list) and len(v) == 2 for v in verts):
                raise InstrumentError(f"{where}: vertices_mm must be a list of [x_mm, y_mm] pairs, found {verts!r}")
            vertices = tuple((_number({"x": v[0]}, "x", where), _number({"y": v[1]}, "y", where)) for v in verts)
        else:
            x0, x1 = _number(z, "from_mm", where), _number(z, "to_mm", where)
            half = 0.5 * _number(z, "width_mm", where)
            y = _number(z, "offset_mm", where) if "offset_mm" in z else 0.0
            if not (x1 > x0 and half > 0):
                raise InstrumentError(f"{where}: a rectangle needs to_mm > from_mm and width_mm > 0")
            vertices = ((x0, y - half), (x1, y - half), (x1, y + half), (x0, y + half))
        layer = z.get("layer", 0)
        if isinstance(layer, bool) or not isinstance(layer, int):
            raise InstrumentError(f"{where}: layer must be an integer, found {layer!r}")
        radius = _number(z, "radius_mm", where) if "radius_mm" in z else 0.0
        try:
            out.append(Polygon(str(z["name"]), z["arm"], vertices, radius, layer))
        except InstrumentError as e:
            raise InstrumentError(f"{where}: {e}") from e
    return tuple(out)


def _interactions(data: dict[str, Any], origin: str) -> tuple[tuple[str, str], ...] | None:
    """The ``[interactions]`` table: ``pairs = [[zone, zone], ...]``, each checked between any two
    positioners both ways round (zone ``a`` of one against zone ``b`` of the other, and the
    reverse); a zone pair not listed is never checked. Without the table, zones on the same
    ``layer`` are checked against each other."""
    if "interactions" not in data:
        return None
    table = data["interactions"]
    where = f"{origin}: [interactions]"
    if not isinstance(table, dict):
        raise InstrumentError(f"{where} must be a table with pairs = [[zone, zone], ...]")
    check_keys(table, INTERACTION_KEYS, where, InstrumentError)
    pairs = table.get("pairs")
    if not isinstance(pairs, list) or not all(isinstance(p, list) and len(p) == 2 and all(isinstance(z, str) for z in p) for p in pairs):
        raise InstrumentError(f"{where}: pairs must be a list of [zone name, zone name], found {pairs!r}")
    return tuple((a, b) for a, b in pairs)


def _motors(data: dict[str, Any], origin: str, top_rad_s: tuple[float, float]) -> MotorLimits:
    """The optional ``[motors]`` table: each key optional, absent = unconstrained. A ramp is
    given as ``ramp_time_s`` or as ``max_acceleration_rpm_per_s`` (alpha, beta), not both; the
    latter becomes the ramp time of the joint slowest to reach its top speed (``top_rad_s``)."""
    if "motors" not in data:
        return MotorLimits()
    table = _table(data, "motors", origin)
    where = f"{origin}: [motors]"
    check_keys(table, MOTOR_KEYS, where, InstrumentError)
    minimum = None
    if "min_speed_rpm" in table:
        lo = _pair(table, "min_speed_rpm", where, unit="rpm (alpha, beta)")
        if min(lo) < 0:
            raise InstrumentError(f"{where}: min_speed_rpm must be >= 0, found {list(lo)}")
        minimum = (lo[0] * _RPM_TO_RAD_S, lo[1] * _RPM_TO_RAD_S)
    change = _number(table, "max_speed_change", where) if "max_speed_change" in table else None
    segments = table.get("max_segments")
    if segments is not None and (isinstance(segments, bool) or not isinstance(segments, int) or segments < 1):
        raise InstrumentError(f"{where}: max_segments must be an integer >= 1, found {segments!r}")
    reverse = table.get("stop_before_reversing", False)
    if not isinstance(reverse, bool):
        raise InstrumentError(f"{where}: stop_before_reversing must be true or false, found {reverse!r}")
    period = _number(table, "command_period_s", where) if "command_period_s" in table else None
    if period is not None and not period > 0:
        raise InstrumentError(f"{where}: command_period_s must be > 0 seconds, found {period!r}")
    if change is not None and not 0 < change < 1:
        raise InstrumentError(f"{where}: max_speed_change must lie in (0, 1) (a relative change), found {change!r}")
    cycles = table.get("max_start_stops")
    if cycles is not None and (isinstance(cycles, bool) or not isinstance(cycles, int) or cycles < 1):
        raise InstrumentError(f"{where}: max_start_stops must be an integer >= 1, found {cycles!r}")
    ramp = None
    if "ramp_time_s" in table and "max_acceleration_rpm_per_s" in table:
        raise InstrumentError(f"{where}: give ramp_time_s or max_acceleration_rpm_per_s, not both (one ramp time follows from the other)")
    if "ramp_time_s" in table:
        ramp = _number(table, "ramp_time_s", where)
        if not ramp > 0:
            raise InstrumentError(f"{where}: ramp_time_s must be > 0 seconds (leave it out for instant speed changes), found {ramp!r}")
    elif "max_acceleration_rpm_per_s" in table:
        acc = _pair(table, "max_acceleration_rpm_per_s", where, unit="rpm per second (alpha, beta)")
        if not min(acc) > 0:
            raise InstrumentError(f"{where}: max_acceleration_rpm_per_s must be > 0 for both joints, found {list(acc)}")
        ramp = max(top / (a * _RPM_TO_RAD_S) for top, a in zip(top_rad_s, acc, strict=True))
    return MotorLimits(minimum, change, segments, reverse, period, cycles, ramp)


def instrument_from_dict(data: dict[str, Any], origin: str = "instrument") -> Instrument:
    """Build an :class:`Instrument` from the file layout (mm, deg, rpm).

    Every key is checked: an unknown key (a misspelling such as ``beta_convension``) is an
    error naming it and the closest valid key.

    Raises:
        InstrumentError: a key is missing, unknown, or has the wrong type or value.
    """
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
    raw_capsules = data.get("capsules", [] if "zones" in data else None)
    capsules = []
    for where_c, c in _table_list(raw_capsules, "capsules", "capsule", CAPSULE_KEYS, origin):
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
    polygons = _zones(data.get("zones", []), origin)
    interactions = _interactions(data, origin)
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
        raise InstrumentError(f"{origin}: missing key 'name'; see a complete file with: fiberplan instruments desi --toml")
    where_g = f"{origin}: [geometry]"
    try:
        instrument = Instrument(
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
            capsules=tuple(capsules) + tuple(edge for poly in polygons for edge in poly.edges()),
            polygons=polygons,
            interactions=interactions,
            sources={str(k): str(v) for k, v in sources.items()},
            planner_defaults=copy.deepcopy(dict(defaults)),
            spec=copy.deepcopy(data),
            motors=_motors(data, origin, (_number(motion, "alpha_speed_rpm", where_m) * _RPM_TO_RAD_S,
                                          _number(motion, "beta_speed_rpm", where_m) * _RPM_TO_RAD_S)),
        )
        check_instrument(instrument)
        return instrument
    except InstrumentError as e:
        if str(e).startswith(origin):
            raise
        raise InstrumentError(f"{origin}: {e}") from e
