"""`refine`: maximum likelihood over the whole record, its sigmas and the trust marks."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from gcs_estimator import cli
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.telemetry.mavlink import read_tlog
from gcs_estimator.model.channels import N_OBS, OBS_NAMES
from gcs_estimator.outputs.diagnosis import (
    ADVICE_HEAD,
    CHANNEL_NIS_LIMIT,
    advised_settings,
    fitted_noise,
    process_noise_settings,
    residuals_white,
    set_argv,
    trust_warnings,
)
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.outputs.sinks import RefineStatus
from gcs_estimator.refine import (
    RefineError,
    RefineProgress,
    choose_method,
    refine_run,
)
from gcs_estimator.refine.result import Refined as RefinedFit
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import IDENTIFIED, NOT_IDENTIFIED, WEAK, identifiability
from sim.reference import output_error
from sim.scenario import scenario_of
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle

BOOK_TIMING = ("--set", "data.estimate_input_delay=false")
"""The book's fits of HFB-320 take the inputs' timing as logged (decision 0044)."""


def test_output_error_matches_the_simulators_own_fit(noc_config: AircraftConfig) -> None:
    """On a calm simulated flight (the model exact, the noise white) refine ends where
    the simulator's output-error yardstick does (its own integrator, finite-difference
    sensitivities), the residuals come out white, no channel's weight moves the fit
    beyond what it gives up, the fit lands where the filter it started from did, so the
    corrected sigma is the Cramer-Rao one, and the noise levels are those the simulator
    used. Half the manoeuvre (30 s: its elevator multisteps and pulses) is as close to the
    yardstick as the whole one and takes half the time (decision 0062)."""
    noc_config = load_config(noc_config.source, ["simulation.manoeuvre.duration_s=30"])
    flight = simulate(noc_config, seed=3)
    run = run_recording(noc_config, flight.t_s, flight.inputs, flight.measurements)
    refined = refine_run(run.result, "output-error")
    yardstick = output_error(noc_config, flight)
    assert refined.converged
    assert np.all(np.abs(refined.coefficients - yardstick.coefficients) < 0.2 * yardstick.sigma)
    np.testing.assert_allclose(refined.crb_sigma, yardstick.sigma, rtol=0.15)
    np.testing.assert_allclose(refined.sigma, refined.crb_sigma, rtol=0.25)
    # The model holds: halving a channel's weight moves the fit no more than the
    # information given up allows, so the structure adds nothing.
    assert np.all(refined.structure_sigma < 0.1 * refined.crb_sigma)
    # Filter and fit agree within what their covariances allow: nothing added.
    assert refined.difference_sigma is not None
    assert np.all(refined.difference_sigma < 0.3 * refined.crb_sigma)
    assert not any("lands further from the filter" in w for w in trust_warnings(run, refined))
    colour = refined.residual_colour
    assert np.isnan(colour[OBS_NAMES.index("h_dot")])  # no climb rate in the record
    assert np.all(colour[np.isfinite(colour)] < 2.0) and np.isfinite(colour).sum() == 7
    simulated = np.array(scenario_of(noc_config).sensors.noise_sigma)
    np.testing.assert_allclose(refined.noise_sigma[:4], simulated[:4], rtol=0.1)
    truth = np.array(noc_config.truth)
    z = (refined.coefficients - truth) / refined.sigma
    assert np.mean(z**2) < 4.0


def test_turbulent_record_gets_wider_sigma_than_cramer_rao(hfb_config: AircraftConfig) -> None:
    """HFB-320 flew in turbulence: output error leaves coloured residuals, its channels
    disagree, it lands far from the filters (which follow the gusts), and the corrected
    sigma is wider than the Cramer-Rao bound on every coefficient, wide enough to cover
    the fit's distance from the book's estimates."""
    from gcs_estimator.ingest.flightdata import load_recording

    rec = load_recording("hfb320", hfb_config.data)[1]
    run = run_recording(hfb_config, rec.t_s, rec.inputs, rec.measurements)
    refined = refine_run(run.result, "output-error")
    assert np.all(refined.sigma >= refined.crb_sigma)
    assert np.median(refined.sigma / refined.crb_sigma) > 1.5
    # The channels pull the fit different ways: trusting one less moves some
    # coefficient by more than its Cramer-Rao sigma.
    assert np.max(refined.structure_sigma / refined.crb_sigma) > 1.0
    # The IEKF and the fit weigh the gusts differently: the fit lands further from the
    # filter than both covariances allow. With that distance in its sigma, the sigma
    # covers how far output error lands from the book (the IEKF lands close to it).
    difference = refined.difference_sigma
    assert difference is not None and np.max(difference / refined.crb_sigma) > 2.0
    book = np.array(hfb_config.truth)
    z = (refined.coefficients - book) / refined.sigma
    assert np.mean(z**2) <= 2.0 and np.all(np.abs(z) <= 3.0)
    assert np.nanmax(refined.residual_colour) > 5.0
    coloured = [w for w in trust_warnings(run, refined) if "far from white" in w]
    assert len(coloured) == 1 and "--method filter-error" in coloured[0]
    apart = [w for w in trust_warnings(run, refined) if "lands further from the filter" in w]
    assert len(apart) == 1 and "CLa ×" in apart[0] and "OE σ includes the difference" in apart[0]
    # A window with too few frames is refused with the reason.
    with pytest.raises(RefineError, match="frames in the window"):
        refine_run(run.result, window_s=(10.0, 10.5))


def test_the_fit_keeps_at_least_the_structure_sigma_the_filters_check_found() -> None:
    """A calm flight with the vane 1 m ahead of the CG and an airframe file that does not
    say so (a model error that stays put): the session's structure check of the IEKF and
    the fit's own both see it. refine_run, given the vehicle, keeps, per coefficient,
    the larger of the two (decision 0031): where the filter's check found more, the
    fit's sigma grows by that; the estimates do not change. The first 20 s of the
    manoeuvre show the vane's error as the whole flight does (decision 0062)."""
    short = "simulation.manoeuvre.duration_s=20"
    config = load_config("noc_uav", [short])
    fl = simulate(load_config("noc_uav", ["sensors.vane_x_m=1.0", short]), seed=1)
    vehicle = run_recording(config, fl.t_s, fl.inputs, fl.measurements)
    assert vehicle.structure is not None and not vehicle.structure.skipped
    # The fit estimates the inputs' delay itself: the floor leaves out the check's
    # timing part (decision 0044).
    parts = vehicle.structure.parts
    filters = np.sqrt(sum(p["IEKF"] ** 2 for name, p in parts.items() if name != "timing"))
    alone = refine_run(vehicle.result, "output-error")
    kept = refine_run(vehicle, "output-error")
    assert alone.filter_structure_sigma is None
    assert kept.filter_structure_sigma is not None
    np.testing.assert_array_equal(kept.filter_structure_sigma, filters)
    np.testing.assert_array_equal(kept.coefficients, alone.coefficients)
    np.testing.assert_allclose(
        kept.structure_sigma, np.fmax(alone.structure_sigma, filters), rtol=1e-12
    )
    # The fit is trusted no further than the filter it started from (decision 0057): its
    # sigma is at least the IEKF's sigma to trust over the same frames, with the same
    # structure sigma as the floor above, without the timing the fit decides itself
    # (decision 0072); a fit given the bare result has no such floor.
    coefficients = vehicle.summaries["IEKF"].coefficients
    shown = np.array([c.sigma for c in coefficients])
    cov = np.array([c.sigma_parts.covariance for c in coefficients])
    moved = cov * np.array([c.sigma_parts.movement_factor for c in coefficients])
    trusted = np.hypot(moved, filters)
    assert alone.sigma_parts.filter_trusted is None
    floor = kept.sigma_parts.filter_trusted
    assert floor is not None
    np.testing.assert_allclose(floor, trusted, rtol=1e-12)
    assert np.all(trusted <= shown * (1.0 + 1e-12))
    assert np.any(trusted < shown)  # the timing part left out
    assert np.all(kept.sigma >= trusted)
    assert kept.difference_sigma is not None
    own = np.sqrt(kept.sigma_within_fit**2 + kept.difference_sigma**2)
    np.testing.assert_allclose(kept.sigma, np.fmax(own, trusted), rtol=1e-12)
    # The vane's error is in alpha: the filter's check finds the lift depends more on
    # the channels' weights than the fit's own does, and the fit's sigma takes that up
    # (where the Cramer-Rao bound is not already the larger).
    grew = [n for n, k, a in zip(kept.names, kept.sigma, alone.sigma, strict=True) if k > 1.1 * a]
    assert {"CL0", "CLa", "CLde"} <= set(grew), grew
    assert np.all(kept.sigma >= alone.sigma * (1.0 - 1e-12))


