"""Motor profiles and time-stamped paths on disk: write what :mod:`fiberplan.profiles` made,
read them back (or any planner's paths) for the verifier.

Forms (the README's formats section shows each):

- ``json``: per positioner and joint, the start time and angle, then ``[duration_s,
  speed_rad_s]`` segments; the scenario is embedded.
- ``csv``: one row per segment (``positioner_id, joint, segment, start_s, duration_s,
  speed_rad_s, start_rad``); reading needs the scenario.
- ``points``: per positioner, for each joint a list of ``[time_s, angle]`` points, the form a
  point-to-point trajectory controller takes (angles in ``"angle_unit"``: ``"rad"`` or ``"deg"``).
- ``h5``: a fiberplan trajectory file whose trajectory is the one the profiles rebuild (so
  ``fiberplan verify`` checks exactly what is exported), with the segment table in ``/profiles``.

Every reader rebuilds a trajectory with :func:`fiberplan.profiles.rebuild`, so the same profiles
give the same samples whatever form they went through.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan._json import json_ready
from fiberplan.errors import FiberplanError, ProfileError
from fiberplan.layout_io import parse_number
from fiberplan.profiles import JOINTS, JointProfile, Profiles, rebuild
from fiberplan.scenario import Scenario, scenario_from_dict
from fiberplan.trajectory import PlanResult, RunFile, Trajectory, save_result

FORMATS = ("h5", "json", "csv", "points")
SUFFIXES = {".h5": "h5", ".hdf5": "h5", ".json": "json", ".csv": "csv"}
PROFILES_FORMAT = "fiberplan-profiles"
POINTS_FORMAT = "fiberplan-points"
VERSION = 1
CSV_COLUMNS = ("positioner_id", "joint", "segment", "start_s", "duration_s", "speed_rad_s", "start_rad")
_AGREE = 1e-9  # a row's derived start time and angle must agree with its segments within this


def format_of(path: Path, given: str | None) -> str:
    """The export form: ``given``, else from the extension (``.json`` is the segment form).

    Raises:
        ProfileError: unknown form or extension.
    """
    if given is not None:
        if given not in FORMATS:
            raise ProfileError(f"unknown profile format {given!r}; choose one of {', '.join(FORMATS)}")
        return given
    found = SUFFIXES.get(path.suffix.lower())
    if found is None:
        raise ProfileError(f"cannot tell the format of {str(path)!r} from its extension; use .h5, .json or .csv, or --format {{{','.join(FORMATS)}}}")
    return found


def write_profiles(profiles: Profiles, result: PlanResult, path: Path, form: str) -> Path:
    """Write ``profiles`` (made from ``result``) to ``path`` in ``form``, atomically."""
    if form == "h5":
        rebuilt = profiles.trajectory()
        stats = dict(result.stats) | {"profiles": profiles.summary()}
        out = PlanResult(  # the profiles end where the samples end: the planner's outcomes stand
            scenario=result.scenario, trajectory=rebuilt, outcome=result.outcome, planner=result.planner, settings=result.settings,
            stats=stats, plan_wall_s=result.plan_wall_s, warnings=result.warnings,
        )
        return save_result(out, path, extra=lambda f: _h5_group(f, profiles))
    if form == "json":
        text = json.dumps(json_ready(_json_document(profiles)), indent=1)
    elif form == "csv":
        text = _csv_text(profiles)
    else:
        text = json.dumps(json_ready(_points_document(profiles)), indent=1)
    with atomic_path(path, what="--out") as tmp:
        tmp.write_text(text)
    return path


def _rows(profiles: Profiles) -> list[tuple[int, str, int, float, float, float, float]]:
    rows = []
    for (i, axis), prof in profiles.joints.items():
        t_knot, q_knot = prof.knots()
        for k, (d, v) in enumerate(zip(prof.durations_s.tolist(), prof.speeds_rad_s.tolist(), strict=True)):
            rows.append((int(profiles.scenario.ids[i]), JOINTS[axis], k, float(t_knot[k]), d, v, float(q_knot[k])))
    return rows


def _csv_text(profiles: Profiles) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for row in _rows(profiles):
        writer.writerow([repr(x) if isinstance(x, float) else x for x in row])
    return buffer.getvalue()


def _json_document(profiles: Profiles) -> dict[str, Any]:
    return {
        "format": PROFILES_FORMAT,
        "version": VERSION,
        "units": {"time": "s", "angle": "rad", "speed": "rad/s"},
        "summary": profiles.summary(),
        "scenario": profiles.scenario.to_dict(),
        "profiles": [
            {"id": int(profiles.scenario.ids[i]), "joint": JOINTS[axis], "start_s": prof.start_s, "start_rad": prof.start_rad,
             "segments": [[d, v] for d, v in zip(prof.durations_s.tolist(), prof.speeds_rad_s.tolist(), strict=True)]}
            for (i, axis), prof in profiles.joints.items()
        ],
    }


def _points_document(profiles: Profiles) -> dict[str, Any]:
    by_id: dict[int, dict[str, Any]] = {}
    for (i, axis), (t_knot, q_knot) in profiles.knots().items():
        entry = by_id.setdefault(int(profiles.scenario.ids[i]), {"id": int(profiles.scenario.ids[i])})
        entry[JOINTS[axis]] = [[t, q] for t, q in zip(t_knot.tolist(), q_knot.tolist(), strict=True)]
    return {"format": POINTS_FORMAT, "version": VERSION, "angle_unit": "rad", "scenario": profiles.scenario.to_dict(),
            "positioners": list(by_id.values())}


def _h5_group(f: h5py.File, profiles: Profiles) -> None:
    group = f.create_group("profiles")
    rows = _rows(profiles)
    group["positioner_id"] = np.array([r[0] for r in rows], dtype=np.int64)
    group["joint"] = np.array([r[1] for r in rows], dtype="S5")
    group["segment"] = np.array([r[2] for r in rows], dtype=np.int64)
    for k, name in enumerate(CSV_COLUMNS[3:], start=3):
        group[name] = np.array([r[k] for r in rows], dtype=float)
    group.attrs["summary_json"] = json.dumps(json_ready(profiles.summary()))
    group.attrs["rows"] = "one per segment; a joint's first row's start_s and start_rad, then every row's duration_s and speed_rad_s, define it"


def read_paths(path: str | Path, scenario: Scenario | None = None) -> tuple[Scenario, Trajectory, str]:
    """Read exported profiles or time-stamped paths (any planner's) and rebuild their trajectory.

    Args:
        path: a profiles JSON or CSV, a points JSON, or a fiberplan HDF5 file with ``/profiles``.
        scenario: the positioners (needed for CSV, and for JSON files without a ``scenario``).

    Returns:
        The scenario, the rebuilt trajectory, and the form read.

    Raises:
        ProfileError: unreadable or malformed file (the message names the row or key), a
            positioner id not in the scenario, or no scenario for a file that holds none.
    """
    path = Path(path)
    if not path.is_file():
        raise ProfileError(f"paths file {str(path)!r} {'does not exist' if not path.exists() else 'is not a regular file'}")
    origin = repr(str(path))
    try:
        if path.suffix.lower() == ".csv":
            return _need(scenario, origin), _from_rows(_need(scenario, origin), _csv_rows(path, origin), origin), "csv"
        if path.suffix.lower() in (".h5", ".hdf5"):
            return _read_h5(path, scenario, origin)
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ProfileError(f"cannot read paths file {origin} ({type(e).__name__}: {e})") from e
    if not isinstance(data, dict) or data.get("format") not in (PROFILES_FORMAT, POINTS_FORMAT):
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ProfileError(f"{origin}: not a fiberplan profiles or points file (format {found!r}; expected {PROFILES_FORMAT!r} or {POINTS_FORMAT!r})")
    if data.get("version") != VERSION:
        raise ProfileError(f"{origin}: unsupported version {data.get('version')!r} (this fiberplan reads {VERSION})")
    if scenario is None:
        if "scenario" not in data:
            raise ProfileError(f"{origin} holds no scenario; give one (fiberplan verify --scenario S.json --paths {path.name})")
        try:
            scenario = scenario_from_dict(data["scenario"], origin=f"{origin} scenario")
        except FiberplanError as e:
            raise ProfileError(str(e)) from e
    if data["format"] == PROFILES_FORMAT:
        return scenario, _from_profiles_json(scenario, data, origin), "json"
    return scenario, _from_points(scenario, data, origin), "points"


def _need(scenario: Scenario | None, origin: str) -> Scenario:
    if scenario is None:
        raise ProfileError(f"{origin} holds no scenario; give one (fiberplan verify --scenario S.json --paths FILE)")
    return scenario


def _index(scenario: Scenario, value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProfileError(f"{where}: positioner id must be an integer, found {value!r}")
    if value not in set(scenario.ids.tolist()):
        raise ProfileError(f"{where}: positioner {value} is not in the scenario (ids {int(scenario.ids.min())}..{int(scenario.ids.max())})")
    return scenario.index_of(value)


def _axis(value: Any, where: str) -> int:
    if value not in JOINTS:
        raise ProfileError(f"{where}: joint must be 'alpha' or 'beta', found {value!r}")
    return JOINTS.index(value)


def _finite(value: Any, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProfileError(f"{where}: {key} must be a finite number, found {value!r}")
    return float(value)


def _profile(start_s: float, start_rad: float, segments: list[tuple[float, float]], where: str) -> JointProfile:
    durations = np.array([d for d, _ in segments], dtype=float)
    if np.any(durations <= 0):
        raise ProfileError(f"{where}: segment durations must be > 0 s, found {durations[durations <= 0][0]!r}")
    return JointProfile(start_s, start_rad, durations, np.array([v for _, v in segments], dtype=float))


def _from_profiles_json(scenario: Scenario, data: dict[str, Any], origin: str) -> Trajectory:
    entries = data.get("profiles")
    if not isinstance(entries, list):
        raise ProfileError(f"{origin}: 'profiles' must be a list of {{id, joint, start_s, start_rad, segments}}")
    joints: dict[tuple[int, int], JointProfile] = {}
    for n, entry in enumerate(entries):
        where = f"{origin} profiles[{n}]"
        if not isinstance(entry, dict) or set(entry) != {"id", "joint", "start_s", "start_rad", "segments"}:
            keys = sorted(entry) if isinstance(entry, dict) else entry
            raise ProfileError(f"{where}: expected the keys id, joint, start_s, start_rad, segments; found {keys!r}")
        key = (_index(scenario, entry["id"], where), _axis(entry["joint"], where))
        if key in joints:
            raise ProfileError(f"{where}: positioner {entry['id']} {entry['joint']} is given twice")
        segments = entry["segments"]
        if not isinstance(segments, list) or not all(isinstance(s, list) and len(s) == 2 for s in segments):
            raise ProfileError(f"{where}: segments must be a list of [duration_s, speed_rad_s]")
        pairs = [(_finite(d, "duration_s", where), _finite(v, "speed_rad_s", where)) for d, v in segments]
        joints[key] = _profile(_finite(entry["start_s"], "start_s", where), _finite(entry["start_rad"], "start_rad", where), pairs, where)
    return Profiles(scenario, dict(sorted(joints.items()))).trajectory()


def _csv_rows(path: Path, origin: str) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        if reader.fieldnames is None or tuple(reader.fieldnames) != CSV_COLUMNS:
            raise ProfileError(f"{origin}: the header must be {','.join(CSV_COLUMNS)}; found {reader.fieldnames}")
        return list(reader)


def _number(text: str, key: str, where: str) -> float:
    return parse_number(text, f"{where}, column {key}", ProfileError)


def _from_rows(scenario: Scenario, rows: list[dict[str, Any]], origin: str) -> Trajectory:
    """Profiles from segment rows (CSV or ``/profiles``): a joint's first row gives its start;
    every later row's derived start must agree with the segments before it."""
    grouped: dict[tuple[int, int], list[tuple[int, dict[str, Any]]]] = {}
    for n, row in enumerate(rows, start=2):
        where = f"{origin} row {n}"
        try:
            ident = int(row["positioner_id"])
        except (TypeError, ValueError) as e:
            raise ProfileError(f"{where}: positioner_id must be an integer, found {row['positioner_id']!r}") from e
        key = (_index(scenario, ident, where), _axis(row["joint"], where))
        grouped.setdefault(key, []).append((n, row))
    joints: dict[tuple[int, int], JointProfile] = {}
    for key, group in grouped.items():
        group.sort(key=lambda item: int(item[1]["segment"]))
        first_n, first = group[0]
        start_s = _number(str(first["start_s"]), "start_s", f"{origin} row {first_n}")
        start_rad = _number(str(first["start_rad"]), "start_rad", f"{origin} row {first_n}")
        pairs = [(_number(str(r["duration_s"]), "duration_s", f"{origin} row {n}"),
                  _number(str(r["speed_rad_s"]), "speed_rad_s", f"{origin} row {n}")) for n, r in group]
        prof = _profile(start_s, start_rad, pairs, f"{origin} row {first_n}")
        t_knot, q_knot = prof.knots()
        for k, (n, r) in enumerate(group):
            if abs(_number(str(r["start_s"]), "start_s", f"{origin} row {n}") - t_knot[k]) > _AGREE or abs(
                    _number(str(r["start_rad"]), "start_rad", f"{origin} row {n}") - q_knot[k]) > _AGREE:
                raise ProfileError(
                    f"{origin} row {n}: start_s/start_rad disagree with the segments before it (expected {t_knot[k]!r}, {q_knot[k]!r})")
        joints[key] = prof
    return Profiles(scenario, dict(sorted(joints.items()))).trajectory()


def _from_points(scenario: Scenario, data: dict[str, Any], origin: str) -> Trajectory:
    unit = data.get("angle_unit")
    if unit not in ("rad", "deg"):
        raise ProfileError(f"{origin}: angle_unit must be 'rad' or 'deg', found {unit!r}")
    entries = data.get("positioners")
    if not isinstance(entries, list):
        raise ProfileError(f"{origin}: 'positioners' must be a list of {{id, alpha, beta}}")
    knots: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    for n, entry in enumerate(entries):
        where = f"{origin} positioners[{n}]"
        if not isinstance(entry, dict) or "id" not in entry or not set(entry) <= {"id", *JOINTS}:
            raise ProfileError(f"{where}: expected the keys id, alpha, beta; found {sorted(entry) if isinstance(entry, dict) else entry!r}")
        i = _index(scenario, entry["id"], where)
        for axis, joint in enumerate(JOINTS):
            if joint not in entry:
                continue
            points = entry[joint]
            if not isinstance(points, list) or not points or not all(isinstance(p, list) and len(p) == 2 for p in points):
                raise ProfileError(f"{where} {joint}: expected a non-empty list of [time_s, angle] points")
            t = np.array([_finite(p[0], "time_s", f"{where} {joint}") for p in points])
            q = np.array([_finite(p[1], "angle", f"{where} {joint}") for p in points])
            if np.any(np.diff(t) <= 0) or t[0] < 0:
                raise ProfileError(f"{where} {joint}: point times must start at >= 0 s and increase strictly")
            knots[(i, axis)] = (t, np.radians(q) if unit == "deg" else q)
    return rebuild(scenario, dict(sorted(knots.items())))


def _profile_rows(path: Path, origin: str) -> list[dict[str, Any]] | None:
    """The ``/profiles`` rows of a trajectory file (``None`` without the group), each dataset read whole."""
    with h5py.File(path, "r") as f:
        if "profiles" not in f:
            return None
        g = f["profiles"]
        columns = {name: g[name][...] for name in CSV_COLUMNS}
    joints = [j.decode("ascii") for j in columns["joint"].tolist()]
    ids, segments = columns["positioner_id"].tolist(), columns["segment"].tolist()
    return [{"positioner_id": int(ident), "joint": joint, "segment": int(seg), **{name: float(columns[name][k]) for name in CSV_COLUMNS[3:]}}
            for k, (ident, joint, seg) in enumerate(zip(ids, joints, segments, strict=True))]


def holds_profiles(path: Path) -> bool:
    """Whether a trajectory file holds motor profiles (a ``/profiles`` group): its trajectory is then motor commands."""
    with h5py.File(path, "r") as f:
        return "profiles" in f


def _read_h5(path: Path, scenario: Scenario | None, origin: str) -> tuple[Scenario, Trajectory, str]:
    from fiberplan.trajectory import read_run

    rows = _profile_rows(path, origin)
    if rows is None:
        raise ProfileError(f"{origin} holds no /profiles group (a plain trajectory file: run `fiberplan verify {path.name}`)")
    scenario = read_run(path).scenario if scenario is None else scenario
    return scenario, _from_rows(scenario, rows, f"{origin} /profiles"), "h5"


def rebuilt_matches(run: RunFile) -> str | None:
    """For a trajectory file (as read) with ``/profiles``: ``None`` when the profiles rebuild its
    trajectory exactly (or it holds none), else what differs."""
    origin = repr(str(run.path))
    rows = _profile_rows(run.path, origin)
    if rows is None:
        return None
    try:
        rebuilt = _from_rows(run.scenario, rows, f"{origin} /profiles")
    except ProfileError as e:
        return f"/profiles cannot be read ({e})"
    stored = run.trajectory
    same = stored.joints.shape == rebuilt.joints.shape and np.array_equal(stored.times, rebuilt.times)
    if not (same and np.array_equal(stored.joints, rebuilt.joints)):
        return "/profiles does not rebuild /trajectory exactly (the file was changed after export)"
    return None
