"""Positioner layouts on a hexagonal lattice, and neighbour lists from geometry."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from fiberplan.errors import ScenarioError
from fiberplan.instrument import Instrument

MAX_POSITIONERS = 50_000


def _lattice_points(rings: int, pitch_mm: float) -> np.ndarray:
    """All hexagonal lattice points within ``rings`` rings of the origin, shape ``(M, 2)``."""
    grid_q, grid_r = np.meshgrid(np.arange(-rings, rings + 1), np.arange(-rings, rings + 1), indexing="ij")
    q, r = grid_q.ravel(), grid_r.ravel()
    keep = (np.abs(q) + np.abs(r) + np.abs(q + r)) // 2 <= rings
    q, r = q[keep], r[keep]
    return np.stack([pitch_mm * (q + 0.5 * r), pitch_mm * (math.sqrt(3) / 2) * r], axis=-1)


def _sort_from_centre(points: np.ndarray) -> np.ndarray:
    """Order points by distance from the origin, then by angle (deterministic)."""
    dist = np.round(np.hypot(points[:, 0], points[:, 1]), 9)
    angle = np.round(np.mod(np.arctan2(points[:, 1], points[:, 0]), 2 * np.pi), 9)
    return points[np.lexsort((angle, dist))]


def hex_patch(n_positioners: int, pitch_mm: float) -> np.ndarray:
    """Bases of the ``n_positioners`` lattice points closest to the centre, shape ``(n, 2)``.

    For ``n = 1, 7, 19, 37, 61, ...`` the patch is a full hexagon; other counts fill the
    next ring from the points closest to the centre.

    Raises:
        ScenarioError: ``n_positioners`` is not between 1 and 50,000.
    """
    if not (1 <= int(n_positioners) <= MAX_POSITIONERS) or int(n_positioners) != n_positioners:
        raise ScenarioError(f"number of positioners must be an integer from 1 to {MAX_POSITIONERS}, found {n_positioners}")
    n = int(n_positioners)
    rings = 0
    while 3 * rings * (rings + 1) + 1 < 1.3 * n + 7:
        rings += 1
    return _sort_from_centre(_lattice_points(rings + 1, pitch_mm))[:n]


def focal_plane(radius_mm: float, pitch_mm: float) -> np.ndarray:
    """Bases of every lattice point within ``radius_mm`` of the centre.

    Raises:
        ScenarioError: the radius is not positive or gives more than 50,000 positioners.
    """
    if not (math.isfinite(radius_mm) and radius_mm > 0):
        raise ScenarioError(f"focal-plane radius must be a positive number of mm, found {radius_mm}")
    # Refused before any allocation: a lattice cell holds sqrt(3)/2 pitch^2 of area.
    estimate = math.pi * radius_mm**2 / (math.sqrt(3) / 2 * pitch_mm**2)
    if estimate > 1.1 * MAX_POSITIONERS + 100:
        raise ScenarioError(
            f"a focal plane of radius {radius_mm:g} mm at pitch {pitch_mm:g} mm holds about {estimate:,.0f} positioners; "
            f"the limit is {MAX_POSITIONERS:,}"
        )
    rings = math.ceil(radius_mm / (pitch_mm * math.sqrt(3) / 2)) + 1
    points = _sort_from_centre(_lattice_points(rings, pitch_mm))
    points = points[np.hypot(points[:, 0], points[:, 1]) <= radius_mm + 1e-9]
    if len(points) > MAX_POSITIONERS:
        raise ScenarioError(f"a focal plane of radius {radius_mm} mm holds {len(points)} positioners; the limit is {MAX_POSITIONERS}")
    return points


def neighbour_pairs(instrument: Instrument, base_xy: np.ndarray) -> np.ndarray:
    """Pairs ``(i, j)``, ``i < j``, whose capsules can ever touch, shape ``(P, 2)``.

    Two positioners are neighbours when their bases are closer than twice the largest
    distance any capsule surface reaches from its base; nothing is assumed about 6 or 18.
    """
    if len(base_xy) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    tree = cKDTree(base_xy)
    pairs = tree.query_pairs(2.0 * instrument.extent_mm, output_type="ndarray")
    pairs = np.sort(pairs.astype(np.int64), axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def neighbour_lists(pairs: np.ndarray, n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each positioner's neighbours and the rows of ``pairs`` (``(P, 2)``, e.g. from
    :func:`neighbour_pairs`) that hold them: partners where it is first in ``pairs``, then where
    it is second, each in pair order (one sort per column, not a scan of all pairs per
    positioner)."""
    partners, rows = [], []
    for own, other in ((0, 1), (1, 0)):
        order = np.argsort(pairs[:, own], kind="stable")
        cuts = np.searchsorted(pairs[order, own], np.arange(1, n))
        partners.append(np.split(pairs[order, other], cuts))
        rows.append(np.split(order, cuts))
    return ([np.concatenate(p) for p in zip(*partners, strict=True)],
            [np.concatenate(r) for r in zip(*rows, strict=True)])
