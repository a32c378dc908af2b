"""Every scenario kind a study, a comparison or a benchmark can name, in one place.

The generator's kinds (``random``, ``unfold``, ``fold``, ``clustered``: :mod:`fiberplan.generate`)
and ``hard``: small groups whose neighbours start and end close together and must cross
(:func:`hard_scenario`), the groups the central reference is measured on. ``hard`` lives here,
above the planners, because it keeps the draw whose straight-line motion the verifier finds
most conflicting.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fiberplan.errors import ScenarioError
from fiberplan.generate import SCENARIO_KINDS, make_scenario
from fiberplan.instrument import Instrument
from fiberplan.instrument_io import instrument_source, load_instrument
from fiberplan.kinematics import move_times
from fiberplan.scenario import Scenario

HARD_KIND = "hard"
STUDY_KINDS = (*SCENARIO_KINDS, HARD_KIND)
"""The scenario kinds of studies, comparisons and benchmarks."""


def hard_scenario(
    instrument: str | Instrument,
    n_positioners: int,
    seed: int,
    *,
    draws: int = 16,
    positioners_per_cluster: int = 2,
    sigma_pitch: float = 1.0 / 6.0,
    background: float = 0.05,
) -> Scenario:
    """A seeded scenario whose neighbours start and end close together and must cross.

    Starts and targets are each drawn from :func:`fiberplan.generate.clustered_sampler`
    (independent Gaussian clusters, one per ``positioners_per_cluster`` positioners, width
    ``sigma_pitch`` pitches, ``background`` uniform share), collision-free. Of ``draws``
    such draws from one generator seeded by ``seed``, the one whose straight-line motion
    (every joint at full speed) has the largest conflict score is kept:

    .. math:: \\text{score} = \\sum_{(i, j)\\ \\text{colliding}} \\max(T_i, T_j) / T_{LB}

    so that conflicts involve the long moves that set the makespan.

    Raises:
        ScenarioError: bad size or no collision-free configuration found.
        InstrumentError: unknown instrument preset.
    """
    from fiberplan.generate import clustered_sampler, joint_scenario, random_configuration
    from fiberplan.layout import hex_patch, neighbour_pairs
    from fiberplan.planners.straight import StraightSettings, plan_straight
    from fiberplan.verify import verify

    if int(draws) != draws or draws < 1:
        raise ScenarioError(f"hard scenario: draws must be an integer >= 1, found {draws}")
    preset = instrument if isinstance(instrument, str) and instrument_source(instrument)[0] == "preset" else None
    inst = load_instrument(instrument) if isinstance(instrument, str) else instrument
    rng = np.random.default_rng(seed)
    base = hex_patch(n_positioners, inst.pitch_mm)
    n = len(base)
    orient = np.zeros(n)
    pairs = neighbour_pairs(inst, base)
    n_clusters = max(1, n // positioners_per_cluster)
    sigma = inst.pitch_mm * sigma_pitch
    best: tuple[float, Scenario] | None = None
    for draw in range(int(draws)):
        start_sampler = clustered_sampler(inst, base, rng, n_clusters=n_clusters, sigma_mm=sigma, background=background)
        start = random_configuration(inst, base, orient, pairs, rng, sampler=start_sampler)
        target_sampler = clustered_sampler(inst, base, rng, n_clusters=n_clusters, sigma_mm=sigma, background=background)
        target = random_configuration(inst, base, orient, pairs, rng, sampler=target_sampler)
        scenario = joint_scenario(
            inst, base, orient, start, target, kind=HARD_KIND, seed=int(seed), instrument_preset=preset,
            meta={"hard_draw": draw, "hard_draws": int(draws)},
        )
        times = move_times(inst, scenario.start, scenario.target)
        lb = float(times.max())
        if lb <= 0:
            continue
        report = verify(scenario, plan_straight(scenario, StraightSettings.for_instrument(inst)).trajectory)
        score = sum(max(times[c.id_i], times[c.id_j]) / lb for c in report.collisions)
        if best is None or score > best[0]:
            best = (score, dataclasses.replace(scenario, meta=scenario.meta | {"hard_score": score}))
    if best is None:
        raise ScenarioError(f"hard scenario: every draw of seed {seed} had start = target; try another seed")
    return best[1]


def study_scenario(instrument: str | Instrument, n_positioners: int, kind: str, seed: int, **options: Any) -> Scenario:
    """A scenario of any kind of :data:`STUDY_KINDS`; ``options`` go to :func:`fiberplan.generate.make_scenario`.

    Raises:
        ScenarioError: unknown kind, bad size, or an option the kind does not take.
    """
    if kind == HARD_KIND:
        if options:
            raise ScenarioError(f"scenario kind 'hard' takes no options, found {', '.join(sorted(options))}")
        return hard_scenario(instrument, n_positioners, seed)
    if kind not in SCENARIO_KINDS:
        raise ScenarioError(f"unknown scenario kind {kind!r}; choose one of {', '.join(STUDY_KINDS)}")
    return make_scenario(instrument, n_positioners, kind, seed, **options)
