"""A team's own focal plane and targets from CSV/ECSV tables: read strictly, planned."""

from __future__ import annotations

import json

import numpy as np
import pytest

import fiberplan as fp
from fiberplan.errors import ScenarioError
from fiberplan.kinematics import fiber_positions
from fiberplan.layout_io import read_layout, read_target_table


def _write_layout(path, scenario, *, orient=None, locked=(), ecsv=False, first_id=100):
    orient = np.zeros(scenario.n_positioners) if orient is None else orient
    if ecsv:
        lines = ["# %ECSV 1.0", "# ---", "# datatype:", "# - {name: id, datatype: int64}", "# delimiter: ' '", "id x_mm y_mm orient_deg locked"]
        sep = " "
    else:
        lines = ["# a focal plane of my own", "id,x_mm,y_mm,orient_deg,locked"]
        sep = ","
    for k in range(scenario.n_positioners):
        cells = [first_id + k, f"{scenario.base_xy[k, 0]:.6f}", f"{scenario.base_xy[k, 1]:.6f}", f"{orient[k]:.3f}",
                 "true" if k in locked else "false"]
        lines.append(sep.join(map(str, cells)))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("ecsv", [False, True])
def test_read_layout_csv_and_ecsv(tmp_path, ecsv):
    sc = fp.make_scenario("desi", 19, "random", 0)
    orient = np.linspace(-90, 90, 19)
    layout = read_layout(_write_layout(tmp_path / "l.txt", sc, orient=orient, locked=(4,), ecsv=ecsv))
    assert layout.ids.tolist() == list(range(100, 119))
    np.testing.assert_allclose(layout.base_xy, sc.base_xy, atol=1e-6)
    np.testing.assert_allclose(layout.orient_deg, orient, atol=1e-3)
    assert layout.locked.tolist() == [k == 4 for k in range(19)]


def test_make_scenario_on_a_layout_keeps_ids_orientations_and_locks(tmp_path):
    sc = fp.make_scenario("desi", 19, "random", 0)
    orient = np.linspace(-90, 90, 19)
    path = _write_layout(tmp_path / "l.csv", sc, orient=orient, locked=(4,))
    made = fp.make_scenario("desi", None, "random", 2, layout=path)
    assert made.ids.tolist() == list(range(100, 119))
    np.testing.assert_allclose(np.degrees(made.orient), orient, atol=1e-3)
    assert made.locked.tolist() == [k == 4 for k in range(19)]
    assert not made.wants_target[4]
    result = fp.plan(made, "mpc")
    report = fp.verify(made, result.trajectory)
    assert report.ok
    np.testing.assert_array_equal(result.trajectory.joints[:, 4], np.repeat(made.start[None, 4], len(result.trajectory.times), axis=0))
    reached = fp.summarize(result, report)["reached"]
    assert reached == int(made.has_target.sum())


def test_cli_layout_random_then_plan(tmp_path, run_cli):
    """The issue's check, on a 100-positioner layout written here (DESI geometry: MOONS random
    starts under MOONS' own zones are the known slow case of docs/results.md)."""
    sc = fp.make_scenario("desi", 100, "random", 0)
    path = _write_layout(tmp_path / "L.csv", sc, orient=np.full(100, 30.0))
    code, out, _ = run_cli(["scenario", "--instrument", "desi", "--layout", str(path), "--kind", "random", "--seed", "3",
                         "--out", str(tmp_path / "s.json")])
    assert code == 0 and "100 positioners from" in out
    code, out, _ = run_cli(["plan", "--scenario", str(tmp_path / "s.json"), "--planner", "mpc", "--json", "-q"])
    summary = json.loads(out)
    assert code == 0 and summary["collisions"] == 0 and summary["reached"] == summary["targets"] == 100


