"""The command line, run as a user would: exit codes, JSON output, files, and bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from fiberplan.generate import make_scenario
from fiberplan.scenario import TARGET_JOINTS, Scenario

REQUIRED_KEYS = {
    "planner", "instrument", "n_positioners", "seed", "reached", "success_rate", "collisions",
    "makespan_s", "lower_bound_s", "plan_wall_s",
}


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "fiberplan.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300)


def assert_clean_error(proc, *fragments):
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    for fragment in fragments:
        assert fragment in proc.stderr, proc.stderr


def test_plan_then_verify_straight_finds_collisions(tmp_path):
    out = tmp_path / "s.h5"
    proc = run("plan", "--instrument", "desi", "--positioners", 500, "--planner", "straight", "--seed", 1, "--out", out, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert REQUIRED_KEYS <= set(summary)
    assert summary["n_positioners"] == 500 and summary["seed"] == 1 and summary["planner"] == "straight"
    assert summary["collisions"] > 0
    ver = run("verify", out, "--json")
    assert ver.returncode == 1  # violations found
    report = json.loads(ver.stdout)
    assert REQUIRED_KEYS <= set(report)
    assert report["collisions"] == summary["collisions"]
    event = report["report"]["collision_events"][0]
    assert {"id_i", "id_j", "t_first_s", "min_distance_mm"} <= set(event)
    table = run("verify", out)
    assert "collision: positioners" in table.stdout


def test_hand_built_clear_scenario_verifies_clean(tmp_path):
    base = make_scenario("desi", 19, "random", 0)
    n = base.n_positioners
    sc = Scenario(
        instrument=base.instrument, ids=base.ids, base_xy=base.base_xy, orient_deg=np.zeros(n),
        start_deg=np.tile([-90.0, 90.0], (n, 1)), target_kind=np.full(n, TARGET_JOINTS),
        target_values=np.tile([45.0, 150.0], (n, 1)), target_parity=np.zeros(n, dtype=int), instrument_preset="desi",
    )
    path = sc.save(tmp_path / "clear.json")
    out = tmp_path / "clear.h5"
    proc = run("plan", "--scenario", path, "--planner", "straight", "--out", out, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["collisions"] == 0
    ver = run("verify", out, "--json")
    assert ver.returncode == 0 and json.loads(ver.stdout)["collisions"] == 0


def test_scenario_show_animate(tmp_path):
    scen = tmp_path / "m.json"
    assert run("scenario", "--instrument", "moons-capsules", "-n", 19, "--kind", "unfold", "--seed", 2, "--out", scen).returncode == 0
    out = tmp_path / "m.h5"
    proc = run("plan", "--scenario", scen, "--planner", "straight", "--out", out, "--picture", tmp_path / "p.png", "-q")
    assert proc.returncode == 0, proc.stderr
    assert "success_rate" in proc.stdout
    assert run("show", out, "--out", tmp_path / "s.png", "--time", 1.0).returncode == 0
    assert run("animate", out, "--out", tmp_path / "a.gif", "--frames", 5).returncode == 0
    assert (tmp_path / "s.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "a.gif").read_bytes()[:3] == b"GIF"


def test_listing_commands():
    assert "desi" in run("instruments").stdout
    assert "reference 000" in run("instruments", "desi").stdout
    assert "straight" in run("planners").stdout


# ---------------------------------------------------------------- bad input: exit 2, no traceback


def test_unknown_preset():
    assert_clean_error(run("plan", "--instrument", "lamost", "-n", 7, "--planner", "straight"), "unknown instrument preset 'lamost'")


def test_unknown_planner():
    assert_clean_error(run("plan", "-n", 7, "--planner", "teleport"), "unknown planner 'teleport'")


def test_unknown_setting():
    assert_clean_error(run("plan", "-n", 7, "--planner", "straight", "--set", "warp=9"), "has no setting 'warp'")


def test_bad_scenario_kind():
    assert_clean_error(run("plan", "-n", 7, "--planner", "straight", "--scenario-kind", "spiral"), "unknown scenario kind")


def test_truncated_scenario_file(tmp_path):
    path = make_scenario("desi", 7, "random", 1).save(tmp_path / "s.json")
    path.write_text(path.read_text()[:200])
    assert_clean_error(run("plan", "--scenario", path, "--planner", "straight"), "not valid JSON")


@pytest.mark.parametrize(
    "spoil,fragment",
    [
        (lambda rows: rows[3].__setitem__("start_deg", [float("nan"), 0.0]), "positioner 3: start_deg holds a non-finite"),
        (lambda rows: rows[4].__setitem__("start_deg", [0.0, 200.0]), "positioner 4: start joints"),
        (lambda rows: rows[6].__setitem__("id", 2), "id 2 appears 2 times"),
    ],
)
def test_invalid_scenario_names_the_positioner(tmp_path, spoil, fragment):
    data = make_scenario("desi", 7, "random", 1).to_dict()
    spoil(data["positioners"])
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    out = tmp_path / "never.h5"
    assert_clean_error(run("plan", "--scenario", path, "--planner", "straight", "--out", out), fragment)
    assert not out.exists()


def test_verify_bad_files(tmp_path):
    assert_clean_error(run("verify", tmp_path / "missing.h5"), "does not exist")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 50)
    assert_clean_error(run("verify", junk), "cannot read trajectory file")


def test_plan_reports_its_time_split(tmp_path, capsys):
    from fiberplan.cli import main

    main(["plan", "--instrument", "desi", "-n", "7", "--seed", "1", "--json", "-q", "--out", str(tmp_path / "r.h5")])
    summary = json.loads(capsys.readouterr().out)
    assert set(summary["time_split_s"]) == {"plan", "verify", "write"}
    assert all(v >= 0 for v in summary["time_split_s"].values())
    assert summary["time_split_s"]["plan"] <= summary["plan_wall_s"] + 1.0


def test_progress_names_the_phases_and_one_argument_callbacks_still_work():
    import fiberplan as fp

    scenario = fp.make_scenario("desi", 19, "random", 2)
    seen: list[tuple[float, str | None]] = []
    fp.plan(scenario, "mpc", progress=lambda fraction, phase=None: seen.append((fraction, phase)))
    phases = {phase for _, phase in seen if phase}
    assert "planner run 1: start schedule" in phases and "planner run 1: control loop" in phases
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    direct: list[tuple[float, str | None]] = []
    fp.plan(scenario, "mpc", {"route": "direct"}, progress=lambda fraction, phase=None: direct.append((fraction, phase)))
    assert {"start schedule", "control loop"} <= {phase for _, phase in direct}
    plain: list[float] = []
    fp.plan(scenario, "dnf", progress=plain.append)
    assert plain and plain[-1] == 1.0
