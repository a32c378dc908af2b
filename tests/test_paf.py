"""An instrument's own files (fiberplan.paf): a MOONS PAF configuration and a target list in,
a scenario out; crossing beta arms accepted by MOONS' model and refused by the capsules;
locked positioners never move; priorities decide who keeps a contested target."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import fiberplan as fp
from fiberplan.cli import cli
from fiberplan.errors import ScenarioError
from fiberplan.instrument_io import load_instrument
from fiberplan.paf import moons_zones, read_paf, read_targets, scenario_dict_from_paf
from fiberplan.scenario import scenario_from_dict

DATA = Path(__file__).parent / "data"
PAF = DATA / "moons_crossing.paf"
TARGETS = DATA / "moons_crossing_targets.txt"


def _scenario(targets: Path | None = TARGETS) -> tuple[fp.Scenario, list[str]]:
    data, warnings = scenario_dict_from_paf(PAF, targets)
    return scenario_from_dict(data), warnings


def test_zones_rebuilt_from_the_paf_sizes_are_the_moons_preset():
    paf = read_paf(PAF)
    sizes = {key: paf.number(f"INS.POS.{key}") for key in ("SAFETY", "LENGTH2", "MINDIST", "B1", "B2", "B3", "B4", "TB2", "W3", "W4",
                                                            "D1", "D2", "DW", "WIDTH2")}
    capsules, zones = moons_zones(sizes)
    preset = load_instrument("moons").spec
    assert capsules[0]["radius_mm"] == preset["capsules"][0]["radius_mm"] == 2.5
    for built, shipped in zip(zones, preset["zones"], strict=True):
        assert built["name"] == shipped["name"]
        for key in ("from_mm", "to_mm", "width_mm", "vertices_mm"):
            if key in shipped:
                assert np.allclose(built[key], shipped[key]), (shipped["name"], key)


def test_paf_positions_orientations_and_flags():
    sc, warnings = _scenario()
    assert sc.ids.tolist() == [1, 2, 3, 4]
    # x = r sin(theta), y = r cos(theta), theta clockwise from +Y
    assert np.allclose(sc.base_xy, [[0, 0], [25, 0], [-25, 0], [0, -25]], atol=1e-9)
    assert np.allclose(sc.orient_deg, 0.0)  # ORIENT 90 (clockwise from +Y) = +X
    assert sc.locked.tolist() == [False, False, True, True]  # LOCK T, HEALTH "BROKEN"
    assert sc.target_priority.tolist() == [1, 2, 0, 0]
    assert sc.infeasible == {2: "locked: it cannot move"}  # positioner 3 was given a target
    assert sc.instrument.motors.min_speed_rad_s == pytest.approx(np.array([0.73, 0.98]) * 2 * np.pi / 60)  # SLOW1, SLOW2
    assert warnings == ["positioner 3 locked (INS.POS3.LOCK = T)", 'positioner 4 locked (INS.FIBRE4.HEALTH = "BROKEN")']


def test_crossing_arms_at_different_heights_plan_clean_and_locked_ones_never_move():
    sc, _ = _scenario()
    result = fp.plan(sc, "mpc")
    report = fp.verify(sc, result.trajectory)
    summary = fp.summarize(result, report)
    assert report.ok and summary["collisions"] == 0
    assert summary["reached"] == 2 == int(sc.has_target.sum())
    joints = result.trajectory.joints
    for k in np.flatnonzero(sc.locked):
        assert np.all(joints[:, k] == joints[0, k])  # not a sample away from the start


def test_the_capsule_approximation_refuses_the_crossing_pair_naming_both():
    data, _ = scenario_dict_from_paf(PAF, TARGETS)
    for row in data["positioners"]:
        if row["target"]:
            row["target"].pop("priority", None)
    approx = scenario_from_dict(data).with_instrument(load_instrument("moons-capsules"), "moons-capsules")
    assert "positioner 2's target" in approx.infeasible[0] and "positioner 1's target" in approx.infeasible[1]
    # With priorities, the more important target (1 = first) wins the contest: only the other is
    # refused for it. (Under the capsules positioner 1's target then still touches positioner 2
    # holding at its datum, so it is refused next, for that reason.)
    ranked = scenario_from_dict(scenario_dict_from_paf(PAF, TARGETS)[0]).with_instrument(load_instrument("moons-capsules"))
    assert "positioner 1's target of higher priority" in ranked.infeasible[1]
    assert "positioner 2 (itself held" in ranked.infeasible[0]


def test_cli_writes_the_scenario_and_refuses_generator_options(tmp_path):
    out = tmp_path / "s.json"
    run = CliRunner().invoke(cli, ["scenario", "--paf", str(PAF), "--targets", str(TARGETS), "--out", str(out)])
    assert run.exit_code == 0, run.output
    data = json.loads(out.read_text())
    assert [row.get("locked", False) for row in data["positioners"]] == [False, False, True, True]
    bad = CliRunner().invoke(cli, ["scenario", "--paf", str(PAF), "--seed", "3", "--out", str(tmp_path / "t.json")])
    assert bad.exit_code == 2 and "--seed cannot be used with --paf" in bad.output
    alone = CliRunner().invoke(cli, ["scenario", "--targets", str(TARGETS), "--out", str(tmp_path / "u.json")])
    assert alone.exit_code == 2 and "--targets needs --paf" in alone.output


@pytest.mark.parametrize(("line", "expected"), [
    ("1 20.0 64.9 X\n", "column 4 (parity)"),
    ("1 twenty 64.9 R\n", "column 2 (r_mm)"),
    ("1 20.0 64.9 R 0\n", "column 5 (priority)"),
    ("1 20.0 64.9\n", "found 3 columns"),
    ("1 20.0 64.9 R\n1 21.0 60.0 L\n", "given twice (first on line 1)"),
])
def test_target_list_errors_name_line_and_column(tmp_path, line, expected):
    path = tmp_path / "t.txt"
    path.write_text(line)
    with pytest.raises(ScenarioError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        read_targets(path)


def test_unused_paf_keys_are_listed_not_dropped(tmp_path):
    path = tmp_path / "extra.paf"
    path.write_text(PAF.read_text() + "INS.POS.COLOUR 3;\nINS.POS2.NOTE 1;\n")
    _, warnings = scenario_dict_from_paf(path)
    assert any(w.startswith("INS.POS.COLOUR (line") and "not used" in w for w in warnings)
    assert any(w.startswith("INS.POS2.NOTE (line") and "not used" in w for w in warnings)


def test_paf_errors_name_line_and_key(tmp_path):
    text = PAF.read_text()
    path = tmp_path / "bad.paf"
    path.write_text(text.replace("INS.POS.LENGTH2     17.000;", 'INS.POS.LENGTH2     "17.0";'))
    with pytest.raises(ScenarioError, match=r"line 8: INS.POS.LENGTH2 must be a number"):
        scenario_dict_from_paf(path)
    path.write_text(text.replace("INS.POS3.LOCK       T;", "INS.POS3.LOCK       maybe;"))
    with pytest.raises(ScenarioError, match=r"INS.POS3.LOCK must be T or F"):
        scenario_dict_from_paf(path)
    path.write_text(text + "INS.POS1.RFOCAL 3.0;\n")
    with pytest.raises(ScenarioError, match=r"INS.POS1.RFOCAL is given twice"):
        scenario_dict_from_paf(path)
    targets = tmp_path / "t.txt"
    targets.write_text("9 20.0 10.0 R\n")
    with pytest.raises(ScenarioError, match=r"positioner\(s\) \[9\] are not in PAF file"):
        scenario_dict_from_paf(PAF, targets)


def test_priority_round_trips_through_the_scenario_file(tmp_path):
    sc, _ = _scenario()
    again = fp.load_scenario(sc.save(tmp_path / "s.json"))
    assert again.target_priority.tolist() == sc.target_priority.tolist()
    data = copy.deepcopy(sc.to_dict())
    data["positioners"][0]["target"]["priority"] = 0
    with pytest.raises(ScenarioError, match="priority must be an integer >= 1"):
        scenario_from_dict(data)
