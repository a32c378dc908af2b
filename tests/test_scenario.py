"""Scenarios: generators, validation with clear errors, and the JSON file format."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fiberplan.errors import InstrumentError, ScenarioError
from fiberplan.generate import SCENARIO_KINDS, make_scenario
from fiberplan.geometry import default_safety_margin_mm, min_pair_clearance
from fiberplan.scenario import load_scenario, scenario_from_dict


@pytest.mark.parametrize("instrument", ["desi", "moons-capsules", "sdss"])
@pytest.mark.parametrize("kind", SCENARIO_KINDS)
def test_generated_scenarios_are_valid_and_collision_free(instrument, kind):
    sc = make_scenario(instrument, 61, kind, 7)
    inst = sc.instrument
    for joints in (sc.start, sc.target):
        assert inst.within_limits(joints).all()
        assert min_pair_clearance(inst, sc.base_xy, sc.orient, joints, sc.pairs).min() >= 0.0
    if kind == "unfold":
        np.testing.assert_allclose(sc.start, np.broadcast_to(inst.datum_rad, sc.start.shape))
    if kind == "fold":
        np.testing.assert_allclose(sc.target, np.broadcast_to(inst.datum_rad, sc.target.shape))


def test_same_seed_same_scenario_other_seed_other():
    a, b, c = (make_scenario("moons-capsules", 19, "random", s) for s in (4, 4, 5))
    assert np.array_equal(a.start_deg, b.start_deg) and np.array_equal(a.target_values, b.target_values)
    assert not np.array_equal(a.target_values, c.target_values)


@pytest.mark.parametrize("kind", ["random", "fold", "clustered"])
def test_drawn_starts_keep_the_safety_margin_and_only_close_starts_change(kind):
    # DESI 500 seed 7 drew positioners 257 and 297 0.003 mm apart before the minimum existed;
    # seed 1 had no pair closer than the margin and is unchanged, start and target.
    margin = default_safety_margin_mm(make_scenario("desi", 7, kind, 0).instrument)
    for seed, changes in ((7, True), (1, False)):
        old = make_scenario("desi", 500, kind, seed, min_start_clearance_mm=0.0)
        new = make_scenario("desi", 500, kind, seed)
        closest = min_pair_clearance(new.instrument, new.base_xy, new.orient, new.start, new.pairs).min()
        assert closest >= margin
        assert np.array_equal(old.target_values, new.target_values)  # the target is drawn from the untouched stream
        moved = np.flatnonzero(np.any(old.start_deg != new.start_deg, axis=1))
        if kind == "random":
            assert (len(moved) > 0) == changes and len(moved) <= 3


def test_a_minimum_start_clearance_that_cannot_hold_is_refused():
    with pytest.raises(ScenarioError, match="datum start"):
        make_scenario("desi", 19, "unfold", 0, min_start_clearance_mm=50.0)
    for bad in (-0.1, float("nan"), "0.1", True):
        with pytest.raises(ScenarioError, match="min_start_clearance_mm"):
            make_scenario("desi", 19, "random", 0, min_start_clearance_mm=bad)
    with pytest.raises(ScenarioError, match="lower min_start_clearance_mm"):
        make_scenario("desi", 7, "random", 0, min_start_clearance_mm=15.0)  # farther than neighbouring bases allow
    assert make_scenario("desi", 19, "unfold", 0, min_start_clearance_mm=0.01).n_positioners == 19


def test_generator_does_not_touch_global_random_state():
    np.random.seed(0)
    before = np.random.get_state()[1].copy()
    make_scenario("desi", 19, "clustered", 2)
    assert np.array_equal(np.random.get_state()[1], before)


def test_clustered_targets_are_closer_together_than_random():
    def mean_nn(sc):
        from scipy.spatial import cKDTree

        d, _ = cKDTree(sc.target_xy).query(sc.target_xy, k=2)
        return d[:, 1].mean()

    random = np.mean([mean_nn(make_scenario("desi", 500, "random", s)) for s in range(3)])
    clustered = np.mean([mean_nn(make_scenario("desi", 500, "clustered", s)) for s in range(3)])
    assert clustered < random


def test_random_targets_fill_the_patrol_disc_uniformly():
    sc = make_scenario("desi", 5000, "unfold", 1)
    r = np.linalg.norm(sc.target_xy - sc.base_xy, axis=1) / sc.instrument.reach_max_mm
    # area-uniform: P(r < 1/sqrt(2)) = 1/2 (collision rejection biases this only slightly)
    assert abs(np.mean(r < 1 / np.sqrt(2)) - 0.5) < 0.05


@pytest.mark.parametrize("instrument", ["desi", "moons-capsules"])
def test_file_round_trip_is_exact(tmp_path, instrument):
    sc = make_scenario(instrument, 37, "random", 11)
    path = sc.save(tmp_path / "s.json")
    back = load_scenario(path)
    for attr in ("ids", "base_xy", "orient_deg", "start_deg", "target_kind", "target_values", "target_parity"):
        assert np.array_equal(getattr(sc, attr), getattr(back, attr)), attr
    assert np.array_equal(sc.start, back.start) and np.array_equal(sc.target, back.target)
    assert back.instrument == sc.instrument
    path2 = back.save(tmp_path / "s2.json")
    assert path.read_text() == path2.read_text()


def test_custom_instrument_round_trips(tmp_path):
    sc = make_scenario("sdss", 7, "fold", 1)
    data = sc.to_dict()
    data["instrument"] = sc.instrument.to_dict()
    data["instrument"]["name"] = "my-sdss"
    path = tmp_path / "custom.json"
    path.write_text(json.dumps(data))
    back = load_scenario(path)
    assert back.instrument.name == "my-sdss" and back.instrument_preset is None
    assert load_scenario(back.save(tmp_path / "again.json")).instrument == back.instrument


def test_xy_target_takes_the_faster_parity():
    sc = make_scenario("moons-capsules", 1, "random", 2)
    data = sc.to_dict()
    xy = sc.target_xy[0]
    data["positioners"][0]["target"] = {"x_mm": float(xy[0]), "y_mm": float(xy[1])}
    back = scenario_from_dict(data)
    from fiberplan.kinematics import inverse_kinematics, move_times

    both = [inverse_kinematics(sc.instrument, sc.base_xy, sc.orient, xy[None], np.array([p])) for p in (1, -1)]
    fastest = min(float(move_times(sc.instrument, sc.start, q)[0]) for q in both)
    assert float(move_times(back.instrument, back.start, back.target)[0]) == pytest.approx(fastest)
    np.testing.assert_allclose(back.target_xy, sc.target_xy, atol=1e-9)


def test_free_parities_are_untangled_when_the_faster_goals_collide():
    # On MOONS the faster parity of each x/y target, chosen alone, often collides with a
    # neighbour's goal; fiberplan flips free parities until the goal is collision-free.
    sc = make_scenario("moons-capsules", 19, "random", 2)
    data = sc.to_dict()
    for row, xy in zip(data["positioners"], sc.target_xy, strict=True):
        row["target"] = {"x_mm": float(xy[0]), "y_mm": float(xy[1])}
    back = scenario_from_dict(data)
    np.testing.assert_allclose(back.target_xy, sc.target_xy, atol=1e-9)
    assert min_pair_clearance(back.instrument, back.base_xy, back.orient, back.target, back.pairs).min() >= 0


def test_positioner_without_target_holds(scenario_dict):
    scenario_dict["positioners"][2]["target"] = None
    sc = scenario_from_dict(scenario_dict)
    assert not sc.has_target[2]
    np.testing.assert_array_equal(sc.target[2], sc.start[2])


# ---------------------------------------------------------------- bad input, each named


def test_unknown_preset(scenario_dict):
    scenario_dict["instrument"] = "hectospec"
    with pytest.raises(ScenarioError, match="unknown instrument preset 'hectospec'"):
        scenario_from_dict(scenario_dict)
    with pytest.raises(InstrumentError, match="unknown instrument preset"):
        make_scenario("hectospec", 7)


def test_truncated_file(tmp_path, scenario_dict):
    text = json.dumps(scenario_dict)
    path = tmp_path / "cut.json"
    path.write_text(text[: len(text) // 2])
    with pytest.raises(ScenarioError, match="not valid JSON.*truncated"):
        load_scenario(path)


def test_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match="does not exist"):
        load_scenario(tmp_path / "nope.json")


def test_missing_key_names_positioner(scenario_dict):
    del scenario_dict["positioners"][2]["start_deg"]
    with pytest.raises(ScenarioError, match="positioner 12: missing key 'start_deg'"):
        scenario_from_dict(scenario_dict)


def test_wrong_type_names_positioner(scenario_dict):
    scenario_dict["positioners"][3]["x_mm"] = "ten"
    with pytest.raises(ScenarioError, match="positioner 13: expected a number"):
        scenario_from_dict(scenario_dict)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_start_names_positioner(scenario_dict, value):
    scenario_dict["positioners"][2]["start_deg"][1] = value
    with pytest.raises(ScenarioError, match="positioner 12: start_deg holds a non-finite value"):
        scenario_from_dict(scenario_dict)


def test_nan_in_file_text(tmp_path, scenario_dict):
    text = json.dumps(scenario_dict).replace('"orient_deg": 0.0', '"orient_deg": NaN', 1)
    path = tmp_path / "nan.json"
    path.write_text(text)
    with pytest.raises(ScenarioError, match="positioner 10: orient_deg holds a non-finite value"):
        load_scenario(path)


def _infeasible(scenario):
    return {int(scenario.ids[k]): why for k, why in scenario.infeasible.items()}


def test_target_outside_patrol_disc_is_infeasible_not_an_error(scenario_dict):
    row = scenario_dict["positioners"][2]
    row["target"] = {"x_mm": row["x_mm"] + 6.5, "y_mm": row["y_mm"]}
    sc = scenario_from_dict(scenario_dict)
    assert list(_infeasible(sc)) == [12]
    assert "outside the patrol region [0.0000, 6.0000] mm" in _infeasible(sc)[12]
    assert not sc.has_target[2] and np.array_equal(sc.target[2], sc.start[2])
    assert sc.has_target.sum() == 6  # everyone else is planned


def test_target_unreachable_with_parity_is_infeasible(scenario_dict):
    row = scenario_dict["positioners"][2]
    row["target"] = {"x_mm": row["x_mm"] + 2.0, "y_mm": row["y_mm"] + 1.0, "parity": -1}
    assert "cannot be reached with parity -1" in _infeasible(scenario_from_dict(scenario_dict))[12]


def test_bad_parity_value(scenario_dict):
    row = scenario_dict["positioners"][2]
    row["target"] = {"x_mm": row["x_mm"] + 2.0, "y_mm": row["y_mm"], "parity": 2}
    with pytest.raises(ScenarioError, match="positioner 12: parity must be 1, -1 or 0"):
        scenario_from_dict(scenario_dict)


def test_start_beyond_hard_stop(scenario_dict):
    scenario_dict["positioners"][4]["start_deg"] = [0.0, 190.0]
    stops = r"\(alpha in \[-180, 180\], beta in \[0, 180\] deg\)"
    with pytest.raises(ScenarioError, match=r"positioner 14: start joints \[0, 190\] deg are beyond a hard stop " + stops):
        scenario_from_dict(scenario_dict)


def test_target_joints_beyond_hard_stop_is_infeasible(scenario_dict):
    scenario_dict["positioners"][4]["target"] = {"alpha_deg": 200.0, "beta_deg": 90.0}
    assert "beyond a hard stop" in _infeasible(scenario_from_dict(scenario_dict))[14]


def test_colliding_start(scenario_dict):
    # centre positioner 10 at (0, 0) reaches 6 mm to +x; positioner at (10.4, 0) reaches 6 mm to -x
    rows = {(round(r["x_mm"], 3), round(r["y_mm"], 3)): r for r in scenario_dict["positioners"]}
    centre, right = rows[(0.0, 0.0)], rows[(10.4, 0.0)]
    centre["start_deg"] = [0.0, 0.0]
    right["start_deg"] = [180.0, 0.0]
    with pytest.raises(ScenarioError, match=rf"positioners {centre['id']} and {right['id']} collide in the start configuration"):
        scenario_from_dict(scenario_dict)


def test_colliding_targets_are_an_infeasible_pair_naming_each_other(scenario_dict):
    rows = {(round(r["x_mm"], 3), round(r["y_mm"], 3)): r for r in scenario_dict["positioners"]}
    a, b = rows[(0.0, 0.0)], rows[(10.4, 0.0)]
    a["target"] = {"x_mm": 5.0, "y_mm": 0.0}
    b["target"] = {"x_mm": 5.5, "y_mm": 0.0}
    why = _infeasible(scenario_from_dict(scenario_dict))
    assert f"collides with positioner {b['id']}'s target" in why[a["id"]]
    assert f"collides with positioner {a['id']}'s target" in why[b["id"]]


def test_duplicate_ids(scenario_dict):
    scenario_dict["positioners"][3]["id"] = 12
    with pytest.raises(ScenarioError, match="id 12 appears 2 times"):
        scenario_from_dict(scenario_dict)


def test_wrong_format_marker(scenario_dict):
    scenario_dict["format"] = "something-else"
    with pytest.raises(ScenarioError, match="'format' must be 'fiberplan-scenario'"):
        scenario_from_dict(scenario_dict)


def test_unknown_kind():
    with pytest.raises(ScenarioError, match="unknown scenario kind 'spiral'"):
        make_scenario("desi", 7, "spiral", 0)


def _moons_file(version: int, start_beta: float, **extra):
    return {"format": "fiberplan-scenario", "version": version, "instrument": "moons", **extra, "positioners": [
        {"id": 0, "x_mm": 0.0, "y_mm": 0.0, "start_deg": [0.0, start_beta], "target": {"alpha_deg": 10.0, "beta_deg": 20.0}},
        {"id": 1, "x_mm": 25.0, "y_mm": 0.0, "start_deg": [0.0, start_beta], "target": {"x_mm": 36.0, "y_mm": 5.0, "parity": "L"}}]}


def test_scenario_angles_default_to_the_instruments_convention():
    # MOONS measures beta from the folded arm: its datum [0, 0] is the folded arm, not stretched out.
    sc = scenario_from_dict(_moons_file(2, 0.0))
    assert sc.angle_convention == "folded"
    assert sc.start_deg.tolist() == [[0.0, 180.0], [0.0, 180.0]]
    assert sc.target_values[0].tolist() == [10.0, 200.0] and sc.target_parity[1] == -1  # "L"
    # Stated explicitly, the file's own convention wins; a version 1 file (before the key) is extended.
    assert scenario_from_dict(_moons_file(2, 180.0, beta_convention="extended")).start_deg[0, 1] == 180.0
    assert scenario_from_dict(_moons_file(1, 180.0)).start_deg[0, 1] == 180.0
    with pytest.raises(ScenarioError, match="'beta_convention' must be 'extended' or 'folded'"):
        scenario_from_dict(_moons_file(2, 0.0, beta_convention="bent"))


def test_angle_messages_use_the_files_convention_rounded():
    with pytest.raises(ScenarioError) as info:
        scenario_from_dict(_moons_file(2, 160.0))
    text = str(info.value)
    # The user wrote 160 from the folded arm; the stop is 150 from the folded arm (330 extended).
    assert "start joints [0, 160] deg (beta from the folded arm)" in text and "beta in [-180, 150] deg" in text
    assert "330.0000" not in text
    data = _moons_file(2, 0.0)
    data["positioners"][1]["target"]["parity"] = "X"
    with pytest.raises(ScenarioError, match="parity must be 1 or 'R', -1 or 'L'"):
        scenario_from_dict(data)


def test_scenario_files_state_their_convention_and_round_trip_bit_identical(tmp_path):
    sc = scenario_from_dict(_moons_file(2, 0.0))
    data = sc.to_dict()
    assert data["version"] == 2 and data["beta_convention"] == "extended"
    again = load_scenario(sc.save(tmp_path / "s.json"))
    np.testing.assert_array_equal(again.start_deg, sc.start_deg)
    np.testing.assert_array_equal(again.target_values, sc.target_values)


def test_priorities_and_conventions_are_checked_in_python_too():
    sc = make_scenario("desi", 7, "random", 0)
    from fiberplan.scenario import _replace

    with pytest.raises(ScenarioError, match="target priority must be 1, 2"):
        _replace(sc, target_priority=np.full(7, -1))
    with pytest.raises(ScenarioError, match="angle_convention must be 'extended' or 'folded'"):
        _replace(sc, angle_convention="bent")