def test_a_window_the_flight_does_not_reach_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`refine` asked for a window the flight does not reach: --window chooses the filters'
    frames too (decision 0050), so nothing is estimated, the run says why (every frame
    left out by the window) and exits EXIT_NOTHING_ESTIMATED, so a script can tell."""
    out = tmp_path / "out"
    argv = ["refine", "hfb320", "--window", "70:80", "--out", str(out), "--view", "off"]
    assert cli.main(argv) == cli.EXIT_NOTHING_ESTIMATED
    err = capsys.readouterr().err
    assert "no segment the model covers" in err and "left out: window 601" in err
    assert not (out / "results_sys1.json").exists()


def test_identifiability_marks() -> None:
    corr = np.eye(3)
    corr[0, 1] = corr[1, 0] = 0.99
    marks = identifiability(
        np.array([1.0, 2.0, 0.01]), np.array([0.05, 0.05, 0.02]), corr, np.array([10, 10, 10])
    )
    assert marks == (WEAK, WEAK, NOT_IDENTIFIED)
    assert identifiability(np.array([1.0]), np.array([0.05]), np.eye(1)) == (IDENTIFIED,)
    # A filter whose sigma barely shrank from its prior learnt nothing from the data.
    assert identifiability(np.array([1.0]), np.array([0.05]), np.eye(1), np.array([0.08])) == (
        NOT_IDENTIFIED,
    )


def test_noise_model_that_does_not_fit_is_named(hfb_config: AircraftConfig) -> None:
    """Measurement sigmas ten times too small: NIS far above the channel count, and the
    run says so."""
    from gcs_estimator.ingest.flightdata import load_recording

    small = tuple(s / 10 for s in hfb_config.filter.measurement_sigma)
    config = load_config(
        "hfb320",
        [f"filter.measurement_sigma.{n}={v}" for n, v in zip(OBS_NAMES, small, strict=True)],
    )
    rec = load_recording("hfb320", config.data)[1]
    run = run_recording(config, rec.t_s, rec.inputs, rec.measurements)
    assert any("noise model does not fit" in w for w in trust_warnings(run))


@dataclass(frozen=True)
class Refined:
    """What `refine` printed and the results JSON it wrote."""

    table: str
    data: dict[str, Any]


@pytest.fixture(scope="module")
def hfb_refined(tmp_path_factory: pytest.TempPathFactory) -> Refined:
    """`refine hfb320`, the method chosen from the data (filter error, for the flight
    test's turbulent air), the timing as logged as in the book's fit (decision 0044): one
    run for the tests of the command and of the filter-error fit (decision 0062)."""
    out = tmp_path_factory.mktemp("hfb")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = cli.main(["refine", "hfb320", "--out", str(out), "--view", "off", *BOOK_TIMING])
    assert code == 0
    return Refined(printed.getvalue(), json.loads((out / "results_sys1.json").read_text()))


def test_refine_command_on_hfb320_and_on_a_tlog(
    tmp_path: Path, hfb_refined: Refined, noc_config: AircraftConfig
) -> None:
    """`refine` on the bundled record and on a real .tlog the simulated vehicle wrote, the
    method chosen from the data: filter error for the flight test's turbulent air, output
    error for the calm simulated flight; the table holds the fit's column, the JSON the fit
    with its sigmas and why its method, the marks and the warnings."""
    text = hfb_refined.table
    assert "FE estimate" in text and "Before trusting these numbers" in text
    assert "| identified? (FE) |" in text  # the marks' source named: the fit's
    assert "chosen: the IEKF's turbulence level over its final pass" in text
    data = hfb_refined.data
    fit = data["refined"]
    assert fit["method"] == "filter error" and fit["frames"] == 601
    assert fit["method_choice"].endswith("turbulent air, so filter error")
    checked = data["filters"]["IEKF"]["estimates"]
    for name, e in fit["estimates"].items():
        parts = e["sigma_parts"]
        assert parts["difference"] is not None and parts["difference"] >= 0.0, name
        assert e["sigma"] >= max(parts["cramer_rao"], parts["structure"], parts["difference"]), name
        # The session's structure check of the IEKF reached the fit (decision 0031).
        assert parts["filter_structure"] == checked[name]["sigma_parts"]["structure"], name
        assert parts["structure"] >= parts["filter_structure"], name
        # The fit is trusted no further than the filter it started from (decision 0057).
        assert parts["filter_trusted"] == checked[name]["sigma"], name
        assert e["sigma"] >= parts["filter_trusted"], name
    marks = {n: e["identifiability"] for n, e in data["filters"]["IEKF"]["estimates"].items()}
    assert marks["Cma"] == IDENTIFIED and marks["CmV"] == NOT_IDENTIFIED
    rows = [
        [cell.strip() for cell in line.strip(" |").split("|")]
        for line in text.splitlines()
        if line.startswith("| ")
    ]
    column = rows[0].index("identified? (FE)")
    shown = {r[0]: r[column].split(" (ρ")[0] for r in rows[1:]}
    assert shown == {n: e["identifiability"] for n, e in fit["estimates"].items()}
    assert data["warnings"]

    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=20"])
    fl = simulate(config, seed=2)
    tlog = tmp_path / "flight.tlog"
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=tlog).run()
    assert sum(1 for _ in read_tlog(tlog)) > 1000
    out = tmp_path / "tlog"
    argv = ["refine", str(tlog), "--config", "noc_uav", "--out", str(out), "--view", "off"]
    assert cli.main(argv) == 0
    data = json.loads((out / "results_sys1.json").read_text())
    fit = data["refined"]
    assert fit["method"] == "output error"
    assert fit["method_choice"].endswith("calm air, so output error")
    truth = np.array(config.truth)
    est = np.array([fit["estimates"][n]["estimate"] for n in data["coefficients"]])
    sig = np.array([fit["estimates"][n]["sigma"] for n in data["coefficients"]])
    assert fit["converged"] and np.mean(((est - truth) / sig) ** 2) < 4.0


def test_held_noise_reproduces_the_books_filter_error_fit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`refine --method filter-error --hold-noise` on HFB-320 with the book's identified
    noise levels (configs/hfb320_book_noise.toml, which extends hfb320): the noise stays
    at that file's levels, and the coefficients the record identifies end within 2 % of
    the book's filter-error estimates; the JSON says the noise was held."""
    book_noise = load_config("hfb320_book_noise")
    out = tmp_path / "held"
    argv = ["refine", "hfb320", "--config", "hfb320_book_noise"]
    argv += ["--method", "filter-error", "--hold-noise", *BOOK_TIMING]
    assert cli.main([*argv, "--out", str(out), "--view", "off"]) == 0
    capsys.readouterr()
    fit = json.loads((out / "results_sys1.json").read_text())["refined"]
    assert fit["method"] == "filter error, noise held" and fit["converged"]
    sigma = [fit["noise_sigma"][n] for n in ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z")]
    # the record's seven channels (it has no climb rate, h_dot)
    np.testing.assert_allclose(sigma, book_noise.filter.measurement_sigma[:7], rtol=1e-12)
    held_q = [fit["process_noise_density"][n] for n in ("V", "alpha", "theta", "q")]
    np.testing.assert_allclose(held_q, book_noise.filter.process_noise.states[:4], rtol=1e-12)
    assert book_noise.truth is not None
    book = dict(zip(book_noise.coefficient_names, book_noise.truth, strict=True))
    for name in ("CLa", "Cma", "Cmq", "Cmde", "CD0", "CDa"):
        estimate = fit["estimates"][name]["estimate"]
        assert abs(estimate - book[name]) < 0.02 * abs(book[name]), name
    # Without a refinement to hold it for, the option is refused before anything runs.
    assert cli.main(["replay", str(tmp_path / "any.tlog"), "--hold-noise"]) == 2
    assert "add --refine" in capsys.readouterr().err


BOOK_PROCESS_NOISE = {"V": 0.12856, "alpha": 5.861e-6, "theta": 2.004e-7, "q": 3.020e-6}
"""diag(F F') the book identified for HFB-320 (gcs_estimator/data/hfb320/README.md)."""


def test_filter_error_estimates_the_noise_as_the_book_does(hfb_refined: Refined) -> None:
    """`refine hfb320` with the project's defaults (nothing taken from the book; the
    method filter error, as "auto" chooses for this record and as `--method filter-error`
    asks, which test_held_noise_reproduces_the_books_filter_error_fit runs): the
    steady-state filter-error fit estimates the process noise and the innovations'
    covariance with the coefficients, from the IEKF's estimate, and lands where the book's
    filter-error method did: the coefficients the record identifies within 2 %, each
    state's process noise within 25 %, the measurement noise below the defaults' sigmas,
    and every Morelli-Klein sigma at least the Cramer-Rao one; the table heads its
    column FE."""
    config = load_config("hfb320")
    table = hfb_refined.table
    # The fit's column leads, its estimate and its one sigma (decisions 0032, 0033).
    head = next(line for line in table.splitlines() if line.startswith("| coefficient"))
    cells = [cell.strip() for cell in head.strip(" |").split("|")]
    assert cells[1:3] == ["FE estimate", "FE σ"] and "OE estimate" not in table
    fit = hfb_refined.data["refined"]
    assert fit["method"] == "filter error" and fit["converged"]
    assert config.truth is not None
    book = dict(zip(config.coefficient_names, config.truth, strict=True))
    for name in ("CLa", "Cma", "Cmq", "Cmde", "CD0", "CDa"):
        estimate = fit["estimates"][name]["estimate"]
        assert abs(estimate - book[name]) < 0.02 * abs(book[name]), name
    for name, level in BOOK_PROCESS_NOISE.items():
        assert abs(fit["process_noise_density"][name] / level - 1.0) < 0.25, name
    names = ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z")
    sigma = np.array([fit["noise_sigma"][n] for n in names])
    configured = np.array(config.filter.measurement_sigma)[:7]  # no h_dot in the record
    assert np.all(sigma > 0.0) and np.all(sigma < configured)
    for name, e in fit["estimates"].items():
        assert e["sigma"] >= e["sigma_parts"]["cramer_rao"], name


def test_filter_error_finds_the_gusts_where_they_act() -> None:
    """The simulated UAV's flight, calm and in light turbulence (the same seed):
    filter error converges on both, finds process noise on alpha (where the vertical
    gust acts) hundreds of times larger in turbulence, leaves white alpha innovations in
    calm air (with the initial state held at the first frame's measurement its error
    stayed as a slow transient: residual colour 120), and gives every coefficient a
    finite sigma at least its Cramer-Rao one, also where the fit drives a state's
    process noise to its lower bound (which the residuals then do not feel). The method
    "auto" picks output error for the calm flight and filter error for the other. Half
    the manoeuvre (30 s) shows it all (decision 0062)."""
    alpha_noise = {}
    for preset in ("none", "light"):
        over = [f'simulation.turbulence.preset="{preset}"', "simulation.manoeuvre.duration_s=30"]
        config = load_config("noc_uav", over)
        flight = simulate(config, seed=1)
        run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
        refined = refine_run(run.result, "filter-error")
        assert refined.method == "filter error" and refined.converged, preset
        chosen = choose_method(run.result)[0]  # what "auto" picks for this flight
        assert chosen == ("output-error" if preset == "none" else "filter-error"), preset
        assert np.all(np.isfinite(refined.sigma)) and np.all(refined.sigma >= refined.crb_sigma)
        alpha_noise[preset] = refined.process_noise[1]
        if preset == "none":  # the initial state fitted: no transient left in alpha
            assert refined.residual_colour[1] < 2.0
    assert alpha_noise["light"] > 100 * alpha_noise["none"]


def test_constant_gain_kernel_without_gain_flies_open_loop(hfb_config: AircraftConfig) -> None:
    """The filter-error kernel with a zero gain is output error: its innovations equal
    the time-varying kernel's with no process noise, to the float, missing samples
    included; a gain pulls the flight toward the data (smaller innovations)."""
    from gcs_estimator.ingest.flightdata import load_recording
    from gcs_estimator.model.aircraft import build_model
    from gcs_estimator.refine.flights import innovations, steady_innovations

    rec = load_recording("hfb320", hfb_config.data)[1]
    model = build_model(hfb_config, gust_states=False)
    x = np.zeros(model.n)
    assert hfb_config.truth is not None
    x[model.coefficients] = hfb_config.truth
    x[:4] = rec.measurements[0, :4]
    u = np.ascontiguousarray([model.inputs(row) for row in rec.inputs], dtype=float)
    mask = np.isfinite(rec.measurements).astype(float)  # every sample but h_dot's
    mask[100:140, 1] = 0.0  # alpha missing for 4 s
    y = np.ascontiguousarray(np.where(mask > 0, rec.measurements, 0.0))
    t = np.ascontiguousarray(rec.t_s, dtype=float)
    nd = model.arrays.n_dynamic
    args = (t, u, y, mask, model.arrays)
    open_loop, ok = steady_innovations(x, *args, np.zeros((nd, N_OBS)), 0.02, True)
    _, _, raw, ok2 = innovations(x, *args, np.zeros(nd), np.ones(N_OBS), 0.02, True)
    assert ok and ok2
    np.testing.assert_array_equal(open_loop, raw)
    assert np.all(open_loop[100:140, 1] == 0.0)
    K = np.zeros((nd, N_OBS))
    K[2, 2] = K[3, 3] = 0.5  # theta and q pulled halfway to their samples
    closed, ok3 = steady_innovations(x, *args, K, 0.02, True)
    assert ok3
    assert np.sqrt(np.mean(closed[:, 2] ** 2)) < 0.5 * np.sqrt(np.mean(open_loop[:, 2] ** 2))


@pytest.mark.filterwarnings("error::RuntimeWarning")  # nothing overflows the history
def test_a_filter_that_ran_away_starts_again_and_is_named() -> None:
    """A 1.7 s gap in the first tenth of a second, while the coefficients are still at
    their zero prior: the prediction across it takes the flight states where no aircraft
    can be (a negative airspeed). The contract takes that for a divergence there, before
    the values run off to infinity: the filter starts again from the prior, the history
    holds nothing absurd, the run says so, and the restarts still reach the estimate."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    fl = simulate(config, seed=1)
    keep = np.r_[0:4, 90 : len(fl.t_s)]
    run = run_recording(config, fl.t_s[keep], fl.inputs[keep], fl.measurements[keep])
    bound = 2 * np.array([config.data.plausible(q) for q in ("airspeed", "alpha", "theta", "q")])
    warnings = trust_warnings(run)
    ekf = run.result.filters["EKF"]
    assert ekf.health.divergences == 1
    assert any(w.startswith("EKF: the estimate diverged 1 time") for w in warnings)
    for f in run.result.filters.values():
        assert f.track is not None
        assert np.all(np.abs(f.track.x[:, :4]) <= bound)
        assert np.all(f.track.x[:, 0] > 0)
    truth = np.array(config.truth)
    well = [run.result.names.index(n) for n in ("CLa", "Cma", "Cmq", "Cmde")]
    iekf = run.result.filters["IEKF"].coefficients
    assert np.all(np.abs(iekf[well] / truth[well] - 1) < 0.05)


@dataclass
class ThreadedFits:
    """The fits of one short flight by each method in one thread and in three, each with
    the progress reports it gave and the BLAS thread counts seen at each report."""

    fits: dict[tuple[str, int], RefinedFit]
    reports: dict[tuple[str, int], list[RefineProgress]]
    blas_before: list[int]
    blas_during: list[list[int]]
    blas_after: list[int]


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.fixture(scope="module")
def threaded_fits() -> ThreadedFits:
    """One 10 s flight fitted by output error and filter error, in one thread and in
    three: the runs the thread test and the progress test look at (decision 0066: the
    progress test flew a 20 s flight of its own for a filter-error fit)."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=10"])
    flight = simulate(config, seed=3)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    fits = ThreadedFits({}, {}, _blas_threads(), [], [])
    for method in ("output-error", "filter-error"):
        for n in (1, 3):
            heard: list[RefineProgress] = []

            def look(p: RefineProgress, heard: list[RefineProgress] = heard) -> None:
                heard.append(p)
                fits.blas_during.append(_blas_threads())

            fits.fits[method, n] = refine_run(run.result, method, progress=look, threads=n)
            fits.reports[method, n] = heard
    fits.blas_after = _blas_threads()
    return fits


