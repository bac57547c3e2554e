"""The data compatibility check (ingest/compat.py, decision 0056) on the NOC simulator's
flights: what it finds where a fault was injected, and what it leaves alone where none was."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.config import load_config
from gcs_estimator.ingest.compat import Compatibility, check, noise_sigma, own_noise
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.logs.reader import load_flight
from gcs_estimator.model.channels import LEGACY_OBS
from gcs_estimator.runtime.session import run_recording
from sim.truth import Flight, simulate

THETA, ALPHA, Q = 2, 1, 3
WELL_EXCITED = ("CL0", "CLa", "Cm0", "Cma", "Cmq", "Cmde")


def _flight(sets: list[str], seed: int) -> tuple[Flight, Recording]:
    f = simulate(load_config("noc_uav", sets), seed=seed)
    return f, Recording(f.t_s, f.inputs, f.measurements, "throttle")


def _lagged(rec: Recording, column: int, tau: float) -> Recording:
    """The record with one channel logged tau seconds late."""
    y = rec.measurements.copy()
    y[:, column] = np.interp(rec.t_s - tau, rec.t_s, y[:, column])
    return Recording(rec.t_s, rec.inputs, y, rec.power)


def _finding(c: Compatibility, channel: str, kind: str) -> tuple[float, float, bool]:
    (f,) = [f for f in c.findings if (f.channel, f.kind) == (channel, kind)]
    return f.value, f.sigma, f.significant


@pytest.mark.parametrize("seed", [1, 2])
def test_a_clean_record_shows_nothing_beyond_its_sigma_and_is_left_as_it_is(seed: int) -> None:
    _, rec = _flight([], seed)
    c = check(rec)
    assert {(f.channel, f.kind) for f in c.findings} >= {
        ("q", "bias"),
        ("theta", "shift"),
        ("a_x", "bias"),
        ("a_z", "bias"),
        ("alpha", "shift"),
    }
    loud = [f.line() for f in c.findings if abs(f.z) > 3.0 or f.significant]
    assert not loud, loud
    np.testing.assert_array_equal(c.recording.measurements, rec.measurements)


@pytest.mark.parametrize(
    ("sets", "lag", "channel", "kind", "injected"),
    [
        (["simulation.sensors.bias.q=0.003"], None, "q", "bias", 0.003),
        (["simulation.sensors.bias.a_z=0.3"], None, "a_z", "bias", 0.3),
        (["simulation.sensors.bias.a_x=-0.3"], None, "a_x", "bias", -0.3),
        ([], (THETA, 0.1), "theta", "shift", 0.1),
        ([], (ALPHA, 0.08), "alpha", "shift", 0.08),
    ],
)
def test_an_injected_bias_or_time_shift_is_found_within_its_sigma_and_corrected(
    sets: list[str], lag: tuple[int, float] | None, channel: str, kind: str, injected: float
) -> None:
    _, rec = _flight(sets, seed=3)
    if lag is not None:
        rec = _lagged(rec, *lag)
    c = check(rec)
    value, sigma, significant = _finding(c, channel, kind)
    assert significant, (value, sigma)
    assert abs(value - injected) < 3.0 * sigma, (value, sigma)
    assert sigma < abs(injected) / 10  # resolved, not just allowed for
    again = check(c.recording)  # the corrected record has nothing left to find
    assert not _finding(again, channel, kind)[2], [f.line() for f in again.findings]


def test_estimates_from_the_corrected_record_of_a_biased_flight_are_closer_to_truth() -> None:
    sets = ["simulation.sensors.bias.q=0.003", "simulation.sensors.bias.a_z=0.3"]
    config = load_config("noc_uav", sets)
    flight, rec = _flight(sets, seed=1)
    c = check(rec)
    errors = {}
    for label, r in (("raw", rec), ("corrected", c.recording)):
        res = run_recording(config, r.t_s, r.inputs, r.measurements, keep_history=False).result
        well = [res.names.index(n) for n in WELL_EXCITED]
        rel = (res.filters["IEKF"].coefficients - flight.truth) / flight.truth
        errors[label] = float(np.sqrt(np.mean(rel[well] ** 2)))
    assert errors["corrected"] < errors["raw"], errors


def _with_gps(rec: Recording, flight: Flight, wind: tuple[float, float], psi: float) -> Recording:
    """The simulated flight on a heading psi through a steady wind, with the GPS velocity
    (north, east, down) over the ground that gives, and the heading, in its aux."""
    v, alpha, theta = flight.states[:, 0], flight.states[:, 1], flight.states[:, 2]
    gamma = theta - alpha
    rng = np.random.default_rng(5)
    aux = {
        "vn": v * np.cos(gamma) * math.cos(psi) + wind[0],
        "ve": v * np.cos(gamma) * math.sin(psi) + wind[1],
        "vd": -v * np.sin(gamma),
        "psi": np.full(len(v), psi),
    }
    aux = {
        k: x + (0.1 * rng.standard_normal(len(x)) if k != "psi" else 0.0) for k, x in aux.items()
    }
    return Recording(rec.t_s, rec.inputs, rec.measurements, rec.power, aux=aux)


def test_gps_velocity_gives_the_wind_and_the_angle_of_attack_without_a_vane() -> None:
    flight, rec = _flight([], seed=1)
    rec = _with_gps(rec, flight, wind=(4.0, -3.0), psi=math.radians(60.0))
    no_vane = rec.measurements.copy()
    no_vane[:, ALPHA] = np.nan
    c = check(Recording(rec.t_s, rec.inputs, no_vane, rec.power, aux=rec.aux))
    out = c.recording.aux
    assert abs(float(np.mean(out["wind_n_fpr"])) - 4.0) < 0.3
    assert abs(float(np.mean(out["wind_e_fpr"])) + 3.0) < 0.3
    err = out["alpha_fpr"] - flight.states[:, 1]
    assert float(np.sqrt(np.mean(err**2))) < math.radians(0.5)
    assert not any(f.significant for f in c.findings), [f.line() for f in c.findings]


CSV_COLUMNS = (
    "time_s",
    "airspeed_mps",
    "alpha_rad",
    "theta_rad",
    "q_radps",
    "qdot_radps2",
    "ax_mps2",
    "az_mps2",
    "elevator_rad",
    "throttle",
)


def _csv(path: Path, rec: Recording) -> Path:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for t, y, u in zip(rec.t_s, rec.measurements, rec.inputs, strict=True):
            obs = y[:LEGACY_OBS]  # the layout's seven observed columns (no climb rate)
            w.writerow([f"{t:.3f}", *(f"{x:.7g}" for x in obs), f"{u[0]:.7g}", f"{u[1]:.7g}"])
    return path


@pytest.mark.parametrize("mode", ["correct", "report", "off"])
def test_every_data_file_is_checked_before_estimation_as_the_config_says(
    tmp_path: Path, mode: str
) -> None:
    sets = ["simulation.sensors.bias.q=0.003"]
    _, rec = _flight(sets, seed=1)
    file = _csv(tmp_path / "biased.csv", rec)
    config = load_config("noc_uav", [f'data.compatibility_check="{mode}"'])
    _, got, _ = load_flight(file, config)
    q_raw = np.round(rec.measurements[:, Q], 9)
    if mode == "off":
        assert got.compatibility is None
        assert not any("compatibility" in n for n in got.notes)
        return
    assert got.compatibility is not None and got.compatibility["mode"] == mode
    (q_bias,) = [
        f for f in got.compatibility["findings"] if (f["channel"], f["kind"]) == ("q", "bias")
    ]
    assert q_bias["significant"] and abs(q_bias["value"] - 0.003) < 3 * q_bias["sigma"]
    assert any("WARNING: q bias" in n for n in got.notes)
    moved = float(np.mean(q_raw - got.measurements[:, Q]))
    assert abs(moved - (q_bias["value"] if mode == "correct" else 0.0)) < 1e-6


def test_a_channel_sampled_at_a_fifth_of_the_frames_reads_its_own_noise() -> None:
    """A rate logged at 10 Hz among 50 Hz frames (NaN between): its noise is read from
    its own samples, whatever their spacing, and carried on the grid as the noise whose
    integral spreads as the channel's own does (sqrt(5) times, on every fifth frame); the
    signal filled between samples (as the check fills it) would have read about a third."""
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 300.0, 0.02)
    sigma = 0.01
    slow = np.full(t.shape, np.nan)
    own = np.arange(0, t.size, 5)
    jitter = t[own] + rng.uniform(-0.004, 0.004, own.size)  # a log's timestamps jitter
    slow[own] = 0.2 * np.sin(0.5 * jitter) + sigma * rng.standard_normal(own.size)
    grid = np.where(np.isfinite(slow), t, np.nan)
    grid[own] = jitter
    sd, spacing = own_noise(grid, slow)
    assert abs(sd / sigma - 1.0) < 0.1 and abs(spacing - 0.1) < 0.005
    assert abs(noise_sigma(t, slow) / (sigma * math.sqrt(5.0)) - 1.0) < 0.1
    # the even grid, every frame: the channel's own sigma
    full = 0.2 * np.sin(0.5 * t) + sigma * rng.standard_normal(t.size)
    assert abs(noise_sigma(t, full) / sigma - 1.0) < 0.1
    # the filled signal's second differences (the reading before) fall far short
    filled = np.interp(t, t[own], slow[own])
    d2 = np.diff(filled, 2)
    before = 1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0)
    assert before < 0.5 * sigma
