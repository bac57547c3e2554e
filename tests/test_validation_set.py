"""The wide validation set (benchmarks/validation_flights.py, benchmarks/validation.py):
its split, its names, the sensors it places as the estimator models them, a glider that
glides."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import jsbsim
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))  # the benchmarks import each other top-level

import jsbsim_flights  # noqa: E402  (benchmarks/jsbsim_flights.py)
import validation  # noqa: E402  (benchmarks/validation.py)
import validation_flights as vf  # noqa: E402  (benchmarks/validation_flights.py)

from gcs_estimator.model import equations as eq  # noqa: E402

HELD_FOR_INDEPENDENT_CHECKS = {"pa28", "c172x", "J3Cub"}


def _records(half: str) -> int:
    """Records per seed in a half: 8 per JSBSim aircraft, 4 NOC flights, 1 HFB-320."""
    jsbsim_records = 8 * sum(m.half == half for m in vf.SET)
    others = [name for name, (_, _, h) in validation.OTHERS.items() if h == half]
    return jsbsim_records + 4 * ("noc" in others) + ("hfb320" in others)


def test_the_set_is_wide_installed_and_leaves_out_the_independent_checks() -> None:
    installed = set(os.listdir(Path(jsbsim.get_default_root_dir()) / "aircraft"))
    models = [m.aircraft.model for m in vf.SET]
    assert len(models) == len(set(models)) >= 8
    assert set(models) <= installed
    assert not set(models) & HELD_FOR_INDEPENDENT_CHECKS
    assert len({m.aircraft.kind for m in vf.SET}) >= 6


def test_the_independent_checks_fly_apart_from_the_set() -> None:
    """The aircraft held for independent checks are flown only when asked for by name
    (--half independent), are installed, and never count in the set's halves or its
    whole (decision 0071)."""
    installed = set(os.listdir(Path(jsbsim.get_default_root_dir()) / "aircraft"))
    independent = {m.aircraft.model for m in vf.INDEPENDENT_SET}
    assert independent == HELD_FOR_INDEPENDENT_CHECKS <= installed
    assert all(m.half == vf.INDEPENDENT for m in vf.INDEPENDENT_SET)
    assert not independent & set(validation.SET)
    assert set(validation.ORDER) == set(validation.SET) | independent
    for model in independent:
        assert vf.member(model).half == vf.INDEPENDENT
    args = argparse.Namespace(half="all", aircraft=[])
    assert validation.chosen(args) == validation.SET
    args = argparse.Namespace(half=vf.INDEPENDENT, aircraft=[])
    assert set(validation.chosen(args)) == independent


def test_the_halves_split_the_records_about_evenly_and_hold_out_several_classes() -> None:
    tuning, held_out = _records(vf.TUNING), _records(vf.HELD_OUT)
    assert tuning + held_out == 8 * len(vf.SET) + 5
    assert abs(tuning - held_out) <= 0.1 * (tuning + held_out)
    held_kinds = {m.aircraft.kind for m in vf.SET if m.half == vf.HELD_OUT}
    assert len(held_kinds) >= 5
    # What the project was tuned on before the set existed is in the tuning half.
    for model in ("c172p", "737"):
        assert vf.member(model).half == vf.TUNING
    assert all(half == vf.TUNING for _, _, half in validation.OTHERS.values())


def test_record_names_read_back() -> None:
    for model in ("SGS", "t6texan2", "737"):
        for seed in (1, 2, 13):
            name = vf.record_name(model, "step", "light", "clean", seed)
            assert vf.parse_name(name) == (model, "step", "light", "clean")


def test_sensors_read_what_the_estimators_observation_equations_expect() -> None:
    rng = np.random.default_rng(3)
    n = 50
    flight = {
        "V": rng.uniform(20.0, 200.0, n),
        "alpha": rng.uniform(-0.1, 0.2, n),
        "theta": rng.uniform(-0.3, 0.3, n),
        "q": rng.uniform(-0.5, 0.5, n),
        "qdot": rng.uniform(-2.0, 2.0, n),
        "a_x": rng.uniform(-3.0, 3.0, n),
        "a_z": rng.uniform(-15.0, -5.0, n),
    }
    where = {"vane_x_m": 4.2, "vane_z_m": -0.8, "accel_x_m": 0.3, "accel_z_m": -0.5}
    read = vf.sensed(flight, where)
    k = np.zeros(eq.SPAN + 1)
    k[eq.VANE_X], k[eq.VANE_Z] = where["vane_x_m"], where["vane_z_m"]
    k[eq.ACCEL_X], k[eq.ACCEL_Z] = where["accel_x_m"], where["accel_z_m"]
    for i in range(n):
        x = np.array([flight[c][i] for c in ("V", "alpha", "theta", "q")])
        h = np.array([flight[c][i] for c in jsbsim_flights.CLEAN])
        eq.sensor_placement(x, k, h, np.zeros((7, 4)))
        h[3] += jsbsim_flights.GYRO_BIAS
        np.testing.assert_allclose(read[i], h, rtol=1e-12, atol=1e-12)


def test_placement_reads_the_models_frame_into_body_axes() -> None:
    """JSBSim's structural frame has x aft and z up; the airframe file's, x ahead, z down."""
    flight = {
        "cg_x": np.array([10.0]),
        "cg_z": np.array([1.0]),
        "eye_x": np.array([4.0]),  # 6 m ahead of the CG
        "eye_z": np.array([1.5]),  # 0.5 m above it
        "aerorp_x": np.array([10.2]),
        "aerorp_z": np.array([0.7]),
    }
    where = vf.placement(flight)
    assert math.isclose(where["vane_x_m"], 6.0) and math.isclose(where["vane_z_m"], -0.5)
    assert math.isclose(where["accel_x_m"], -0.2) and math.isclose(where["accel_z_m"], 0.3)


def test_the_glider_glides_steadily_without_a_throttle_to_trim() -> None:
    sgs = vf.member("SGS").aircraft
    assert not sgs.throttle
    flight = jsbsim_flights.fly(sgs, False, 1, "fcs")
    assert float(np.max(flight["thrust"])) == 0.0
    quiet = flight["t"] < 1.9  # before the first multistep
    assert np.ptp(flight["V"][quiet]) < 0.01 * flight["V"][0]
    assert np.ptp(flight["alpha"][quiet]) < math.radians(0.05)
