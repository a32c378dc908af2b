"""An instrument's own files: ESO parameter files (PAF) of a fibre positioner configuration, and target lists.

MOONS describes its focal plane in an ESO PAF file (``KEY value;`` lines). fiberplan reads:

* global keys ``INS.POS.<KEY>``: the arm lengths (``LENGTH1/2``), top speeds (``FAST1/2``),
  hard stops (``LOW1/2``, ``HIGH1/2``, beta measured from the folded arm), the datum
  (``DEF1/2``), the tolerance (``TOLER``, microns), the closest fibre approach (``MINDIST``),
  the padding of every zone (``SAFETY``) and the zone sizes (``B1 B2 B3 B4 TB2 W3 W4 D1 D2 DW
  WIDTH2``), from which the zones of the ``moons`` preset are rebuilt exactly as MOONS' shared
  library builds them (:func:`moons_zones`);
* per positioner ``n``: ``INS.POS<n>.RFOCAL`` (mm) and ``INS.POS<n>.THFOCAL`` (deg, measured
  clockwise from +Y: ``x = r sin(theta)``, ``y = r cos(theta)``), ``INS.POS<n>.ORIENT`` (deg,
  the direction of alpha = 0, measured the same way: fiberplan's ``orient_deg = 90 - ORIENT``),
  ``INS.POS<n>.LOCK`` (``T``: locked) and ``INS.FIBRE<n>.HEALTH`` (anything but ``OK``/``GOOD``:
  the fibre is unusable and its positioner is locked).

A target list has one row per positioner, ``id r_mm theta_deg parity [priority]`` (``#``
comments, blank lines allowed): the same polar convention, parity ``L`` / ``R`` (or ``-1`` /
``+1``), and a row with ``r = 1e6`` meaning "no target". Every key and row is checked: a key
fiberplan does not use is listed in the warnings, never silently dropped; a malformed value
names its file, line and key.
"""

from __future__ import annotations

import copy
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan.errors import ScenarioError

NO_TARGET_R_MM = 1.0e6
"""A target-list row with this radius (or larger) means "no target" (MOONS' convention)."""
HEALTHY = ("OK", "GOOD", "T", "TRUE", "1")
"""``INS.FIBRE<n>.HEALTH`` values meaning a usable fibre (case-insensitive)."""
PARITIES = {"R": 1, "+1": 1, "1": 1, "L": -1, "-1": -1}
"""Target-list parity: ``R`` = +1 (beta turned counterclockwise from the alpha arm, the elbow to the
right of the line from base to fibre), ``L`` = -1."""

GLOBAL_KEYS = {
    "LENGTH1": "alpha arm length (mm)", "LENGTH2": "beta arm length (mm)",
    "FAST1": "alpha top speed (rpm)", "FAST2": "beta top speed (rpm)",
    "LOW1": "alpha lower hard stop (deg)", "HIGH1": "alpha upper hard stop (deg)",
    "LOW2": "beta lower hard stop (deg, from folded)", "HIGH2": "beta upper hard stop (deg, from folded)",
    "DEF1": "alpha datum (deg)", "DEF2": "beta datum (deg, from folded)", "TOLER": "tolerance (microns)",
    "MINDIST": "closest fibre approach (mm)", "SAFETY": "padding of every zone (mm)",
    "B1": "metrology zone length", "B2": "gap before the metrology zone", "B3": "fibre-snag triangle length",
    "B4": "safe length of the beta arm", "TB2": "metrology triangle length", "W3": "fibre-snag triangle width",
    "W4": "metrology zone width", "D1": "datum foot length", "D2": "datum foot behind the elbow", "DW": "datum foot width",
    "WIDTH2": "beta arm width", "SLOW1": "alpha minimum speed (rpm)", "SLOW2": "beta minimum speed (rpm)",
}
"""The global ``INS.POS.<KEY>`` entries fiberplan reads (all numbers)."""
_PER_POSITIONER = re.compile(r"^INS\.(POS|FIBRE)(\d+)\.([A-Z0-9_]+)$")


