"""Sensors where they really are: a vane ahead of the CG, accelerometers off it, a rate
gyro with a bias. The simulator flies them; the filters are told where they sit and
estimate the bias with the coefficients."""

from __future__ import annotations

import numpy as np

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.warmstart import equation_error
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.outputs.diagnosis import (
    VELOCITY_STAGE,
    advised_settings,
    air_moved,
    trust_warnings,
)
from gcs_estimator.runtime.session import (
    FRAMES_CHECK_MIN,
    RecordingSource,
    Session,
    run_recording,
)
from gcs_estimator.uncertainty.metrics import NOT_IDENTIFIED, WEAK
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import Flight, simulate

PLACEMENT = [
    "sensors.vane_x_m=1.0",
    "sensors.vane_z_m=0.1",
    "sensors.accel_x_m=-0.2",
    "sensors.accel_z_m=0.05",
]
GYRO_BIAS = 0.003  # rad/s: an ordinary MEMS rate-gyro bias
NO_CHECK = "filter.structure_check=off"
WELL_EXCITED = ("CL0", "CLa", "Cm0", "Cma", "Cmq", "Cmde")


def test_declared_placement_and_bias_state_recover_coefficients_and_bias() -> None:
    flying = [*PLACEMENT, f"simulation.sensors.bias.q={GYRO_BIAS}"]
    flight = simulate(load_config("noc_uav", flying), seed=1)
    # The covariance's sigma alone: no structure check (decision 0066).
    told = load_config("noc_uav", [*flying, 'sensors.bias_states=["q"]', NO_CHECK])
    res = run_recording(told, flight.t_s, flight.inputs, flight.measurements).result
    assert res.bias_names == ("q_bias",)
    for kind, f in res.filters.items():
        z = (f.coefficients - flight.truth) / f.sigma
        assert np.all(np.abs(z) < 3.0), (kind, dict(zip(res.names, z.round(1), strict=True)))
        assert abs(f.biases[0] - GYRO_BIAS) < 3.0 * f.bias_sigma[0], (kind, f.biases, f.bias_sigma)
        assert f.bias_sigma[0] < GYRO_BIAS / 3  # the bias is resolved, not just allowed for


def test_placement_left_out_biases_the_lift_and_moment_derivatives() -> None:
    """The same flight read as if the sensors sat at the CG: the filters cannot tell,
    and the well-excited coefficients end many sigma off (why the geometry is asked for)."""
    flight = simulate(load_config("noc_uav", PLACEMENT), seed=1)
    unaware = load_config("noc_uav", [NO_CHECK])  # the covariance's sigma alone
    res = run_recording(unaware, flight.t_s, flight.inputs, flight.measurements).result
    well = [res.names.index(n) for n in WELL_EXCITED]
    z = (res.filters["IEKF"].coefficients - flight.truth) / res.filters["IEKF"].sigma
    assert np.max(np.abs(z[well])) > 10.0


def test_warm_start_bridges_a_channel_sent_at_half_the_frame_rate() -> None:
    """Alpha in every other frame only (a slower stream, lost packets): the equation-error
    fit still uses nearly every frame, and lands near the truth."""
    config = load_config("noc_uav")
    flight = simulate(config, seed=1)
    n = 500  # the first 10 s
    y = flight.measurements[:n].copy()
    y[1::2, 1] = np.nan
    model = build_model(config)
    p = model.n_coefficients
    ws = equation_error(model, flight.t_s[:n], flight.inputs[:n], y, np.zeros(p), np.full(p, 10.0))
    assert min(ws.samples) > 0.9 * n
    for name in ("CLa", "Cma", "Cmde"):
        i = model.names.index(name)
        assert abs(ws.beta[i] - flight.truth[i]) < 0.1 * abs(flight.truth[i]), name


def test_warm_start_bridges_channels_sent_at_a_twentieth_of_the_frame_rate() -> None:
    """Airspeed and pitch angle at 2.5 Hz among 50 Hz frames (a telemetry link's default
    streams, every other channel in every frame): no frame carries every channel, and
    the fit still uses nearly every frame and lands near the truth."""
    config = load_config("noc_uav")
    flight = simulate(config, seed=1)
    n = 500
    y = flight.measurements[:n].copy()
    slow = np.ones(n, bool)
    slow[::20] = False
    y[slow, 0] = np.nan  # V
    y[np.roll(slow, 7), 2] = np.nan  # theta, its samples between V's
    assert not np.isfinite(y).all(axis=1).any()
    model = build_model(config)
    p = model.n_coefficients
    ws = equation_error(model, flight.t_s[:n], flight.inputs[:n], y, np.zeros(p), np.full(p, 10.0))
    assert min(ws.samples) > 0.9 * n
    for name in ("CLa", "Cma", "Cmde"):
        i = model.names.index(name)
        assert abs(ws.beta[i] - flight.truth[i]) < 0.1 * abs(flight.truth[i]), name


ALPHA_RATE = ['coefficients.Cm=["1", "alpha", "qhat", "elevator", "adhat"]', "truth.Cmadot=-20"]
"""The NOC UAV with a pitch-damping alpha-rate term (as JSBSim's and DATCOM's models have)."""


