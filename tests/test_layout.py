"""Hexagonal layouts and neighbour lists."""

from __future__ import annotations

import numpy as np
import pytest

from fiberplan.errors import ScenarioError
from fiberplan.instrument_io import load_instrument
from fiberplan.layout import focal_plane, hex_patch, neighbour_lists, neighbour_pairs


@pytest.mark.parametrize("n", [1, 7, 19, 61, 500, 5000])
def test_hex_patch_has_n_distinct_lattice_points(n):
    base = hex_patch(n, 10.4)
    assert base.shape == (n, 2)
    assert len(np.unique(np.round(base, 6), axis=0)) == n
    if n > 1:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(base).query(base, k=2)
        assert d[:, 1].min() == pytest.approx(10.4)


def test_full_hexagons():
    for n, rings in ((7, 1), (19, 2), (61, 4)):
        base = hex_patch(n, 1.0)
        assert np.hypot(*base.T).max() == pytest.approx(rings)


def test_fifty_thousand_positioners():
    assert hex_patch(50_000, 10.4).shape == (50_000, 2)


@pytest.mark.parametrize("bad", [0, -3, 50_001, 2.5])
def test_bad_sizes(bad):
    with pytest.raises(ScenarioError, match="number of positioners"):
        hex_patch(bad, 10.4)


def test_focal_plane_by_radius():
    base = focal_plane(100.0, 10.4)
    assert np.hypot(*base.T).max() <= 100.0 + 1e-9
    assert len(base) > 300


@pytest.mark.parametrize("name,expected", [("desi", 6), ("moons-capsules", 18), ("sdss", 18)])
def test_interior_neighbour_count_comes_from_geometry(name, expected):
    inst = load_instrument(name)
    base = hex_patch(61, inst.pitch_mm)
    pairs = neighbour_pairs(inst, base)
    counts = np.bincount(pairs.ravel(), minlength=len(base))
    assert counts[0] == expected  # the centre positioner is interior
    assert (pairs[:, 0] < pairs[:, 1]).all()


def test_neighbour_lists_match_the_pairs():
    inst = load_instrument("desi")
    base = hex_patch(61, inst.pitch_mm)
    pairs = neighbour_pairs(inst, base)
    neighbours, rows = neighbour_lists(pairs, len(base))
    assert sum(len(r) for r in rows) == 2 * len(pairs)
    for i in range(len(base)):
        held = pairs[rows[i]]
        assert np.all((held[:, 0] == i) | (held[:, 1] == i))
        assert np.array_equal(np.where(held[:, 0] == i, held[:, 1], held[:, 0]), neighbours[i])
    centre = pairs[(pairs == 0).any(axis=1)]
    assert sorted(neighbours[0].tolist()) == sorted(centre[centre != 0].tolist())
