"""The validation set flown as a mission (benchmarks/jsbsim_missions.py): a 60 s piece
of one aircraft's mission, one leg with elevator inputs and one turn, flown by the
simple autopilot in wind and light turbulence and written in the autopilots' formats;
read back with pymavlink (DFReader, mavlogdump.py as a process, the tlog reader), pyulog
and the estimator's own log reader."""

from __future__ import annotations

import csv
import io
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import DFReader, mavutil
from pyulog import ULog

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))  # the benchmarks import each other top-level

import jsbsim_missions as jm  # noqa: E402  (benchmarks/jsbsim_missions.py)
from jsbsim_flights import NOISE, RATE_HZ  # noqa: E402
from validation_flights import member  # noqa: E402

from gcs_estimator.config import load_config, load_truths  # noqa: E402
from gcs_estimator.ingest.logs.reader import load_content  # noqa: E402
from sim.formats import truth_path  # noqa: E402

MODEL = "c182"
FIRST_TURN = 1
"""The plan's first turn follows its first (excited) leg."""


@pytest.fixture(scope="module")
def flight() -> jm.Flight:
    return jm.fly(MODEL, "windy", 1, duration_s=60.0)


@pytest.fixture(scope="module")
def written(flight: jm.Flight, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("missions")
    jm.write_flight(flight, out)
    return out


def _turning(flight: jm.Flight) -> np.ndarray:
    return np.asarray(flight.values["phase"] == FIRST_TURN, dtype=bool)


def _noise_bound(sigma: float) -> float:
    """Five sigma of a sensor's noise: what a written value may differ from the flown one."""
    return 5.0 * sigma


def test_the_turn_reaches_the_commanded_bank(flight: jm.Flight) -> None:
    turn = jm.PLAN[FIRST_TURN]
    assert turn.kind == "turn" and 20.0 <= turn.bank_deg <= 35.0
    turning = _turning(flight)
    assert turning.any(), "the 60 s flight reaches its first turn"
    bank = np.degrees(np.abs(flight.values["phi"][turning]))
    # Held at the commanded bank (within 3 deg) for a stretch of the turn, never far beyond.
    held = np.abs(bank - turn.bank_deg) < 3.0
    assert held.sum() / RATE_HZ >= 3.0
    assert bank.max() < turn.bank_deg + 5.0
    heading = flight.values["psi"]
    start, end = np.flatnonzero(turning)[[0, -1]]
    turned = math.degrees(jm._wrap(heading[end] - heading[start]))
    assert abs(turned - turn.value) < 10.0


def test_the_turn_is_coordinated(flight: jm.Flight) -> None:
    beta = np.degrees(flight.values["beta"][_turning(flight)])
    assert np.sqrt(np.mean(beta**2)) < 1.5
    assert np.abs(beta).max() < 4.0


def test_the_first_leg_carries_the_elevator_inputs_on_top_of_the_autopilot(
    flight: jm.Flight,
) -> None:
    v = flight.values
    leg = v["phase"] == 0
    exc = v["excitation"][leg]
    amplitude = math.radians(member(MODEL).aircraft.amplitude_deg)
    assert np.isclose(np.abs(exc).max(), amplitude)
    assert not v["excitation"][_turning(flight)].any()


def test_dataflash_log_carries_the_turn_wind_and_throttle(flight: jm.Flight, written: Path) -> None:
    name = jm.record_name(MODEL, "windy", 1)
    log = DFReader.DFReader_binary(str(written / f"{name}.bin"))
    rows: dict[str, list[Any]] = {}
    while (m := log.recv_msg()) is not None:
        rows.setdefault(m.get_type(), []).append(m)
    v = flight.values
    att = rows["ATT"]
    roll = np.radians([m.Roll for m in att])
    flown = np.interp([m.TimeUS for m in att], _time_us(flight), v["phi"])
    assert np.abs(roll - flown).max() < _noise_bound(NOISE[2]) + math.radians(0.01)
    imu = rows["IMU"]
    assert np.abs(np.array([m.GyrZ for m in imu]) - v["r"]).max() < _noise_bound(NOISE[3])
    wn, we = jm.wind("windy", 1)
    xkf2 = rows["XKF2"]
    assert {round(m.VWN, 2) for m in xkf2} == {round(wn, 2)}
    assert {round(m.VWE, 2) for m in xkf2} == {round(we, 2)}
    params = {m.Name: m.Value for m in rows["PARM"]}
    assert params["SERVO2_FUNCTION"] == 19 and params["SERVO3_FUNCTION"] == 70
    rcou = rows["RCOU"]
    throttle = (np.array([m.C3 for m in rcou]) - 1000.0) / 1000.0
    at = np.interp([m.TimeUS for m in rcou], _time_us(flight), v["throttle"])
    assert np.abs(throttle - at).max() <= 0.001


def _time_us(flight: jm.Flight) -> np.ndarray:
    """The logs' clock (microseconds since boot) at each flown sample."""
    t = flight.values["t"]
    return np.asarray((t - t[0] + 5.0) * 1e6, dtype=float)


def test_mavlogdump_reads_the_dataflash_log(written: Path) -> None:
    path = written / f"{jm.record_name(MODEL, 'windy', 1)}.bin"
    tool = Path(sys.executable).parent / "mavlogdump.py"
    done = subprocess.run(
        [sys.executable, str(tool), "--types", "ATT", "--format", "csv", str(path)],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    rows = list(csv.DictReader(io.StringIO(done.stdout)))
    banks = np.abs([float(r["Roll"]) for r in rows])
    assert len(rows) > 0 and banks.max() > 20.0


@pytest.mark.parametrize("kind", ["asked", "default"])
def test_tlogs_carry_attitude_rates_climb_and_wind(
    flight: jm.Flight, written: Path, kind: str
) -> None:
    path = written / f"{jm.record_name(MODEL, 'windy', 1)}_{kind}.tlog"
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    msgs: dict[str, list[Any]] = {}
    while (m := conn.recv_match()) is not None:
        msgs.setdefault(m.get_type(), []).append(m)
    att = msgs["ATTITUDE"]
    seconds = flight.values["t"][-1]
    rate = len(att) / seconds
    assert rate > 20.0 if kind == "asked" else 3.0 < rate < 5.0
    assert max(abs(m.roll) for m in att) > math.radians(20.0)
    assert max(abs(m.yawspeed) for m in att) > 0.05
    wind = msgs["WIND"]
    wn, we = jm.wind("windy", 1)
    assert all(abs(m.speed - math.hypot(wn, we)) < 1e-3 for m in wind)
    climb = np.array([m.climb for m in msgs["VFR_HUD"]])
    assert np.all(np.isfinite(climb)) and np.ptp(climb) > 0.5
    params = {m.param_id: m.param_value for m in msgs["PARAM_VALUE"]}
    assert params["SERVO2_FUNCTION"] == 19 and params["SERVO2_REVERSED"] == 1
    config = load_config(written / f"{jm.record_name(MODEL, 'windy', 1)}.toml")
    # The airframe file's [truth] has 6 digits, the truth file's every digit.
    truth = load_truths(truth_path(path), config.coefficient_names)[1]
    assert config.truth is not None
    np.testing.assert_allclose(np.array(truth), np.array(config.truth), rtol=1e-5)


def test_ulog_carries_the_turn_and_wind(flight: jm.Flight, written: Path) -> None:
    log = ULog(str(written / f"{jm.record_name(MODEL, 'windy', 1)}.ulg"))
    data = {d.name: d.data for d in log.data_list}
    q = [data["vehicle_attitude"][f"q[{i}]"] for i in range(4)]
    phi = np.arctan2(2 * (q[0] * q[1] + q[2] * q[3]), 1 - 2 * (q[1] ** 2 + q[2] ** 2))
    assert np.degrees(np.abs(phi)).max() > 20.0
    wn, _ = jm.wind("windy", 1)
    assert np.allclose(data["wind"]["windspeed_north"], wn, atol=1e-5)
    assert np.ptp(data["vehicle_local_position"]["vz"]) > 0.5


@pytest.mark.parametrize("suffix", [".bin", ".ulg"])
def test_the_estimators_log_reader_finds_bank_rates_climb_and_wind(
    written: Path, suffix: str
) -> None:
    content = load_content(written / f"{jm.record_name(MODEL, 'windy', 1)}{suffix}")
    assert content.fixed_wing and "unknown" not in content.vehicle
    for channel in ("phi", "p", "r", "vz", "wind_n", "wind_e", "throttle", "elevator"):
        assert channel in content.signals, channel
    assert np.degrees(np.abs(content.signals["phi"].values)).max() > 20.0


def test_the_airframe_file_has_the_lateral_inertia_and_the_spec_sheet_only(
    flight: jm.Flight, written: Path
) -> None:
    path = written / f"{jm.record_name(MODEL, 'windy', 1)}.toml"
    text = path.read_text(encoding="utf-8")
    spec = jm.SPECS[MODEL]
    # Keys where the configuration has them, commented out where not yet.
    for key, value in (
        ("inertia_xx_kgm2", np.mean(flight.values["ixx"])),
        ("inertia_xz_kgm2", np.mean(flight.values["ixz"])),
        ("prop_diameter_m", spec.diameter_m),
        ("max_power_w", spec.power_w),
    ):
        found = re.search(rf"^(?:# )?{key} = (\S+)$", text, re.MULTILINE)
        assert found is not None, key
        assert math.isclose(float(found.group(1)), value, rel_tol=1e-5, abs_tol=1e-9), key
    config = load_config(path)
    assert config.propulsion.model == "propeller" and config.propulsion.input_name == "throttle"
    assert "prop_coefficient" not in text or "prop_coefficient = 1.0 " in text
    assert "[filter]" not in text and "vane" not in text
    assert config.airframe.elevator_travel_deg > 0


def test_the_clean_signals_are_the_flights_own(flight: jm.Flight, written: Path) -> None:
    """NAME.clean.npz (the best fit's signals): the flown values without noise, the climb
    rate the motion over the ground's."""
    clean = np.load(written / f"{jm.record_name(MODEL, 'windy', 1)}.clean.npz")
    assert set(clean.files) == set(jm.CLEAN_KEYS)
    for key in ("t", "de", "thrust", "phi", "V", "alpha", "a_z", "gust_q"):
        np.testing.assert_array_equal(clean[key], flight.values[key], err_msg=key)
    np.testing.assert_array_equal(clean["h_dot"], -flight.values["v_down"])
