"""``fiberplan compare``: planners on the same seeded scenarios, verified, one row each."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import fiberplan.planners as planners_module
from fiberplan.cli import main
from fiberplan.errors import PlannerError, ScenarioError
from fiberplan.planners.straight import StraightSettings, plan_straight
from fiberplan.studies import HARD_KIND, ROW_COLUMNS, aggregate, hard_scenario, run_compare, write_parquet
from fiberplan.verify import verify

FAST_CENTRAL = {"central": {"warm_start": ["straight", "sequential"], "steps": 30}}


@pytest.fixture(scope="module")
def compare_desi7():
    return run_compare("desi", 7, ["central", "straight"], [1], settings=FAST_CENTRAL)


def test_hard_scenario_is_seeded_and_conflicting() -> None:
    a = hard_scenario("desi", 7, 3)
    b = hard_scenario("desi", 7, 3)
    assert a.kind == HARD_KIND and a.seed == 3
    np.testing.assert_array_equal(a.start_deg, b.start_deg)
    np.testing.assert_array_equal(a.target_values, b.target_values)
    straight = plan_straight(a, StraightSettings.for_instrument(a.instrument))
    assert verify(a, straight.trajectory).n_collisions >= 1
    assert a.meta["hard_score"] > 0


def test_rows_gaps_and_aggregates(compare_desi7) -> None:
    rows = {r["planner"]: r for r in compare_desi7.rows}
    assert set(rows) == {"central", "straight"}
    for row in rows.values():
        assert set(ROW_COLUMNS) <= set(row)
    central, straight = rows["central"], rows["straight"]
    assert central["clean"] and central["collisions"] == 0 and central["success_rate"] == 1.0
    assert central["gap_to_central"] == 0.0
    assert central["makespan_over_bound"] >= 0.98
    assert central["solver_status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    # Straight collides on a hard scenario: not clean, no gap.
    assert straight["collisions"] >= 1 and not straight["clean"] and math.isnan(straight["gap_to_central"])
    agg = compare_desi7.aggregates
    assert agg["central"]["gap_to_central"]["median"] == 0.0
    assert agg["straight"]["collisions_total"] >= 1


def test_parquet_has_the_columns(compare_desi7, tmp_path: Path) -> None:
    path = write_parquet(compare_desi7.rows, tmp_path / "out.parquet")
    frame = pd.read_parquet(path)
    assert list(frame.columns)[: len(ROW_COLUMNS)] == list(ROW_COLUMNS)
    assert len(frame) == 2
    assert frame["clean"].dtype == bool
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def test_a_raising_planner_is_a_row_not_a_crash(monkeypatch: pytest.MonkeyPatch) -> None:
    real = planners_module.plan

    def flaky(scenario, name="straight", settings=None, progress=None):
        if name == "straight":
            raise RuntimeError("solver exploded on positioner 3")
        return real(scenario, name, settings, progress)

    monkeypatch.setattr(planners_module, "plan", flaky)
    result = run_compare("desi", 7, ["straight"], [0], kind="random")
    (row,) = result.rows
    assert "solver exploded on positioner 3" in row["error"]
    assert math.isnan(row["success_rate"]) and not row["clean"]
    assert result.aggregates["straight"]["errors"] == 1
    assert math.isnan(aggregate(result.rows)["straight"]["success_rate_mean"])


@pytest.mark.parametrize(
    ("planners", "match"),
    [(["nope"], "unknown planner 'nope'"), ([], "at least one planner"), (["straight", "straight"], "twice")],
)
def test_bad_planner_lists(planners: list[str], match: str) -> None:
    with pytest.raises(PlannerError, match=match):
        run_compare("desi", 7, planners, [0])


def test_bad_kind() -> None:
    with pytest.raises(ScenarioError, match="unknown scenario kind 'weird'"):
        run_compare("desi", 7, ["straight"], [0], kind="weird")


def test_cli_json_and_parquet(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cmp.parquet"
    main([
        "compare", "--instrument", "desi", "--positioners", "7", "--planners", "straight,central", "--seed-list", "2",
        "--set", "central.steps=30", "--set", 'central.warm_start=["straight","sequential"]', "--out", str(out), "--json", "-q",
    ])
    payload = json.loads(capsys.readouterr().out)
    assert payload["parameters"]["seeds"] == [2]
    assert {r["planner"] for r in payload["rows"]} == {"straight", "central"}
    assert payload["aggregates"]["central"]["collisions_total"] == 0
    assert len(pd.read_parquet(out)) == 2


@pytest.mark.parametrize(
    "args",
    [
        ["compare", "--planners", "bogus", "--seeds", "1"],
        ["compare", "--planners", "straight", "--set", "straight.nope=1", "--seeds", "1"],
        ["compare", "--planners", "straight", "--scenario-kind", "weird", "--seeds", "1"],
    ],
)
def test_cli_bad_input_exits_2(args: list[str], tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as info:
        main([*args, "--out", str(tmp_path / "x.parquet"), "-q"])
    assert info.value.code == 2


def test_energy_gap_without_the_makespan_reference() -> None:
    # --energy-gap with central left out of the planners still solves the energy-mode reference
    # at each planner's makespan (it was skipped silently before): the makespan-mode reference is
    # not needed for it, and can come from a stored compare (bench.py gap).
    heard: list[str] = []
    result = run_compare("desi", 7, ["mpc"], [1], settings=FAST_CENTRAL, energy_gap=True, progress=heard.append)
    # The energy-mode solve, the long part of such a run, is reported too.
    assert heard == ["mpc seed 1", "energy reference mpc seed 1"]
    (row,) = result.rows
    assert row["planner"] == "mpc" and row["clean"]
    assert math.isnan(row["gap_to_central"])  # no makespan reference was solved
    assert row["central_energy_same_makespan"] > 0
    # Warm-started from the mpc's own trajectory at its makespan: the reference needs no more energy.
    assert row["energy_gap_to_central"] >= -1e-6
    assert result.parameters["energy_gap"] is True
    # The table shows the energy gap it solved (it showed only the energy before), and only then.
    from fiberplan.studies.compare import format_table

    table = format_table(result)
    assert "e gap" in table and f"{row['energy_gap_to_central']:+.1%}" in table
    plain = run_compare("desi", 7, ["mpc"], [1], settings=FAST_CENTRAL)
    assert "e gap" not in format_table(plain)


def test_planners_with_the_same_trajectory_share_one_energy_solve(monkeypatch: pytest.MonkeyPatch) -> None:
    # On small MOONS groups the mpc and the dnf often return the layer's same candidate: the
    # energy-mode reference at that makespan, from that warm start, is solved once for both.
    import fiberplan.studies.reference as reference
    from fiberplan.metrics import energy
    from fiberplan.planners import plan
    from fiberplan.studies.compare import _add_energy_gaps

    scenario = hard_scenario("desi", 7, 1)
    result = plan(scenario, "mpc")
    calls = []
    real = reference.central_reference
    monkeypatch.setattr(reference, "central_reference", lambda *a, **k: calls.append(1) or real(*a, **k))
    row = {"clean": True, "makespan_s": result.trajectory.times[-1], "energy_rad2_s": energy(result.trajectory)}
    rows = {"mpc": dict(row), "dnf": dict(row), "prioritized": dict(row, makespan_s=row["makespan_s"] + 0.5)}
    _add_energy_gaps(scenario, rows, {"mpc": result, "dnf": result, "prioritized": result}, FAST_CENTRAL["central"])
    assert len(calls) == 2  # mpc and dnf once; a different makespan is a different problem
    assert rows["mpc"]["central_energy_same_makespan"] == rows["dnf"]["central_energy_same_makespan"] > 0
    assert rows["prioritized"]["central_energy_same_makespan"] < rows["mpc"]["central_energy_same_makespan"]  # more time, less energy