def test_refine_reports_each_iteration(threaded_fits: ThreadedFits) -> None:
    """The progress callback hears every Gauss-Newton iteration with the filter runs so
    far; the last report is the fit's own count; and the status line draws it in place
    on a terminal and as plain lines elsewhere."""
    refined = threaded_fits.fits["filter-error", 1]
    reports = threaded_fits.reports["filter-error", 1]
    assert [p.iterations for p in reports] == list(range(1, refined.iterations + 1))
    assert all(np.isfinite(p.cost) for p in reports)
    runs = [p.runs for p in reports]
    assert runs == sorted(runs) and runs[-1] <= int(refined.message.split("(")[1].split()[0])

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    now = [0.0]
    for out in (Terminal(), io.StringIO()):
        status = RefineStatus(out, every_s=2.0, clock=lambda: now[0])
        for k, p in enumerate(reports):
            now[0] = float(k)  # one report a second
            status(p)
        status.end()
        text = out.getvalue()
        last = f"iteration {refined.iterations}, "
        if isinstance(out, Terminal):  # every 2 s, then the end
            draws = text.split("\r\033[K")[1:]
            assert len(draws) == (len(reports) + 1) // 2 + 1
            assert last in draws[-1] and text.endswith("\n") and text.count("\n") == 1
        else:  # every 20 s, then the end
            lines = text.splitlines()
            assert all(line.startswith("refining: iteration ") for line in lines)
            assert len(lines) == (len(reports) + 19) // 20 + 1 and last in lines[-1]


