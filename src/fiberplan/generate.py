"""Seeded scenario generators: random, unfold, fold and clustered (galaxy-like) targets.

Randomness is explicit: every generator takes a seed or a ``numpy.random.Generator`` and
never touches the global generator, so the same seed gives the same scenario.

Kinds:

- ``random``: random collision-free start -> random collision-free targets (reference 000's
  simulation sets);
- ``unfold``: datum (folded) start -> random targets (reference 002);
- ``fold``: random start -> datum;
- ``clustered``: random start -> targets drawn from a clustered, galaxy-like field, so that
  neighbours' targets fall close together.

Random fiber positions are uniform in each positioner's patrol region (area-uniform in the
annulus ``[reach_min, reach_max]``); the parity is drawn at random where both are allowed.
Colliding positioners are redrawn until the configuration is collision-free.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from fiberplan.errors import ScenarioError
from fiberplan.geometry import default_safety_margin_mm, min_pair_clearance
from fiberplan.instrument import Instrument
from fiberplan.instrument_io import instrument_source, load_instrument
from fiberplan.kinematics import inverse_kinematics
from fiberplan.layout import focal_plane, hex_patch, neighbour_pairs
from fiberplan.scenario import TARGET_JOINTS, Scenario

SCENARIO_KINDS = ("random", "unfold", "fold", "clustered")

DRAWN_START_KINDS = ("random", "fold", "clustered")
"""Kinds whose start is drawn (and keeps ``min_start_clearance_mm``); ``unfold`` starts at the datum."""

Sampler = Callable[[np.ndarray, np.random.Generator], np.ndarray]
"""Draws fiber positions ``(len(rows), 2)`` for the given positioner rows."""


def _uniform_patrol_points(instrument: Instrument, base_xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Points uniform in each base's patrol annulus, shape ``base_xy.shape``."""
    lo, hi = instrument.reach_min_mm, instrument.reach_max_mm
    n = len(base_xy)
    # Stay a hair inside the reach circles so inverse kinematics never rounds outside them.
    radius = np.sqrt(rng.uniform((lo + 1e-6) ** 2, (hi - 1e-6) ** 2, n))
    angle = rng.uniform(0.0, 2 * np.pi, n)
    return base_xy + radius[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def _joints_for_points(
    instrument: Instrument, base_xy: np.ndarray, orient: np.ndarray, points: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Joint angles for fiber points with a random allowed parity (NaN rows where none fits)."""
    n = len(points)
    parity = rng.choice(np.array([1, -1]), size=n)
    joints = inverse_kinematics(instrument, base_xy, orient, points, parity)
    missing = np.isnan(joints[:, 0])
    if np.any(missing):
        joints[missing] = inverse_kinematics(instrument, base_xy[missing], orient[missing], points[missing], -parity[missing])
    return joints


def random_configuration(
    instrument: Instrument,
    base_xy: np.ndarray,
    orient: np.ndarray,
    pairs: np.ndarray,
    rng: np.random.Generator,
    sampler: Sampler | None = None,
    max_rounds: int = 1000,
    min_clearance_mm: float = 0.0,
) -> np.ndarray:
    """A collision-free configuration with fibers drawn by ``sampler`` (uniform by default).

    Every positioner is drawn once; then, round after round, one positioner of every
    colliding pair (the later index) is drawn again until no pair collides. With
    ``min_clearance_mm > 0``, pairs that are then closer than that are drawn again the same
    way, from a generator spawned from ``rng`` (so that ``rng``'s own stream, and everything
    drawn from it afterwards, is the same as without the minimum: only configurations that
    had a pair that close change, and only in the positioners drawn again).

    Raises:
        ScenarioError: no configuration was found in ``max_rounds`` rounds.
    """
    joints = _separated(instrument, base_xy, orient, pairs, rng, sampler, max_rounds, 0.0, None)
    if min_clearance_mm > 0.0 and len(pairs):
        joints = _separated(instrument, base_xy, orient, pairs, rng, sampler, max_rounds, float(min_clearance_mm), joints)
    return joints


def _separated(
    instrument: Instrument,
    base_xy: np.ndarray,
    orient: np.ndarray,
    pairs: np.ndarray,
    rng: np.random.Generator,
    sampler: Sampler | None,
    max_rounds: int,
    min_clearance_mm: float,
    joints: np.ndarray | None,
) -> np.ndarray:
    """Draw (``joints`` None) or take ``joints``, then redraw until every pair is at least
    ``min_clearance_mm`` apart (0: does not collide); a given ``joints`` that needs a redraw is
    redrawn from a generator spawned from ``rng``."""
    if joints is not None:
        if len(pairs) == 0 or min_pair_clearance(instrument, base_xy, orient, joints, pairs).min() >= min_clearance_mm:
            return joints
        joints = joints.copy()
        rng = rng.spawn(1)[0]

    def draw(rows: np.ndarray) -> np.ndarray:
        for _ in range(100):
            pts = (
                _uniform_patrol_points(instrument, base_xy[rows], rng)
                if sampler is None
                else sampler(rows, rng)
            )
            joints = _joints_for_points(instrument, base_xy[rows], orient[rows], pts, rng)
            bad = np.isnan(joints[:, 0])
            if not np.any(bad):
                return joints
            # Retry only the rows whose point no parity reaches.
            if np.all(bad):
                continue
            out = joints
            out[bad] = draw(rows[bad])
            return out
        raise ScenarioError(f"could not draw a reachable fiber position for positioner row {rows[0]}")

    n = len(base_xy)
    if joints is None:
        joints = draw(np.arange(n))
    for _ in range(max_rounds):
        if len(pairs) == 0:
            return joints
        clearance = min_pair_clearance(instrument, base_xy, orient, joints, pairs)
        colliding = pairs[clearance < min_clearance_mm]
        if len(colliding) == 0:
            return joints
        # Redraw the later index of each colliding pair, and sometimes the earlier one so
        # that a positioner boxed in by fixed neighbours can still get out.
        redraw = np.unique(np.where(rng.random(len(colliding)) < 0.8, colliding[:, 1], colliding[:, 0]))
        joints[redraw] = draw(redraw)
    if min_clearance_mm > 0.0:
        raise ScenarioError(
            f"no configuration with every pair at least {min_clearance_mm} mm apart found after {max_rounds} rounds for {n} "
            "positioners; lower min_start_clearance_mm (--min-start-clearance-mm)"
        )
    raise ScenarioError(
        f"no collision-free configuration found after {max_rounds} rounds for {n} positioners; "
        "the targets may be too dense for this instrument"
    )


def clustered_sampler(
    instrument: Instrument,
    base_xy: np.ndarray,
    rng: np.random.Generator,
    *,
    n_clusters: int | None = None,
    sigma_mm: float | None = None,
    background: float = 0.2,
    proposals: int = 64,
) -> Sampler:
    """Sampler of galaxy-like targets: Gaussian clusters over a uniform background.

    The field density is ``background`` uniform plus ``1 - background`` spread over
    ``n_clusters`` Gaussian blobs of width ``sigma_mm`` (defaults: one cluster per 8
    positioners, sigma a third of the pitch). Each positioner's target is drawn from that
    density restricted to its patrol annulus (importance resampling of ``proposals``
    uniform candidates), so neighbours' targets fall close together.
    """
    n = len(base_xy)
    n_clusters = max(1, n // 8) if n_clusters is None else int(n_clusters)
    sigma = instrument.pitch_mm / 3.0 if sigma_mm is None else float(sigma_mm)
    margin = instrument.reach_max_mm
    lo = base_xy.min(axis=0) - margin
    hi = base_xy.max(axis=0) + margin
    centres = rng.uniform(lo, hi, size=(n_clusters, 2))
    area = float(np.prod(hi - lo))
    tree = cKDTree(centres)
    k_near = min(8, n_clusters)

    def sample(rows: np.ndarray, gen: np.random.Generator) -> np.ndarray:
        base = base_xy[rows]
        cand = np.stack([_uniform_patrol_points(instrument, base, gen) for _ in range(proposals)], axis=1)
        _, near = tree.query(base, k=k_near)
        near = np.asarray(near).reshape(len(rows), k_near)
        diff = cand[:, :, None, :] - centres[near][:, None, :, :]
        blobs = np.exp(-0.5 * np.sum(diff**2, axis=-1) / sigma**2).sum(axis=-1) / (2 * np.pi * sigma**2 * n_clusters)
        weight = background / area + (1.0 - background) * blobs
        cdf = np.cumsum(weight, axis=1)
        pick = (cdf < gen.random(len(rows))[:, None] * cdf[:, -1:]).sum(axis=1)
        return cand[np.arange(len(rows)), np.minimum(pick, proposals - 1)]

    return sample


def make_scenario(
    instrument: str | Instrument = "desi",
    n_positioners: int | None = 500,
    kind: str = "random",
    seed: int | np.random.Generator = 0,
    *,
    radius_mm: float | None = None,
    random_orientation: bool = False,
    clusters: int | None = None,
    cluster_fraction: float = 0.8,
    instrument_preset: str | None = None,
    layout: Any = None,
    min_start_clearance_mm: float | None = None,
) -> Scenario:
    """Generate a seeded scenario on a hexagonal patch, a full focal plane by radius, or a given layout.

    Args:
        instrument: preset name, instrument file path, or :class:`Instrument`.
        n_positioners: size of the hexagonal patch (ignored when ``radius_mm`` is given).
        kind: one of ``random``, ``unfold``, ``fold``, ``clustered``.
        seed: integer seed or a ``numpy.random.Generator``.
        radius_mm: lay out every lattice point within this radius instead of a patch.
        random_orientation: draw each base orientation uniformly (default: all zero).
        clusters: number of target clusters for ``clustered`` (default one per 8 positioners).
        cluster_fraction: share of the target density in the clusters for ``clustered``
            (0: uniform targets, close to 1: crowded clusters); a knob for target density.
        instrument_preset: the preset name of an :class:`Instrument` given as an object (files
            then store the name instead of the table).
        layout: a :class:`fiberplan.layout_io.Layout` or the path of a layout table (CSV/ECSV:
            ``id, x_mm, y_mm, orient_deg[, locked]``): its positioners, ids and orientations
            replace the patch (``n_positioners`` and ``radius_mm`` are then ignored); locked
            positioners keep their drawn start and get no target.
        min_start_clearance_mm: every pair of a drawn start (``random``, ``fold``,
            ``clustered``) is at least this far apart (default: the instrument's
            :func:`~fiberplan.geometry.default_safety_margin_mm`, so that no positioner starts
            closer to a neighbour than the planners' safety layers let a step come). Only the
            starts that had a pair closer than this are drawn again (see
            :func:`random_configuration`); 0 gives the starts drawn before the minimum existed
            (before commit 2ebfbe3). For ``unfold`` (the datum start) a given value is checked.

    Raises:
        ScenarioError: unknown kind, bad size, or no collision-free configuration found.
        InstrumentError: unknown instrument preset.
    """
    if kind not in SCENARIO_KINDS:
        raise ScenarioError(f"unknown scenario kind {kind!r}; choose one of {', '.join(SCENARIO_KINDS)}")
    if isinstance(instrument, str):
        kind_of, where = instrument_source(instrument)
        preset = where if kind_of == "preset" else None
        inst = load_instrument(instrument)
    else:
        inst, preset = instrument, instrument_preset
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer, np.random.Generator)):
        raise ScenarioError(f"seed must be an integer or a numpy.random.Generator, found {seed!r}")
    if not isinstance(seed, np.random.Generator) and not 0 <= int(seed) <= 2**63 - 1:
        raise ScenarioError(f"seed must lie in [0, 2**63 - 1], found {seed}")
    if radius_mm is None and (isinstance(n_positioners, bool) or not isinstance(n_positioners, (int, np.integer, type(None)))):
        raise ScenarioError(f"n_positioners must be an integer, found {n_positioners!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    if layout is not None:
        from fiberplan.layout_io import Layout, read_layout

        table = layout if isinstance(layout, Layout) else read_layout(layout)
        if random_orientation:
            raise ScenarioError("random_orientation cannot be used with a layout (the layout gives the orientations)")
        base = table.base_xy
    elif radius_mm is not None:
        base = focal_plane(radius_mm, inst.pitch_mm)
    else:
        if n_positioners is None:
            raise ScenarioError("give n_positioners or radius_mm")
        base = hex_patch(n_positioners, inst.pitch_mm)
    n = len(base)
    orient = rng.uniform(-np.pi, np.pi, n) if random_orientation else np.zeros(n)
    if layout is not None:
        orient = np.radians(table.orient_deg)
    pairs = neighbour_pairs(inst, base)
    datum = np.broadcast_to(np.array(inst.datum_rad), (n, 2)).copy()

    given_clearance = min_start_clearance_mm is not None
    min_start = default_safety_margin_mm(inst) if min_start_clearance_mm is None else min_start_clearance_mm
    if isinstance(min_start, bool) or not isinstance(min_start, (int, float, np.integer, np.floating)) or not np.isfinite(min_start) or min_start < 0:
        raise ScenarioError(f"min_start_clearance_mm must be a finite number of mm >= 0, found {min_start_clearance_mm!r}")
    if kind == "unfold":
        start = datum
        if given_clearance and len(pairs) and (closest := float(min_pair_clearance(inst, base, orient, datum, pairs).min())) < min_start:
            raise ScenarioError(f"min_start_clearance_mm {min_start} mm: the datum start of an unfold has pairs {closest:.4f} mm "
                                "apart; lower min_start_clearance_mm (--min-start-clearance-mm) or leave it unset")
    else:
        start = random_configuration(inst, base, orient, pairs, rng, min_clearance_mm=float(min_start))
    if kind == "fold":
        target = datum
    elif kind == "clustered":
        if not 0.0 <= cluster_fraction <= 1.0:
            raise ScenarioError(f"cluster_fraction must lie in [0, 1], found {cluster_fraction}")
        sampler = clustered_sampler(inst, base, rng, n_clusters=clusters, background=1.0 - cluster_fraction)
        target = random_configuration(inst, base, orient, pairs, rng, sampler=sampler)
    else:
        target = random_configuration(inst, base, orient, pairs, rng)

    seed_value = None if isinstance(seed, np.random.Generator) else int(seed)
    made = joint_scenario(inst, base, orient, start, target, kind=kind, seed=seed_value, instrument_preset=preset)
    if layout is None:
        return made
    return _on_layout(made, table)


def _on_layout(made: Scenario, table: Any) -> Scenario:
    """``made`` (generated on the layout's bases) with the layout's ids and locks; locked
    positioners hold their drawn start (a target that then collides with one is reported
    infeasible, naming it)."""
    from fiberplan.scenario import scenario_from_dict

    data = made.to_dict()
    for row, ident, locked in zip(data["positioners"], table.ids.tolist(), table.locked.tolist(), strict=True):
        row["id"] = ident
        if locked:
            row["locked"] = True
            row["target"] = None
    data["name"] = f"{made.instrument.name}-{table.name}-{made.kind}-seed{made.seed}"
    data["meta"] = dict(data.get("meta") or {}) | {"layout": table.origin}
    return scenario_from_dict(data, origin=table.origin)


def joint_scenario(
    instrument: Instrument,
    base_xy: np.ndarray,
    orient: np.ndarray,
    start: np.ndarray,
    target: np.ndarray,
    *,
    kind: str,
    seed: int | None,
    instrument_preset: str | None = None,
    meta: dict[str, Any] | None = None,
) -> Scenario:
    """A scenario with ids ``0..N-1`` and joint-angle targets, from radian arrays."""
    n = len(base_xy)
    return Scenario(
        instrument=instrument,
        ids=np.arange(n),
        base_xy=base_xy,
        orient_deg=np.degrees(orient),
        start_deg=np.degrees(start),
        target_kind=np.full(n, TARGET_JOINTS),
        target_values=np.degrees(target),
        target_parity=np.zeros(n, dtype=np.int64),
        name=f"{instrument.name}-{n}-{kind}-seed{seed}",
        kind=kind,
        seed=seed,
        instrument_preset=instrument_preset,
        meta=dict(meta or {}),
    )

