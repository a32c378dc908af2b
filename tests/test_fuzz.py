"""Fuzzing the inputs a user writes: scenario files, instrument files, study files, command lines.

Every case must end with exit status 0, 1 or 2 from ``fiberplan.cli.main`` (never an internal
error, never an exception escaping), and an output file that existed before is either left
untouched or replaced by a complete, readable one. The default run keeps each target small
(well under a minute in all); ``pytest -m slow tests/test_fuzz.py`` runs ten times more cases.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fiberplan as fp
from fiberplan.cli import main

SMALL = settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
LARGE = settings(max_examples=3000, deadline=None, suppress_health_check=list(HealthCheck))

ODD_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**80), max_value=2**80),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0, -1, 1e300, -1e-300, 1e6, 0.5, 7, 2**63]),
    st.text(max_size=8), st.lists(st.integers(-3, 3), max_size=3), st.just({}), st.just({"x_mm": 1.0}),
)
KEYS = st.sampled_from([
    "id", "x_mm", "y_mm", "orient_deg", "start_deg", "target", "alpha_deg", "beta_deg", "parity", "targett", "meta", "seed",
    "name", "kind", "instrument", "positioners", "format", "version", "pitch_mm", "radius_mm", "layer", "arm", "start_mm",
    "end_mm", "datum_deg", "beta_convention", "beta_convension", "planner_defaults", "dt_s", "mpc", "grid", "seeds", "planner",
    "n_positioners", "scenario_kind", "settings", "study", "out", "per_positioner", "retries", "no_worker_timeout_s",
])


def _paths(tree: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path to a dict key or list index inside ``tree``."""
    out = [prefix]
    if isinstance(tree, dict):
        for key, value in tree.items():
            out += _paths(value, (*prefix, key))
    elif isinstance(tree, list):
        for k, value in enumerate(tree):
            out += _paths(value, (*prefix, k))
    return out


def _get(tree: Any, path: tuple) -> Any:
    for key in path:
        tree = tree[key]
    return tree


@st.composite
def mutated(draw, base: Any, n_edits: int = 3) -> Any:
    """``base`` with a few edits: values replaced by odd ones, keys removed, added or misspelled."""
    tree = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, n_edits))):
        paths = _paths(tree)
        path = draw(st.sampled_from(paths))
        action = draw(st.sampled_from(["replace", "delete", "add", "rename"]))
        if not path:
            continue
        parent = _get(tree, path[:-1])
        key = path[-1]
        if action == "replace":
            parent[key] = copy.deepcopy(draw(ODD_VALUES))
        elif action == "delete":
            if isinstance(parent, dict):
                del parent[key]
            elif len(parent) > 1:
                parent.pop(key)
        elif action == "add" and isinstance(parent, dict):
            parent[draw(KEYS)] = copy.deepcopy(draw(ODD_VALUES))
        elif action == "rename" and isinstance(parent, dict):
            parent[str(key) + draw(st.sampled_from(["t", "s", "_", "x"]))] = parent.pop(key)
    return tree


def run_cli(argv: list[str]) -> int:
    """``main(argv)`` in this process; its exit status (0 when it returns)."""
    try:
        main(argv)
    except SystemExit as e:
        return int(e.code or 0)
    return 0


def assert_output_intact(path: Path, before: bytes) -> None:
    """The output is untouched, or a complete fiberplan file."""
    assert path.exists()
    if path.read_bytes() != before:
        fp.trajectory.read_run(path)  # raises if partial or foreign
    assert not [p for p in path.parent.iterdir() if p.name.startswith(f".{path.name}.")], "a temporary file was left"


BASE_SCENARIO = fp.make_scenario("desi", 7, "random", 5).to_dict()
BASE_INSTRUMENT = fp.load_instrument("desi").to_dict()
BASE_STUDY = {
    "study": {"name": "fuzz", "out": "fuzz.parquet"},
    "grid": {"instrument": ["desi"], "n_positioners": [3], "scenario_kind": ["random"], "planner": ["straight"], "seeds": 1},
    "settings": {"straight": {"dt_s": [0.02]}},
}


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, allow_nan=True))


def _scenario_case(tmp_path: Path, data: Any) -> None:
    scen = tmp_path / "s.json"
    _write_json(scen, data)
    out = tmp_path / "out.h5"
    out.write_bytes(b"previous content")
    before = out.read_bytes()
    code = run_cli(["plan", "--scenario", str(scen), "--planner", "straight", "-q", "--out", str(out)])
    assert code in (0, 1, 2)
    assert_output_intact(out, before)
    if code == 0:
        assert out.read_bytes() != before