def test_the_fit_is_the_same_in_any_number_of_threads(threaded_fits: ThreadedFits) -> None:
    """The sensitivities' columns run in threads: one thread or three give the same fit to
    the bit, with the same filter runs, for output error and filter error. While refine
    runs, every BLAS library of the process has one thread (their spinning threads would
    take the cores the fit's threads need); afterwards each has what it had before."""
    for method in ("output-error", "filter-error"):
        one, three = (threaded_fits.fits[method, n] for n in (1, 3))
        assert one.converged and three.converged, method
        assert one.message == three.message, method  # the same filter runs
        for field in ("coefficients", "crb_sigma", "sigma", "biases", "process_noise"):
            assert np.array_equal(getattr(one, field), getattr(three, field), equal_nan=True), (
                method,
                field,
            )
    before, during = threaded_fits.blas_before, threaded_fits.blas_during
    assert before and during and all(counts == [1] * len(before) for counts in during)
    assert threaded_fits.blas_after == before


def test_turbulence_the_running_level_misses_is_found_over_the_pass() -> None:
    """Weak gusts of a long scale length (sigma_w 0.05 m/s, L 530 m) on the simulated UAV:
    the running level, judged over a few seconds, is applied in a small share of the
    final pass, while the pass's average stands many standard errors above zero. The
    report says so for each filter, `refine`'s auto choice is filter error, and the JSON
    carries the pass's level and its z; the same flight in calm air finds nothing over the
    pass."""
    found = {}
    for sigma_w in (0.0, 0.05):
        over = [
            'simulation.turbulence.preset="light"',
            f"simulation.turbulence.sigma_w_mps={sigma_w}",
            "simulation.turbulence.length_w_m=530",
            "simulation.turbulence.length_u_m=530",
            "filter.structure_check=off",  # the level alone: no sigma read (decision 0066)
        ]
        config = load_config("noc_uav", over)
        flight = simulate(config, seed=1)
        run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
        s = run.summaries["IEKF"]
        threshold = config.filter.turbulence.detection_sigma
        warned = {
            w.split(":")[0] for w in trust_warnings(run) if "turbulence over the whole pass" in w
        }
        data = results_dict(run)["filters"]["IEKF"]
        assert data["turbulence_pass_z"] == pytest.approx(s.gust_pass_z)
        # Each frame's report carries the pass's level so far (the view plots it): at the
        # last frame, the level the run reports for its final pass.
        track = run.result.filters["IEKF"].track
        assert track is not None
        assert track.gust_pass_sigma[-1] == pytest.approx(s.gust_pass_sigma, rel=1e-6)
        found[sigma_w] = (s, warned, choose_method(run.result)[0])
    s, warned, method = found[0.05]
    assert s.gust_on_share < 0.5 and s.gust_pass_z >= 2 * threshold
    assert warned == {"EKF", "IEKF"} and method == "filter-error"
    s, warned, method = found[0.0]
    assert s.gust_on_share == 0.0 and s.gust_pass_z < threshold
    assert not warned and method == "output-error"