@dataclass(frozen=True)
class PafFile:
    """The entries of a PAF file: ``values[key] = (text, line)``, and the file it came from."""

    path: str
    values: dict[str, tuple[str, int]]
    warnings: list[str] = field(default_factory=list)

    def number(self, key: str) -> float:
        """The entry ``key`` as a finite number.

        Raises:
            ScenarioError: missing, or not a number (a quoted string is not a number).
        """
        if key not in self.values:
            raise ScenarioError(f"PAF file {self.path!r}: missing key {key}")
        text, line = self.values[key]
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or text.startswith('"'):
            raise ScenarioError(f"PAF file {self.path!r}, line {line}: {key} must be a number, found {text}")
        return value


def read_paf(path: str | Path) -> PafFile:
    """Read the ``KEY value;`` entries of an ESO parameter file.

    ``#`` starts a comment; a value may be quoted; a key without a value (``PAF.HDR.START;``)
    is kept with an empty value. A line that is not an entry, or a key given twice, is an error.

    Raises:
        ScenarioError: the file is missing or malformed, naming the line.
    """
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"PAF file {str(path)!r} does not exist")
    values: dict[str, tuple[str, int]] = {}
    entry = re.compile(r'^([A-Za-z][A-Za-z0-9_.]*)(?:\s+("[^"]*"|[^\s;"]+))?\s*;\s*(?:#.*)?$')
    for number, raw in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        match = entry.match(line)
        if match is None:
            raise ScenarioError(f"PAF file {str(path)!r}, line {number}: expected 'KEY value;', found {raw.strip()!r}")
        key, value = match.group(1).upper(), match.group(2) or ""
        if key in values:
            raise ScenarioError(f"PAF file {str(path)!r}, line {number}: {key} is given twice (first on line {values[key][1]})")
        values[key] = (value, number)
    return PafFile(str(path), values)