def test_an_alpha_rate_term_is_flown_and_identified_apart_from_pitch_damping() -> None:
    """The simulator flies Cmadot; the filters, told of it, estimate it and Cmq within 3
    sigma and 10 %, do not mark Cmadot identified apart, and mark the pair as strongly
    correlated (in calm air alphadot follows q). The warm start's fit includes the term."""
    config = load_config("noc_uav", ALPHA_RATE)
    flight = simulate(config, seed=1)
    model = build_model(config)
    p = model.n_coefficients
    ws = equation_error(
        model, flight.t_s, flight.inputs, flight.measurements, np.zeros(p), np.full(p, 100.0)
    )
    i_q, i_ad = config.coefficient_names.index("Cmq"), config.coefficient_names.index("Cmadot")
    damping = flight.truth[i_q] + flight.truth[i_ad]
    assert abs(ws.beta[i_q] + ws.beta[i_ad] - damping) < 0.2 * abs(damping)
    vehicle = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    res = vehicle.result
    for kind, f in res.filters.items():
        for i in (i_q, i_ad):
            err = f.coefficients[i] - flight.truth[i]
            assert abs(err) < 3.0 * f.sigma[i], (kind, res.names[i], f.coefficients[i], f.sigma[i])
            assert abs(err) < 0.1 * abs(flight.truth[i]), (kind, res.names[i], f.coefficients[i])
        mark = {c.name: c for c in vehicle.summaries[kind].coefficients}["Cmadot"]
        # never "identified" apart from Cmq; the structure check's timing and placement
        # priors (decision 0047) widen its sigma to "not identified" in some runs
        assert mark.identifiability in (WEAK, NOT_IDENTIFIED), mark
        assert mark.correlated_with == "Cmq" and abs(mark.correlation) > 0.9, mark


def _checked_run(config: AircraftConfig, flight: Flight) -> VehicleResult:
    """A run as a link's session makes it: its frames' compatibility checked at the end."""
    session = Session(config, check_frames=True)
    session.run(RecordingSource(flight.t_s, flight.inputs, flight.measurements))
    return session.results()[RecordingSource.SYSTEM_ID]


def _gyro_warnings(run: VehicleResult) -> list[str]:
    return [w for w in trust_warnings(run) if "q bias" in w]


def test_a_gyro_bias_the_filters_do_not_carry_is_found_in_a_links_frames_and_named() -> None:
    """A link's frames through the data compatibility check at the end of the run
    (compat.of_frames; decision 0084): a gyro bias the filters do not carry is found
    within 3 of its sigmas of the bias flown, and the warning names the key; told to
    estimate it, the warning names no key; flown without one, nothing is found."""
    flying = [f"simulation.sensors.bias.q={GYRO_BIAS}", NO_CHECK]
    flight = simulate(load_config("noc_uav", flying), seed=2)
    run = _checked_run(load_config("noc_uav", flying), flight)
    assert run.compatibility is not None
    (q_bias,) = [
        f for f in run.compatibility["findings"] if (f["channel"], f["kind"]) == ("q", "bias")
    ]
    assert q_bias["significant"] and abs(q_bias["value"] - GYRO_BIAS) < 3 * q_bias["sigma"]
    (named,) = _gyro_warnings(run)
    assert 'bias_states = ["q"]' in named, named
    told = load_config("noc_uav", [*flying, 'sensors.bias_states=["q"]'])
    (named,) = _gyro_warnings(_checked_run(told, flight))
    assert "bias_states" not in named, named
    plain = load_config("noc_uav", [NO_CHECK])
    run = _checked_run(plain, simulate(plain, seed=2))
    assert run.compatibility is not None
    assert not [f for f in run.compatibility["findings"] if f["significant"]], run.compatibility
    assert not _gyro_warnings(run)
    # Within its budget of frames (the last ones), and none where the budget is spent.
    assert run.compatibility["frames_checked"] == run.compatibility["frames"] == len(flight.t_s)
    session = Session(plain, check_frames=True)
    session.run(RecordingSource(flight.t_s, flight.inputs, flight.measurements))
    est = session.estimators[RecordingSource.SYSTEM_ID]
    found = session.frames_checked(est, budget=1000)
    assert found is not None and found["frames_checked"] == 1000
    assert session.frames_checked(est, budget=FRAMES_CHECK_MIN - 1) is None
    # A recording's session (a log's: checked as it is read) does not check its frames.
    assert (
        run_recording(plain, flight.t_s, flight.inputs, flight.measurements).compatibility is None
    )


def test_what_the_velocity_stage_finds_in_moving_air_is_named_and_not_advised() -> None:
    """The compatibility check's velocity stage takes the wind as steady. In light
    turbulence, with sensors that have no errors, it finds the airspeed and alpha
    shifted and alpha biased far beyond its sigma (the gusts). The filters found the air
    moving: the warning says those findings may be the gusts, and nothing is advised
    (neither a bias state nor a larger sigma on channels whose innovations the filters
    predict). In calm air an accelerometer bias it finds is advised (decision 0088)."""
    short = [NO_CHECK, "simulation.manoeuvre.duration_s=20"]
    gusts = load_config("noc_uav", [*short, 'simulation.turbulence.preset="light"'])
    run = _checked_run(gusts, simulate(gusts, seed=1))
    assert run.compatibility is not None
    found = [f for f in run.compatibility["findings"] if f["significant"]]
    assert any(f["channel"] in VELOCITY_STAGE for f in found), found
    assert air_moved(run)
    assert advised_settings(run) == {}
    (named,) = [w for w in trust_warnings(run) if w.startswith("the frames' kinematics")]
    assert "may be the gusts" in named and "bias_states" not in named, named
    (noisier,) = [w for w in trust_warnings(run) if w.startswith("the data read noisier")]
    assert "not advised on" in noisier, noisier

    biased = load_config("noc_uav", [*short, "simulation.sensors.bias.a_z=0.3"])
    run = _checked_run(biased, simulate(biased, seed=1))
    assert not air_moved(run)
    assert advised_settings(run)["sensors.bias_states"] == ["a_z"]
    (named,) = [w for w in trust_warnings(run) if w.startswith("the frames' kinematics")]
    assert "may be the gusts" not in named and 'bias_states = ["a_z"]' in named, named