def test_auto_with_a_fixed_turbulence_level_goes_by_the_level_applied() -> None:
    """With [filter.turbulence] adaptive = false nothing is measured over the pass (its z
    is NaN), so `refine`'s auto choice goes by the fixed level: applied throughout, filter
    error; none, output error."""
    for sigma_w, expected in ((0.8, "filter-error"), (0.0, "output-error")):
        config = load_config(
            "noc_uav",
            [
                "simulation.manoeuvre.duration_s=20",
                "filter.turbulence.adaptive=false",
                f"filter.turbulence.sigma_w_mps={sigma_w}",
            ],
        )
        flight = simulate(config, seed=1)
        run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
        assert np.isnan(run.summaries["IEKF"].gust_pass_z)
        method, why = choose_method(run.result)
        assert method == expected and "turbulence level in" in why, why


def test_the_process_noise_filter_error_finds_is_advised_and_brings_the_filters_in_band() -> None:
    """Light turbulence flown, the filters told the air is calm (no adaptive level): a
    model that misses the gusts. Their innovations come out far larger than they predict,
    and the warnings name `--refine filter-error`; the filter-error fit finds the process
    noise on alpha (where the vertical gust acts), the warnings advise it as `--set`
    arguments (the JSON's diagnostics.advised_settings, the same settings). Run again with
    them, every channel's innovations are as large as the filters predict, every
    coefficient lies within 3 of its sigmas of the truth, and nothing is advised again
    (decision 0085)."""
    over = [
        'simulation.turbulence.preset="light"',
        "simulation.manoeuvre.duration_s=20",
        "filter.turbulence.adaptive=false",
    ]
    config = load_config("noc_uav", over)
    flight = simulate(config, seed=1)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    for s in run.summaries.values():
        assert np.nanmax(s.channel_nis) > 10 * CHANNEL_NIS_LIMIT, s.channel_nis
    assert any("`--refine filter-error`" in w for w in trust_warnings(run))
    fit = refine_run(run.result, "filter-error")
    assert fit.method == "filter error" and fit.converged
    advised = advised_settings(run, fit)
    assert advised["filter.process_noise.alpha"] == pytest.approx(fit.process_noise[1], rel=1e-3)
    warnings = trust_warnings(run, fit)
    assert any(w.startswith("FE finds the flight states driven beyond the model") for w in warnings)
    (line,) = [w for w in warnings if w.startswith(ADVICE_HEAD)]
    assert shlex.split(line[len(ADVICE_HEAD) :]) == set_argv(advised)
    assert results_dict(run, refined=fit)["diagnostics"]["advised_settings"] == advised
    assert residuals_white(fit)
    assert process_noise_settings(run, fit) == {
        k: v for k, v in advised.items() if k.startswith("filter.process_noise.")
    }

    # The same fit with residuals coloured as a model's systematic miss leaves them (the
    # JSBSim mission set: decision 0087): the densities are named and not advised.
    coloured = dataclasses.replace(fit, residual_colour=np.where(fit.residual_colour > 0, 12.0, 0))
    assert not residuals_white(coloured)
    kept = advised_settings(run, coloured)
    fit_only = {"filter.measurement_noise"}  # what holds the fitted sigmas (below)
    assert kept.keys() == {
        k for k in advised if not k.startswith("filter.process_noise.") and k not in fit_only
    }
    (named,) = [w for w in trust_warnings(run, coloured) if w.startswith("FE finds the flight")]
    assert "coloured" in named and "not advised" in named

    # The fit's measurement noise comes with its process noise: where it finds a channel
    # whose innovations are high noisier than the filters took it (here the gusts' short
    # scale roughens the pitch rate, its rate and a_z beyond what the data's own reading
    # says), that sigma is advised; named and not advised where the residuals are coloured
    # (decision 0089).
    fitted = fitted_noise(run, fit)
    assert fitted
    for name, found in fitted:
        assert advised[f"filter.measurement_sigma.{name}"] == float(f"{found:.4g}")
    # and "auto" would take a reading below them again: the configured sigmas are held
    # (decision 0091)
    assert advised["filter.measurement_noise"] == "config"
    (said,) = [w for w in trust_warnings(run, fit) if w.startswith("FE finds the measure")]
    assert "0089" in said and "not advised" not in said
    (said,) = [w for w in trust_warnings(run, coloured) if w.startswith("FE finds the measure")]
    assert "not advised" in said

    sets = set_argv(advised)[1::2]  # what each --set carries, as the command line reads it
    again_config = load_config("noc_uav", [*over, *sets])
    again = run_recording(again_config, flight.t_s, flight.inputs, flight.measurements)
    for kind, s in again.summaries.items():
        nis = np.array(s.channel_nis)
        nis = nis[np.isfinite(nis)]
        assert np.all((nis > 1 / CHANNEL_NIS_LIMIT) & (nis < CHANNEL_NIS_LIMIT)), (kind, nis)
        est = np.array([c.estimate for c in s.coefficients])
        sigma = np.array([c.sigma for c in s.coefficients])
        assert np.all(np.abs(est - flight.truth) < 3.0 * sigma), (
            kind,
            (est - flight.truth) / sigma,
        )
    assert advised_settings(again) == {}
    assert not any("`--refine filter-error`" in w for w in trust_warnings(again))
    assert not fitted_noise(again, fit)  # the sigmas set as advised are not advised again
