"""Instrument presets and files."""

from __future__ import annotations

import math

import pytest

from fiberplan.errors import InstrumentError
from fiberplan.instrument_io import load_instrument, preset_names

NUMBERED_KEYS = (
    "pitch_mm", "alpha_arm_mm", "beta_arm_mm", "alpha_speed_rpm", "beta_speed_rpm",
    "alpha_limits_deg", "beta_limits_deg", "datum_deg", "tolerance_mm", "capsules",
)


def test_presets_are_shipped():
    assert set(preset_names()) >= {"desi", "moons-capsules", "sdss"}


@pytest.mark.parametrize("name", ["desi", "moons-capsules", "sdss"])
def test_every_number_has_a_source(name):
    inst = load_instrument(name)
    missing = [key for key in NUMBERED_KEYS if not inst.sources.get(key)]
    assert not missing, f"{name}: no source for {missing}"


def test_desi_numbers_match_reference_000():
    inst = load_instrument("desi")
    assert inst.alpha_arm_mm == 3.0 and inst.beta_arm_mm == 3.0
    assert inst.alpha_speed_rad_s == pytest.approx(30 * 2 * math.pi / 60)
    assert inst.beta_speed_rad_s == pytest.approx(20 * 2 * math.pi / 60)
    assert inst.tolerance_mm == 0.1
    assert inst.capsules[0].radius_mm * 2 == 2.0  # fiber ends >= d = 2 mm apart
    assert inst.reach_max_mm == pytest.approx(6.0)
    assert inst.control_dt_s == 0.01


def test_moons_folded_convention_is_converted():
    inst = load_instrument("moons-capsules")
    assert math.degrees(inst.beta_limits_rad[0]) == pytest.approx(0.0)
    assert math.degrees(inst.beta_limits_rad[1]) == pytest.approx(330.0)
    assert math.degrees(inst.datum_rad[1]) == pytest.approx(180.0)
    # a half turn of alpha takes about 11 s
    assert math.pi / inst.alpha_speed_rad_s == pytest.approx(10.8, abs=0.2)


def test_unknown_preset_names_the_choices():
    with pytest.raises(InstrumentError, match="unknown instrument preset 'vlt'.*desi"):
        load_instrument("vlt")


def test_user_instrument_file(tmp_path):
    text = (load_instrument("desi").to_dict())
    import tomli_w

    text["name"] = "mine"
    text["geometry"]["pitch_mm"] = 12.0
    path = tmp_path / "mine.toml"
    path.write_text(tomli_w.dumps(text))
    inst = load_instrument(path)
    assert inst.name == "mine" and inst.pitch_mm == 12.0


def test_malformed_instrument_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("name = 'x'\n[geometry\n")
    with pytest.raises(InstrumentError, match="not valid TOML"):
        load_instrument(path)


def test_missing_key_in_instrument_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("name = 'x'\n[geometry]\npitch_mm = 1.0\n")
    with pytest.raises(InstrumentError, match="missing key"):
        load_instrument(path)


def test_negative_speed_rejected(tmp_path):
    import tomli_w

    data = load_instrument("desi").to_dict()
    data["motion"]["beta_speed_rpm"] = -1.0
    path = tmp_path / "neg.toml"
    path.write_text(tomli_w.dumps(data))
    with pytest.raises(InstrumentError, match="beta_speed must be a finite number > 0"):
        load_instrument(path)


def test_an_instrument_hashes_once_as_equality_says_and_not_across_a_pickle():
    """The cached hash (``Instrument.__hash__``) agrees with ``==``: an equal instrument read
    again hashes the same, a changed field changes equality and (here) the hash, and a pickled
    copy carries no cached value (string hashes differ between processes)."""
    import dataclasses
    import pickle

    moons = load_instrument("moons")
    assert hash(moons) == hash(moons) and moons.__dict__["_hash"] == hash(moons)  # computed once, kept
    again = load_instrument("moons")
    assert again == moons and hash(again) == hash(moons)
    copy = pickle.loads(pickle.dumps(moons))
    assert "_hash" not in copy.__dict__ and copy == moons and hash(copy) == hash(moons)
    wider = dataclasses.replace(moons, pitch_mm=moons.pitch_mm + 1.0)
    assert wider != moons and hash(wider) != hash(moons)
    assert {moons: 1}[again] == 1  # usable as a key, as the geometry's caches use it
