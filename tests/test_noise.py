"""Measurement noise from the record (gcs_estimator/estimation/noise.py,
`measurement_noise = "auto"`): the estimator of each channel's sigma, its spread, and
the filters using it from the first restart on where the sensor is clearly better."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from gcs_estimator.cli import main
from gcs_estimator.config import load_config
from gcs_estimator.differences import divided_differences
from gcs_estimator.estimation.noise import (
    CLEARLY,
    FLOOR_RATIO,
    MIN_DIFFERENCES,
    READING_SPREAD,
    noise_from_differences,
    reading_z,
)
from gcs_estimator.model.channels import OBS_NAMES
from gcs_estimator.outputs.diagnosis import (
    CHANNEL_NIS_LIMIT,
    advised_settings,
    contradicted_readings,
    set_argv,
    trust_warnings,
)
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import channel_mean_squares
from sim.scenario import scenario_of
from sim.truth import simulate
from tests.conftest import CONFIGS


def _signal(t: np.ndarray) -> np.ndarray:
    """A smooth manoeuvre with kinks: slow sines and a ramp that turns every 2 s."""
    ramp = np.abs(((t / 2.0) % 2.0) - 1.0)
    return np.sin(0.7 * t) + 0.5 * np.sin(2.3 * t + 1.0) + 0.3 * ramp


def test_white_noise_on_a_smooth_signal_is_read_within_a_few_percent() -> None:
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 50.0, 0.02)  # 2500 samples: the estimate within about 4 %
    sigma = np.array([0.3, 0.005, 0.0035, 0.0017, 0.05, 0.2, 0.6])
    y = _signal(t)[:, None] * [5.0, 0.05, 0.1, 0.2, 2.0, 1.0, 3.0]
    y = y + sigma * rng.standard_normal((t.shape[0], sigma.shape[0]))
    got, used = noise_from_differences(t, y, 3.0 * sigma)  # a config three times off
    np.testing.assert_allclose(got, sigma, rtol=0.12)
    assert np.all(used == t.shape[0] - 4)


def test_the_readings_spread_is_the_one_auto_judges_by() -> None:
    """White noise of the configured sigma, read from 250 samples in 600 records: the
    readings' relative spread is READING_SPREAD / sqrt(m) within 10 %, and a reading falls
    CLEARLY standard errors below the configured sigma (auto would take it) in under 1 %
    of records; noise at a third of the configured sigma always does."""
    rng = np.random.default_rng(11)
    n, records = 250, 600
    t = np.arange(n, dtype=float) * 0.02
    y = rng.standard_normal((n, records))
    got, used = noise_from_differences(t, y, np.ones(records))
    expected = READING_SPREAD / math.sqrt(n - 4)
    assert abs(np.std(got) / expected - 1.0) < 0.1
    z = reading_z(got, used, np.ones(records))
    assert np.mean(z < -CLEARLY) < 0.01
    third, used = noise_from_differences(t, y / 3.0, np.ones(records))
    assert np.all(reading_z(third, used, np.ones(records)) < -CLEARLY)
    # Too few differences for a reading of its own: no verdict either way.
    assert np.isnan(reading_z(np.array([0.1]), np.array([MIN_DIFFERENCES - 1]), np.ones(1)))[0]


def test_auto_takes_the_reading_only_where_the_sensor_is_clearly_better() -> None:
    """A flight whose accelerometers are three times quieter than configured and whose
    pitch-acceleration signal is three times noisier: with the default ("auto") the final
    pass uses the accelerometers' reading (within 20 % of the noise flown) and keeps the
    configured sigma on every other channel, and the run names qdot as read noisier.
    Doing what that warning says (qdot's sigma set to the sensor's) puts every
    coefficient within 3 sigma of the truth, with sigmas no wider than the configured
    accelerometer noise gives."""
    over = [
        "simulation.manoeuvre.duration_s=30",
        "simulation.sensors.noise_sigma.a_x=0.0667",
        "simulation.sensors.noise_sigma.a_z=0.0667",
        "simulation.sensors.noise_sigma.qdot=0.15",
    ]
    config = load_config(CONFIGS / "noc_uav.toml", over)
    assert config.filter.measurement_noise == "auto"
    flight = simulate(config, seed=5)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    used = np.array(run.result.measurement_sigma)
    configured = np.array(config.filter.measurement_sigma)
    quiet = [OBS_NAMES.index("a_x"), OBS_NAMES.index("a_z")]
    np.testing.assert_allclose(used[quiet], 0.0667, rtol=0.2)
    rest = [c for c in range(len(OBS_NAMES)) if c not in quiet]
    np.testing.assert_array_equal(used[rest], configured[rest])
    (text,) = [w for w in trust_warnings(run) if "read noisier" in w]
    assert "qdot" in text and "a_z" not in text and "set [filter.measurement_sigma]" in text

    advised = [*over, "filter.measurement_sigma.qdot=0.15"]
    truth = np.array(config.truth)
    sigmas = {}
    for policy in ("auto", "config"):
        choice = f'filter.measurement_noise="{policy}"'
        cfg = load_config(CONFIGS / "noc_uav.toml", [*advised, choice])
        result = run_recording(cfg, flight.t_s, flight.inputs, flight.measurements).result
        sigmas[policy] = result.filters["EKF"].sigma
        if policy == "auto":
            for f in result.filters.values():
                assert np.all(np.abs(f.coefficients - truth) < 3.0 * f.sigma)
    assert np.all(sigmas["auto"] <= sigmas["config"] * 1.001)
    assert np.median(sigmas["auto"] / sigmas["config"]) < 0.9


def test_gaps_uneven_samples_and_empty_channels() -> None:
    """Each channel is read from its own samples: a sample missing now and then, or an
    uneven interval, still gives differences (divided ones); five samples across a lost
    stretch give none; a channel without enough keeps its fallback, and a constant one
    gets the floor, never zero."""
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 50.0, 0.02)  # 2500 samples: the estimate within about 4 %
    t[1250:] += 0.013  # one uneven interval
    y = np.zeros((t.shape[0], 3))
    y[:, 0] = _signal(t) + 0.3 * rng.standard_normal(t.shape[0])
    y[::20, 0] = np.nan  # a sample missing now and then
    y[600:700, 0] = np.nan  # a lost stretch of 2 s
    y[:, 1] = np.nan
    y[: MIN_DIFFERENCES + 3, 1] = 0.2 * rng.standard_normal(MIN_DIFFERENCES + 3)
    y[:, 2] = 1.5  # a channel that never moves
    fallback = np.array([1.0, 0.7, 0.4])
    got, used = noise_from_differences(t, y, fallback)
    assert abs(got[0] / 0.3 - 1.0) < 0.15
    present = int(np.isfinite(y[:, 0]).sum())
    assert used[0] == present - 4 - 4  # all fives but the four across the lost stretch
    assert used[1] == MIN_DIFFERENCES - 1 and got[1] == fallback[1]
    assert got[2] == FLOOR_RATIO * fallback[2]


def test_each_channel_at_its_own_rate_and_jitter_is_read() -> None:
    """Frames as a link or a log brings them: the pitch rate at 10 Hz and the pitch angle
    at 2.5 Hz, each sample a few milliseconds off its grid, each in frames of its own
    (NaN in the other's column), a time sent twice. Both readings within 15 % of the noise
    drawn; white noise on a grid this uneven gives differences of its own sigma."""
    rng = np.random.default_rng(8)
    t_q = np.arange(0.0, 300.0, 0.1) + rng.uniform(-0.01, 0.01, 3000)
    t_th = np.arange(0.0, 300.0, 0.4) + 0.05 + rng.uniform(-0.02, 0.02, 750)
    t = np.concatenate([t_q, t_th, t_q[100:101]])
    y = np.full((t.shape[0], 2), np.nan)
    y[:3000, 0] = 0.02 * np.sin(0.7 * t_q) + 0.004 * rng.standard_normal(3000)
    y[3000:3750, 1] = 0.05 * np.sin(0.2 * t_th) + 0.002 * rng.standard_normal(750)
    y[3750, 0] = y[100, 0]
    order = np.argsort(t, kind="stable")
    got, used = noise_from_differences(t[order], y[order], np.array([0.01, 0.01]))
    np.testing.assert_allclose(got, [0.004, 0.002], rtol=0.15)
    assert used[0] == 3000 - 4 and used[1] == 750 - 4
    grid = np.sort(t_q)
    white = [divided_differences(grid, rng.standard_normal(3000)) for _ in range(20)]
    assert abs(float(np.mean(np.square(white))) - 1.0) < 0.03
    # A clock reset: the fives across it give none, the rest as before.
    reset = np.concatenate([grid[:1500], grid[:1500] - 0.05])
    assert divided_differences(reset, np.ones(3000)).shape[0] == 2 * (1500 - 4)


def test_each_channels_reading_is_reported_and_config_reads_none(tmp_path: Path) -> None:
    """A flight whose pitch-rate gyro and accelerometer are three times noisier than the
    config says: the restarts read every channel's noise within 20 % of the levels flown,
    the results say so (result, JSON, table), and "auto" keeps the configured sigma on
    the two read noisier; with "config" nothing is read. The readings alone: no structure
    check, which widens only the coefficients' sigmas (decision 0066)."""
    over = [
        "simulation.manoeuvre.duration_s=30",
        "simulation.sensors.noise_sigma.q_deg=0.3",
        "simulation.sensors.noise_sigma.a_z=0.6",
        "filter.structure_check=off",
    ]
    config = load_config(CONFIGS / "noc_uav.toml", over)
    flight = simulate(config, seed=6)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    flown = np.array(scenario_of(config).sensors.noise_sigma)
    assert run.result.noise_reading is not None
    np.testing.assert_allclose(run.result.noise_reading.sigma, flown, rtol=0.2)
    # every channel the flight has read (a channel it lacks, h_dot here, counts none)
    has = np.isfinite(flight.measurements).any(axis=0)
    differences = np.array(run.result.noise_reading.differences)
    assert differences[has].min() >= MIN_DIFFERENCES and not differences[~has].any()
    noisier = [OBS_NAMES.index("q"), OBS_NAMES.index("a_z")]
    used = np.array(run.result.measurement_sigma)
    configured_sigma = np.array(config.filter.measurement_sigma)
    np.testing.assert_array_equal(used[noisier], configured_sigma[noisier])
    configured = run_recording(
        load_config(CONFIGS / "noc_uav.toml", [*over, 'filter.measurement_noise="config"']),
        flight.t_s,
        flight.inputs,
        flight.measurements,
    ).result
    assert configured.noise_reading is None
    assert configured.measurement_sigma == tuple(load_config("noc_uav").filter.measurement_sigma)

    args = ["simulate", "--out", str(tmp_path), "--seed", "6", "--view", "off"]
    assert main(args + [a for o in over for a in ("--set", o)]) == 0
    data = json.loads((tmp_path / "results_sys1.json").read_text())["diagnostics"]
    assert data["measurement_noise"] == "auto"
    assert list(data["measurement_sigma"]) == list(OBS_NAMES)
    np.testing.assert_allclose(list(data["noise_reading"].values()), flown, rtol=0.2)
    table = (tmp_path / "results_sys1.md").read_text()
    assert "measurement noise (σ, SI; measurement_noise = 'auto'): V " in table


def test_a_channel_whose_noise_is_set_wrong_is_named_by_its_innovations() -> None:
    """Each channel's innovations over the final pass against what the filter predicts
    (metrics.FilterSummary.channel_nis, the JSON's innovation_mean_square): near 1 on every
    channel where the settings are the simulator's, about 9 on a gyro configured with a
    third of its noise (named as larger than predicted), about 1/9 on one configured with
    three times its noise (named as smaller). The innovations alone: no structure check,
    which widens only the coefficients' sigmas (decision 0066)."""
    short = ["simulation.manoeuvre.duration_s=30"]
    flight = simulate(load_config("noc_uav", short), seed=4)
    q = OBS_NAMES.index("q")
    ratios: dict[str, np.ndarray] = {}
    named: dict[str, list[str]] = {}
    for label, sigma_deg in (("right", 0.1), ("a third", 0.1 / 3.0), ("three times", 0.3)):
        config = load_config(
            "noc_uav",
            [
                *short,
                f"filter.measurement_sigma.q_deg={sigma_deg}",
                'filter.measurement_noise="config"',
                "filter.structure_check=off",
            ],
        )
        run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
        ratios[label] = np.array(run.summaries["EKF"].channel_nis)
        named[label] = [w for w in trust_warnings(run) if "innovations" in w and "predicts" in w]
        saved = results_dict(run)["filters"]["EKF"]["innovation_mean_square"]
        assert list(saved) == list(OBS_NAMES)
        got = [np.nan if saved[n] is None else saved[n] for n in OBS_NAMES]
        assert np.allclose(got, ratios[label], equal_nan=True)
    # the channels the flight has (not h_dot here): NaN on a channel never used
    has = np.isfinite(flight.measurements).any(axis=0)
    for label in ratios:
        assert np.array_equal(np.isfinite(ratios[label]), has), label
        ratios[label] = ratios[label][has]
    assert np.all(np.abs(ratios["right"] - 1.0) < 0.15), ratios["right"].round(2)
    assert named["right"] == []
    assert ratios["a third"][q] > 2.0 * CHANNEL_NIS_LIMIT
    assert ratios["three times"][q] < 0.5 / CHANNEL_NIS_LIMIT
    others = np.arange(int(has.sum())) != q
    for label in ("a third", "three times"):
        assert np.all(np.abs(ratios[label][others] - 1.0) < 0.2), (label, ratios[label].round(2))
    for w in named["a third"]:
        assert "larger than the filter predicts on q " in w
    assert [w.split(":")[0] for w in named["a third"]] == ["EKF", "IEKF"]
    assert [w.split(":")[0] for w in named["three times"]] == ["EKF", "IEKF"]
    assert all("smaller than the filter predicts on q " in w for w in named["three times"])
    # Rows where a channel was not used leave it out; a channel never used is NaN.
    e = np.array([[1.0, np.nan], [3.0, np.nan], [np.nan, np.nan]])
    s = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0]])
    mean = channel_mean_squares(e, s)
    assert mean[0] == 5.0 and math.isnan(mean[1])