def test_cli_layout_with_a_target_table(tmp_path, run_cli):
    sc = fp.make_scenario("moons-capsules", 19, "unfold", 1)
    path = _write_layout(tmp_path / "L.csv", sc, locked=(0,))
    xy = fiber_positions(sc.instrument, sc.base_xy, sc.orient, sc.target)
    rows = ["id,x_mm,y_mm,parity,priority"] + [f"{100 + k},{xy[k, 0]:.6f},{xy[k, 1]:.6f},{'R' if sc.target[k, 1] > 0 else 'L'},{1 + k % 2}"
                                                for k in range(1, 19, 2)]
    (tmp_path / "T.csv").write_text("\n".join(rows) + "\n")
    code, _, err = run_cli(["scenario", "--instrument", "moons-capsules", "--layout", str(path), "--targets", str(tmp_path / "T.csv"),
                           "--out", str(tmp_path / "s.json")])
    assert code == 0, err
    made = fp.load_scenario(tmp_path / "s.json")
    assert made.locked.tolist()[0] and int(made.wants_target.sum()) == 9
    assert made.target_priority[made.index_of(101)] == 2
    np.testing.assert_array_equal(made.start, np.repeat(np.array(made.instrument.datum_rad)[None], 19, axis=0))


def test_joint_angle_targets(tmp_path):
    (tmp_path / "T.csv").write_text("id,alpha_deg,beta_deg\n3,10,150\n4,-20.5,90\n")
    assert read_target_table(tmp_path / "T.csv") == {3: {"alpha_deg": 10.0, "beta_deg": 150.0}, 4: {"alpha_deg": -20.5, "beta_deg": 90.0}}


@pytest.mark.parametrize(
    "text,match",
    [
        ("id,x_mm,y_mm\n1,0,0\n", "missing column.s. orient_deg"),
        ("id,x_mm,y_mm,orient_deg,colour\n1,0,0,0,red\n", "unknown column.s. colour"),
        ("id,x_mm,y_mm,orient_deg\n1,0,0,0\n2,abc,0,0\n", "line 3, column x_mm: expected a number, found 'abc'"),
        ("id,x_mm,y_mm,orient_deg\n1,0,0,0\n1,20,0,0\n", "line 3: positioner id 1 repeats line 2"),
        ("id,x_mm,y_mm,orient_deg,locked\n1,0,0,0,maybe\n", "line 2, column locked: expected true or false"),
        ("id,x_mm,y_mm,orient_deg\n1,0,0\n", "line 2: 3 columns where the header has 4"),
        ("id,x_mm,y_mm,orient_deg\n1,nan,0,0\n", "column x_mm: expected a finite number"),
    ],
)
def test_layout_errors_name_line_and_column(tmp_path, text, match):
    (tmp_path / "L.csv").write_text(text)
    with pytest.raises(ScenarioError, match=match):
        read_layout(tmp_path / "L.csv")


@pytest.mark.parametrize(
    "text,match",
    [
        ("id,x_mm\n1,0\n", "either the columns x_mm, y_mm"),
        ("id,x_mm,y_mm,alpha_deg,beta_deg\n1,0,0,0,0\n", "either the columns x_mm, y_mm"),
        ("id,x_mm,y_mm,parity\n1,0,0,up\n", "line 2, column parity: expected 1, -1, R or L, found 'up'"),
        ("id,x_mm,y_mm,priority\n1,0,0,first\n", "line 2, column priority: expected an integer"),
    ],
)
def test_target_table_errors_name_line_and_column(tmp_path, text, match):
    (tmp_path / "T.csv").write_text(text)
    with pytest.raises(ScenarioError, match=match):
        read_target_table(tmp_path / "T.csv")


def test_cli_refuses_targets_of_unknown_or_locked_positioners(tmp_path, run_cli):
    sc = fp.make_scenario("desi", 7, "random", 0)
    path = _write_layout(tmp_path / "L.csv", sc, locked=(2,))
    (tmp_path / "T.csv").write_text("id,alpha_deg,beta_deg\n999,0,90\n")
    code, _, err = run_cli(["scenario", "--layout", str(path), "--targets", str(tmp_path / "T.csv"), "--out", str(tmp_path / "s.json")])
    assert code == 2 and "positioner(s) [999]" in err
    (tmp_path / "T.csv").write_text("id,alpha_deg,beta_deg\n102,0,90\n")
    code, _, err = run_cli(["scenario", "--layout", str(path), "--targets", str(tmp_path / "T.csv"), "--out", str(tmp_path / "s.json")])
    assert code == 2 and "positioner 102 is locked" in err
    code, _, err = run_cli(["scenario", "--layout", str(path), "-n", "19", "--out", str(tmp_path / "s.json")])
    assert code == 2 and "cannot be used with --layout" in err
    assert not (tmp_path / "s.json").exists()
