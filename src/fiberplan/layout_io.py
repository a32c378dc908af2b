"""A team's own focal plane and targets from tables: CSV or ECSV files.

Layout: one row per positioner, columns ``id, x_mm, y_mm, orient_deg`` and optionally
``locked`` (``true``/``false``, ``1``/``0``, ``T``/``F``). Targets: one row per positioner with a
target, columns ``id`` and either ``x_mm, y_mm`` (a fiber position; optional ``parity``: ``1``,
``-1``, ``R`` or ``L``) or ``alpha_deg, beta_deg`` (joint angles, extended convention unless the
instrument's is folded, as scenario files), and optionally ``priority`` (1 first). A positioner
of the layout without a row holds still.

CSV: comma-separated with a header row; lines starting with ``#`` are comments. ECSV (astropy's
text tables, ``# %ECSV 1.0``): the ``#`` header is skipped, the delimiter is read from its
``delimiter:`` entry (default a space). Errors name the file, row and column.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan.errors import ScenarioError

LAYOUT_COLUMNS = ("id", "x_mm", "y_mm", "orient_deg")
LAYOUT_OPTIONAL = ("locked",)
TARGET_POSITION = ("x_mm", "y_mm")
TARGET_JOINTS = ("alpha_deg", "beta_deg")
TARGET_OPTIONAL = ("parity", "priority")
_TRUE = {"true", "1", "t", "yes"}
_FALSE = {"false", "0", "f", "no", ""}


@dataclass(frozen=True, eq=False)
class Layout:
    """Positioners of a focal plane: ids, base positions (mm), orientations (deg), locks."""

    ids: np.ndarray
    base_xy: np.ndarray
    orient_deg: np.ndarray
    locked: np.ndarray
    origin: str
    name: str


def _table(path: str | Path, what: str) -> tuple[list[str], list[tuple[int, list[str]]], str]:
    """Header, ``(line number, cells)`` rows and the quoted origin of a CSV or ECSV file."""
    path = Path(path)
    origin = f"{what} {str(path)!r}"
    if not path.is_file():
        raise ScenarioError(f"{origin} {'does not exist' if not path.exists() else 'is not a regular file'}")
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ScenarioError(f"cannot read {origin} ({type(e).__name__}: {e})") from e
    delimiter = ","
    if lines and lines[0].startswith("# %ECSV"):
        found = re.search(r"^#\s*delimiter:\s*['\"]?(.)['\"]?\s*$", "\n".join(lines), flags=re.MULTILINE)
        delimiter = found.group(1) if found else " "
    numbered = [(n, line) for n, line in enumerate(lines, start=1) if line.strip() and not line.lstrip().startswith("#")]
    if not numbered:
        raise ScenarioError(f"{origin} holds no header row")
    reader = csv.reader([line for _, line in numbered], delimiter=delimiter, skipinitialspace=True)
    cells = list(reader)
    header = [c.strip() for c in cells[0]]
    rows = [(n, [c.strip() for c in row]) for (n, _), row in zip(numbered[1:], cells[1:], strict=True)]
    for n, row in rows:
        if len(row) != len(header):
            raise ScenarioError(f"{origin} line {n}: {len(row)} columns where the header has {len(header)} ({', '.join(header)})")
    return header, rows, origin


def _columns(header: list[str], required: tuple[str, ...], optional: tuple[str, ...], origin: str) -> None:
    missing = [c for c in required if c not in header]
    unknown = [c for c in header if c not in required + optional]
    if missing or unknown or len(set(header)) != len(header):
        parts = ([f"missing column(s) {', '.join(missing)}"] if missing else []) + ([f"unknown column(s) {', '.join(unknown)}"] if unknown else [])
        if len(set(header)) != len(header):
            parts.append("a repeated column")
        raise ScenarioError(f"{origin}: {'; '.join(parts)}; expected {', '.join(required)} and optionally {', '.join(optional)}")


def parse_number(text: str, where: str, error: type[Exception] = ScenarioError) -> float:
    """A table cell as a finite number, else ``error`` naming ``where`` (file, line, column)."""
    try:
        value = float(text)
    except ValueError as e:
        raise error(f"{where}: expected a number, found {text!r}") from e
    if not math.isfinite(value):
        raise error(f"{where}: expected a finite number, found {text!r}")
    return value


def _number(text: str, column: str, where: str) -> float:
    return parse_number(text, f"{where}, column {column}")


def _rows_by_id(rows: list[tuple[int, list[str]]], id_column: int, origin: str) -> Iterator[tuple[str, list[str], int]]:
    """``(where, cells, id)`` of every row, refusing a repeated id (naming both lines)."""
    seen: dict[int, int] = {}
    for n, row in rows:
        where = f"{origin} line {n}"
        ident = _integer(row[id_column], "id", where)
        if ident in seen:
            raise ScenarioError(f"{where}: positioner id {ident} repeats line {seen[ident]}")
        seen[ident] = n
        yield where, row, ident


def _integer(text: str, column: str, where: str) -> int:
    try:
        return int(text)
    except ValueError as e:
        raise ScenarioError(f"{where}, column {column}: expected an integer, found {text!r}") from e


def read_layout(path: str | Path) -> Layout:
    """Read a layout table (see the module docstring).

    Raises:
        ScenarioError: unreadable file, missing or unknown column, a bad cell (named by line and
            column), or a repeated id.
    """
    header, rows, origin = _table(path, "layout")
    _columns(header, LAYOUT_COLUMNS, LAYOUT_OPTIONAL, origin)
    if not rows:
        raise ScenarioError(f"{origin} has a header but no positioner")
    col = {name: header.index(name) for name in header}
    ids, xy, orient, locked = [], [], [], []
    for where, row, ident in _rows_by_id(rows, col["id"], origin):
        ids.append(ident)
        xy.append((_number(row[col["x_mm"]], "x_mm", where), _number(row[col["y_mm"]], "y_mm", where)))
        orient.append(_number(row[col["orient_deg"]], "orient_deg", where))
        flag = row[col["locked"]].lower() if "locked" in col else ""
        if flag not in _TRUE | _FALSE:
            raise ScenarioError(f"{where}, column locked: expected true or false, found {row[col['locked']]!r}")
        locked.append(flag in _TRUE)
    return Layout(np.array(ids), np.array(xy, dtype=float), np.array(orient), np.array(locked), origin, Path(path).stem)


def read_target_table(path: str | Path) -> dict[int, dict[str, Any]]:
    """Read a target table (see the module docstring): ``id -> target`` in the scenario JSON layout.

    Raises:
        ScenarioError: unreadable file, neither or both of the position and joint columns, a bad
            cell (named by line and column), or a repeated id.
    """
    header, rows, origin = _table(path, "target table")
    by_position = all(c in header for c in TARGET_POSITION)
    by_joints = all(c in header for c in TARGET_JOINTS)
    if by_position == by_joints:
        raise ScenarioError(f"{origin}: give either the columns x_mm, y_mm (fiber positions) or alpha_deg, beta_deg (joint angles), "
                            f"found {', '.join(header)}")
    _columns(header, ("id", *(TARGET_POSITION if by_position else TARGET_JOINTS)), TARGET_OPTIONAL if by_position else ("priority",), origin)
    col = {name: header.index(name) for name in header}
    out: dict[int, dict[str, Any]] = {}
    for where, row, ident in _rows_by_id(rows, col["id"], origin):
        if by_position:
            target: dict[str, Any] = {"x_mm": _number(row[col["x_mm"]], "x_mm", where), "y_mm": _number(row[col["y_mm"]], "y_mm", where)}
            if "parity" in col and row[col["parity"]] != "":
                parity = row[col["parity"]]
                if parity not in ("1", "-1", "+1", "R", "L"):
                    raise ScenarioError(f"{where}, column parity: expected 1, -1, R or L, found {parity!r}")
                target["parity"] = parity if parity in ("R", "L") else int(parity)
        else:
            target = {"alpha_deg": _number(row[col["alpha_deg"]], "alpha_deg", where),
                      "beta_deg": _number(row[col["beta_deg"]], "beta_deg", where)}
        if "priority" in col and row[col["priority"]] != "":
            target["priority"] = _integer(row[col["priority"]], "priority", where)
        out[ident] = target
    return out


def scenario_dict_from_tables(instrument: Any, layout_path: str | Path, targets_path: str | Path | None) -> dict[str, Any]:
    """The scenario (JSON layout) of a layout table and an optional target table: every
    positioner starts at the datum; angles in the instrument's convention.

    Args:
        instrument: the :class:`~fiberplan.instrument.Instrument`, and what the file stores for
            it: pass ``(instrument, preset name or None)``.
    """
    inst, preset = instrument
    layout = read_layout(layout_path)
    targets = read_target_table(targets_path) if targets_path is not None else None
    datum = np.degrees(np.array(inst.datum_rad))
    if inst.beta_convention == "folded":
        datum[1] -= 180.0
    rows = layout_rows(layout, np.repeat(datum[None], len(layout.ids), axis=0), targets)
    name = layout.name + (f"+{Path(targets_path).stem}" if targets_path is not None else "")
    return {"format": "fiberplan-scenario", "version": 2, "name": name, "kind": "custom", "seed": None,
            "instrument": preset if preset is not None else inst.to_dict(),
            "meta": {"layout": str(layout_path), "targets": None if targets_path is None else str(targets_path)}, "positioners": rows}


def layout_rows(layout: Layout, start_deg: np.ndarray, targets: dict[int, dict[str, Any]] | None) -> list[dict[str, Any]]:
    """Scenario positioner rows of ``layout`` starting at ``start_deg (N, 2)``, with ``targets``
    (``None``: every positioner holds). Locked positioners keep no target.

    Raises:
        ScenarioError: a target for a positioner the layout lacks, or for a locked one.
    """
    targets = targets or {}
    unknown = sorted(set(targets) - set(layout.ids.tolist()))
    if unknown:
        raise ScenarioError(f"the target table names positioner(s) {unknown[:10]} that {layout.origin} lacks")
    rows = []
    for k, ident in enumerate(layout.ids.tolist()):
        row: dict[str, Any] = {"id": ident, "x_mm": float(layout.base_xy[k, 0]), "y_mm": float(layout.base_xy[k, 1]),
                               "orient_deg": float(layout.orient_deg[k]), "start_deg": [float(v) for v in start_deg[k]],
                               "target": targets.get(ident)}
        if layout.locked[k]:
            if ident in targets:
                raise ScenarioError(f"positioner {ident} is locked in {layout.origin} but has a target; remove one of the two")
            row["locked"] = True
        rows.append(row)
    return rows