def _instrument_case(tmp_path: Path, data: Any) -> None:
    path = tmp_path / "inst.toml"
    try:
        text = tomli_w.dumps(data)
    except (TypeError, ValueError):  # not representable in TOML (None, NaN keys...): nothing to test
        return
    path.write_text(text)
    assert run_cli(["plan", "--instrument", str(path), "-n", "3", "--planner", "straight", "-q", "--no-verify"]) in (0, 1, 2)
    assert run_cli(["instruments", str(path)]) in (0, 2)


def _study_case(tmp_path: Path, data: Any) -> None:
    path = tmp_path / "study.toml"
    try:
        path.write_text(tomli_w.dumps(data))
    except (TypeError, ValueError):
        return
    from fiberplan.studies import StudyError, load_study

    try:
        spec = load_study(path)
    except StudyError:
        assert run_cli(["sweep", str(path), "-q"]) == 2
        return
    if len(spec.tasks) <= 2 and all(t.n_positioners <= 19 for t in spec.tasks):
        assert run_cli(["sweep", str(path), "-q", "--workers", "1"]) in (0, 2)


def _non_finite(value: Any) -> bool:
    return isinstance(value, float) and not math.isfinite(value)


@SMALL
@given(data=mutated(BASE_SCENARIO))
def test_fuzz_scenario_files(tmp_path_factory, data):
    _scenario_case(tmp_path_factory.mktemp("scen"), data)


@SMALL
@given(data=mutated(BASE_INSTRUMENT))
def test_fuzz_instrument_files(tmp_path_factory, data):
    _instrument_case(tmp_path_factory.mktemp("inst"), data)


@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(data=mutated(BASE_STUDY, n_edits=2))
def test_fuzz_study_files(tmp_path_factory, data):
    _study_case(tmp_path_factory.mktemp("study"), data)


COMMANDS = st.sampled_from(["plan", "verify", "show", "animate", "scenario", "instruments", "planners", "sweep", "study-plot", "compare"])
OPTIONS = st.sampled_from([
    "--instrument", "-n", "--positioners", "--radius-mm", "--scenario-kind", "--kind", "--seed", "--seeds", "--planner", "--planners",
    "--set", "--out", "--picture", "--json", "--fps", "--frames", "--time", "--settings", "--scenario", "--quiet", "--strict",
    "--max-events", "--x", "--rate", "--seed-list", "--workers", "--bogus",
])
VALUES = st.one_of(
    st.sampled_from(["desi", "moons-capsules", "sdss", "nosuch", "straight", "dnf", "warp", "0", "-1", "7", "1e6", "nan", "inf", "-3",
                     "99999999999999999999999", "x.h5", "x.xyz", "/dev/null", "dt_s=0.02", "dt_s=-1", "horizon_steps=1e9",
                     "bogus=1", "random", "fold", "hard", "3,2", "a,b", ""]),
    st.text(max_size=6),
)


@SMALL
@given(command=COMMANDS, rest=st.lists(st.one_of(OPTIONS, VALUES), max_size=6))
def test_fuzz_command_lines(tmp_path_factory, command, rest):
    folder = tmp_path_factory.mktemp("cli")
    argv = [command, *[a.replace("x.h5", str(folder / "x.h5")).replace("x.xyz", str(folder / "x.xyz")) for a in rest]]
    if command in ("plan", "compare") and not any(a in ("-n", "--positioners") for a in rest):
        argv += ["-n", "3"]  # keep the default-size runs small
    if command == "compare":
        argv += ["--planners", "straight", "--seeds", "1", "--out", str(folder / "c.parquet")]
    if "--planner" not in rest and command == "plan":
        argv += ["--planner", "straight"]
    assert run_cli(argv) in (0, 1, 2)


@pytest.mark.slow
@LARGE
@given(data=mutated(BASE_SCENARIO, n_edits=5))
def test_fuzz_scenario_files_large(tmp_path_factory, data):
    _scenario_case(tmp_path_factory.mktemp("scen"), data)


@pytest.mark.slow
@LARGE
@given(data=mutated(BASE_INSTRUMENT, n_edits=5))
def test_fuzz_instrument_files_large(tmp_path_factory, data):
    _instrument_case(tmp_path_factory.mktemp("inst"), data)


@pytest.mark.slow
@settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=mutated(BASE_STUDY, n_edits=3))
def test_fuzz_study_files_large(tmp_path_factory, data):
    _study_case(tmp_path_factory.mktemp("study"), data)


@pytest.mark.slow
@LARGE
@given(command=COMMANDS, rest=st.lists(st.one_of(OPTIONS, VALUES), max_size=8))
def test_fuzz_command_lines_large(tmp_path_factory, command, rest):
    test_fuzz_command_lines.hypothesis.inner_test(tmp_path_factory, command, rest)