def moons_zones(size: dict[str, float]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The holder capsule and the zones of MOONS' model from its PAF sizes (mm), in the beta arm's frame.

    As MOONS' shared library (fps_shared, 2016-07-27) builds them, each padded by ``SAFETY``:
    holder disc ``MINDIST / 2 + SAFETY``; metrology rectangle from ``LENGTH2 - B1 - SAFETY`` to
    ``LENGTH2 + SAFETY``, ``W4 + 2 SAFETY`` wide; metrology triangle from ``LENGTH2 - B1`` back to
    ``LENGTH2 - B1 - TB2 - 2 SAFETY``; fibre-snag triangle with the padding stretched by
    ``B1 / W3`` at its point; three beta-arm rectangles from ``B4 - SAFETY`` over
    ``LENGTH2 + 2 SAFETY - B4 - B1 - B2``, ``WIDTH2 + 2 SAFETY`` wide; datum foot from
    ``-D2 - SAFETY`` to ``D1 + SAFETY``, ``DW + 2 SAFETY`` wide.
    """
    s, l2 = size["SAFETY"], size["LENGTH2"]
    metrology_end = l2 - size["B1"]
    ratio = size["B1"] / size["W3"]
    holder = {"name": "holder", "arm": "beta", "start_mm": l2, "end_mm": l2, "radius_mm": size["MINDIST"] / 2 + s}
    half4, half3 = size["W4"] / 2 + s, size["W3"] / 2 + s
    zones: list[dict[str, Any]] = [
        {"name": "metrology", "arm": "beta", "shape": "rectangle", "from_mm": metrology_end - s, "to_mm": l2 + s, "width_mm": 2 * half4},
        {"name": "metrology_tip", "arm": "beta", "shape": "polygon",
         "vertices_mm": [[metrology_end, -half4], [metrology_end, half4], [metrology_end - size["TB2"] - 2 * s, 0.0]]},
        {"name": "fibre_snag", "arm": "beta", "shape": "polygon",
         "vertices_mm": [[metrology_end + s / ratio, -half3], [metrology_end + s / ratio, half3],
                         [metrology_end - size["B3"] - s * ratio, 0.0]]},
    ]
    start, length = size["B4"] - s, (l2 + 2 * s - size["B4"] - size["B1"] - size["B2"]) / 3
    for k in range(3):
        zones.append({"name": f"beta_{k + 1}", "arm": "beta", "shape": "rectangle", "from_mm": start + k * length,
                      "to_mm": start + (k + 1) * length, "width_mm": size["WIDTH2"] + 2 * s})
    zones.append({"name": "datum_foot", "arm": "beta", "shape": "rectangle", "from_mm": -size["D2"] - s, "to_mm": size["D1"] + s,
                  "width_mm": size["DW"] + 2 * s})
    return [holder], zones


def instrument_spec_from_paf(paf: PafFile) -> dict[str, Any]:
    """An instrument table (the TOML layout) for the positioners a MOONS PAF file describes.

    The ``moons`` preset gives what a PAF does not (the pitch, the interaction table, the
    planners' defaults); every number the PAF gives replaces the preset's, with the PAF named as
    its source. Unknown global keys are listed in ``paf.warnings``.
    """
    from fiberplan.instrument_io import instrument_text

    spec = tomllib.loads(instrument_text("moons"))
    size = {key: paf.number(f"INS.POS.{key}") for key in GLOBAL_KEYS}
    spec["name"] = f"moons ({Path(paf.path).name})"
    spec["description"] = f"MOONS fibre positioners as PAF file {Path(paf.path).name} describes them, MOONS' avoidance zones"
    geometry, motion = spec["geometry"], spec["motion"]
    geometry["alpha_arm_mm"], geometry["beta_arm_mm"] = size["LENGTH1"], size["LENGTH2"]
    motion["alpha_speed_rpm"], motion["beta_speed_rpm"] = size["FAST1"], size["FAST2"]
    motion["alpha_limits_deg"] = [size["LOW1"], size["HIGH1"]]
    motion["beta_limits_deg"] = [size["LOW2"], size["HIGH2"]]
    motion["datum_deg"] = [size["DEF1"], size["DEF2"]]
    motion["tolerance_mm"] = size["TOLER"] / 1000.0
    spec.setdefault("motors", {})["min_speed_rpm"] = [size["SLOW1"], size["SLOW2"]]
    spec["capsules"], spec["zones"] = moons_zones(size)
    given = f"PAF file {Path(paf.path).name}"
    sources = spec["sources"]
    for key, what in (("alpha_arm_mm", "LENGTH1"), ("beta_arm_mm", "LENGTH2"), ("alpha_speed_rpm", "FAST1"), ("beta_speed_rpm", "FAST2"),
                      ("alpha_limits_deg", "LOW1, HIGH1"), ("beta_limits_deg", "LOW2, HIGH2 (from the folded arm)"),
                      ("datum_deg", "DEF1, DEF2"), ("tolerance_mm", "TOLER (microns)")):
        sources[key] = f"{given}: INS.POS.{what}"
    sources["motors"] = f"{given}: min_speed_rpm from INS.POS.SLOW1, SLOW2; the other motor limits as the moons preset"
    sources["capsules"] = f"{given}: holder radius INS.POS.MINDIST / 2 + INS.POS.SAFETY"
    sources["zones"] = f"{given}: INS.POS.B1 B2 B3 B4 TB2 W3 W4 D1 D2 DW WIDTH2 SAFETY, shapes as fps_shared builds them (fiberplan.paf.moons_zones)"
    for key in sorted(paf.values):
        if key.startswith("INS.POS.") and key[len("INS.POS."):] not in GLOBAL_KEYS:
            paf.warnings.append(f"{key} (line {paf.values[key][1]}) not used: not a key fiberplan reads")
    return spec


@dataclass(frozen=True)
class PafPositioners:
    """Positioners of a PAF file, sorted by number: ids, focal-plane centres (mm), ``orient_deg`` and locks."""

    ids: np.ndarray
    base_xy: np.ndarray
    orient_deg: np.ndarray
    locked: np.ndarray
    lock_reasons: dict[int, str]


def positioners_from_paf(paf: PafFile) -> PafPositioners:
    """The positioners ``INS.POS<n>.*`` of a PAF file.

    Raises:
        ScenarioError: a positioner without ``RFOCAL``/``THFOCAL``, a flag that is not ``T``/``F``.
    """
    keys: dict[int, dict[str, str]] = {}
    for key in paf.values:
        match = _PER_POSITIONER.match(key)
        if match:
            keys.setdefault(int(match.group(2)), {})[f"{match.group(1)}.{match.group(3)}"] = key
    ids = sorted(n for n, k in keys.items() if any(name.startswith("POS.") for name in k))
    if not ids:
        raise ScenarioError(f"PAF file {paf.path!r}: no positioner (expected INS.POS<n>.RFOCAL and INS.POS<n>.THFOCAL entries)")
    for n in sorted(set(keys) - set(ids)):
        paf.warnings.append(f"INS.FIBRE{n}.* given for positioner {n}, which has no INS.POS{n}.* entries: not used")
    base = np.zeros((len(ids), 2))
    orient = np.zeros(len(ids))
    locked = np.zeros(len(ids), dtype=bool)
    reasons: dict[int, str] = {}
    for row, n in enumerate(ids):
        r, theta = paf.number(f"INS.POS{n}.RFOCAL"), math.radians(paf.number(f"INS.POS{n}.THFOCAL"))
        base[row] = (r * math.sin(theta), r * math.cos(theta))
        orient[row] = 90.0 - paf.number(f"INS.POS{n}.ORIENT") if f"INS.POS{n}.ORIENT" in paf.values else 0.0
        if f"INS.POS{n}.LOCK" in paf.values and _flag(paf, f"INS.POS{n}.LOCK"):
            locked[row], reasons[n] = True, f"INS.POS{n}.LOCK = T"
        health = f"INS.FIBRE{n}.HEALTH"
        if health in paf.values and paf.values[health][0].strip('"').upper() not in HEALTHY:
            locked[row] = True
            reasons[n] = "; ".join(filter(None, [reasons.get(n), f"{health} = {paf.values[health][0]}"]))
        for name, key in keys[n].items():
            if name not in ("POS.RFOCAL", "POS.THFOCAL", "POS.ORIENT", "POS.LOCK", "FIBRE.HEALTH"):
                paf.warnings.append(f"{key} (line {paf.values[key][1]}) not used: not a key fiberplan reads")
    return PafPositioners(np.array(ids, dtype=np.int64), base, orient, locked, reasons)


def _flag(paf: PafFile, key: str) -> bool:
    text, line = paf.values[key]
    value = text.strip('"').upper()
    if value not in ("T", "F"):
        raise ScenarioError(f"PAF file {paf.path!r}, line {line}: {key} must be T or F, found {text}")
    return value == "T"


@dataclass(frozen=True)
class TargetRow:
    """One target of a target list: focal-plane x/y (mm), parity (+1/-1) and priority (0: none)."""

    x_mm: float
    y_mm: float
    parity: int
    priority: int


def read_targets(path: str | Path) -> dict[int, TargetRow | None]:
    """Read a target list: ``id r_mm theta_deg parity [priority]`` per row; ``None`` for ``r >= 1e6``.

    Raises:
        ScenarioError: naming the file, line and column of anything malformed, or an id given twice.
    """
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"target list {str(path)!r} does not exist")
    rows: dict[int, TargetRow | None] = {}
    lines: dict[int, int] = {}
    for number, raw in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        text = raw.split("#", 1)[0].replace(",", " ").split()
        if not text:
            continue
        where = f"target list {str(path)!r}, line {number}"
        if len(text) not in (4, 5):
            raise ScenarioError(f"{where}: expected 'id r_mm theta_deg parity [priority]', found {len(text)} columns")
        try:
            ident = int(text[0])
        except ValueError:
            raise ScenarioError(f"{where}, column 1 (id): expected an integer, found {text[0]!r}") from None
        numbers = []
        for column, name in ((1, "r_mm"), (2, "theta_deg")):
            try:
                numbers.append(float(text[column]))
            except ValueError:
                raise ScenarioError(f"{where}, column {column + 1} ({name}): expected a number, found {text[column]!r}") from None
            if not math.isfinite(numbers[-1]):
                raise ScenarioError(f"{where}, column {column + 1} ({name}): expected a finite number, found {text[column]!r}")
        parity = PARITIES.get(text[3].upper())
        if parity is None:
            raise ScenarioError(f"{where}, column 4 (parity): expected L or R (or -1 / +1), found {text[3]!r}")
        priority = 0
        if len(text) == 5:
            try:
                priority = int(text[4])
            except ValueError:
                priority = -1
            if priority < 1:
                raise ScenarioError(f"{where}, column 5 (priority): expected an integer >= 1 (1 = first), found {text[4]!r}")
        if ident in rows:
            raise ScenarioError(f"{where}: positioner {ident} is given twice (first on line {lines[ident]})")
        lines[ident] = number
        r, theta = numbers[0], math.radians(numbers[1])
        rows[ident] = None if r >= NO_TARGET_R_MM else TargetRow(r * math.sin(theta), r * math.cos(theta), parity, priority)
    return rows


def scenario_dict_from_paf(paf_path: str | Path, targets_path: str | Path | None = None) -> tuple[dict[str, Any], list[str]]:
    """The scenario (the JSON layout) of a PAF file and an optional target list, and the warnings.

    Every positioner starts at the datum (MOONS parks its positioners there between
    configurations); a positioner without a row, or with ``r = 1e6``, has no target.

    Raises:
        ScenarioError: either file is malformed, or the target list names a positioner the PAF lacks.
    """
    paf = read_paf(paf_path)
    spec = instrument_spec_from_paf(paf)
    positioners = positioners_from_paf(paf)
    targets = read_targets(targets_path) if targets_path is not None else {}
    unknown = sorted(set(targets) - set(positioners.ids.tolist()))
    if unknown:
        raise ScenarioError(f"target list {str(targets_path)!r}: positioner(s) {unknown[:10]} are not in PAF file {paf.path!r}")
    datum = list(spec["motion"]["datum_deg"])
    if spec.get("beta_convention") == "folded":
        datum = [datum[0], datum[1] + 180.0]
    rows = []
    for k, n in enumerate(positioners.ids.tolist()):
        row: dict[str, Any] = {"id": n, "x_mm": float(positioners.base_xy[k, 0]), "y_mm": float(positioners.base_xy[k, 1]),
                               "orient_deg": float(positioners.orient_deg[k]), "start_deg": list(datum), "target": None}
        target = targets.get(n)
        if target is not None:
            row["target"] = {"x_mm": target.x_mm, "y_mm": target.y_mm, "parity": target.parity,
                             **({"priority": target.priority} if target.priority else {})}
        if positioners.locked[k]:
            row["locked"] = True
        rows.append(row)
    locks = [f"positioner {n} locked ({why})" for n, why in positioners.lock_reasons.items()]
    name = Path(paf.path).stem + (f"+{Path(targets_path).stem}" if targets_path is not None else "")
    scenario = {"format": "fiberplan-scenario", "version": 2, "beta_convention": "extended", "name": name, "kind": "custom", "seed": None,
                "instrument": copy.deepcopy(spec), "meta": {"paf": paf.path, "targets": None if targets_path is None else str(targets_path)},
                "positioners": rows}
    return scenario, [*locks, *paf.warnings]