def _smoothed(y: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """y through a first-order low-pass of time constant tau [s] at sample interval dt [s],
    as an autopilot filters its airspeed before it logs or sends it."""
    a = math.exp(-dt / tau)
    out = y.copy()
    for k in range(1, out.shape[0]):
        out[k] = a * out[k - 1] + (1.0 - a) * y[k]
    return out


def test_a_smoothed_channel_read_below_its_error_is_named_and_the_reading_not_kept() -> None:
    """An airspeed the autopilot low-passes (time constant 0.1 s at 50 Hz) changes far
    less from one sample to the next than its error from the aircraft's: "auto" reads its
    noise far below the configured sigma and takes it, and its innovations come out many
    times what the filters predict, dragging the estimates. The run names that reading
    and advises measurement_noise = "config", keeping the readings that held (the
    accelerometers, three times quieter than configured) as their sigmas. Run again with
    that advice, the airspeed has its configured sigma, the accelerometers their readings,
    no channel's innovations are above what the filters predict, every coefficient is
    within 3 of its sigmas of the truth, the sigmas are widened less, and nothing is
    advised again (decision 0091)."""
    over = [
        "simulation.manoeuvre.duration_s=30",
        "simulation.sensors.noise_sigma.a_x=0.0667",
        "simulation.sensors.noise_sigma.a_z=0.0667",
    ]
    config = load_config(CONFIGS / "noc_uav.toml", over)
    flight = simulate(config, seed=2)
    y = np.array(flight.measurements, float)
    v = OBS_NAMES.index("V")
    y[:, v] = _smoothed(y[:, v], float(np.median(np.diff(flight.t_s))), 0.1)
    run = run_recording(config, flight.t_s, flight.inputs, y)
    configured = np.array(config.filter.measurement_sigma)
    used = np.array(run.result.measurement_sigma)
    assert used[v] < configured[v] / CLEARLY
    for s in run.summaries.values():
        assert s.channel_nis[v] > 2 * CHANNEL_NIS_LIMIT
    assert [name for name, _, _ in contradicted_readings(run)] == ["V"]
    (said,) = [w for w in trust_warnings(run) if "smoother than their error" in w]
    assert said.startswith("the noise read from the samples was taken below the configured σ on V")
    advised = advised_settings(run)
    quiet = ["a_x", "a_z"]
    assert advised.keys() == {"filter.measurement_noise"} | {
        f"filter.measurement_sigma.{n}" for n in quiet
    }
    assert advised["filter.measurement_noise"] == "config"
    for n in quiet:  # each as the run used it, the data's reading
        c = OBS_NAMES.index(n)
        assert advised[f"filter.measurement_sigma.{n}"] == float(f"{used[c]:.4g}")
        assert used[c] < configured[c] / 2

    again_config = load_config(CONFIGS / "noc_uav.toml", [*over, *set_argv(advised)[1::2]])
    again = run_recording(again_config, flight.t_s, flight.inputs, y)
    used_again = dict(zip(OBS_NAMES, again.result.measurement_sigma, strict=True))
    assert used_again["V"] == configured[v]
    for n in quiet:
        assert used_again[n] == advised[f"filter.measurement_sigma.{n}"]
    for kind, s in again.summaries.items():
        nis = np.array(s.channel_nis)
        assert np.all(nis[np.isfinite(nis)] < CHANNEL_NIS_LIMIT), (kind, nis)
        est = np.array([c.estimate for c in s.coefficients])
        sigma = np.array([c.sigma for c in s.coefficients])
        z = (est - flight.truth) / sigma
        assert np.all(np.abs(z) < 3.0), (kind, z)
        widened = max(c.sigma_parts.inflation for c in s.coefficients)
        before = max(c.sigma_parts.inflation for c in run.summaries[kind].coefficients)
        assert widened < before / 2, (kind, widened, before)
    assert advised_settings(again) == {}
    assert not contradicted_readings(again)
