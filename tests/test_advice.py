"""What to fly next (uncertainty/advice.py) and the held-out check (--validate; Theil's
inequality coefficient), on the simulated NOC UAV (decisions 0051, 0052)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator import cli
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.outputs.checks import Checks
from gcs_estimator.refine.holdout import check
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.advice import (
    ENVELOPE_PITCH_DEG,
    ENVELOPE_SPEED,
    Advice,
    Candidate,
    advice_of,
    advise,
    candidate_flights,
    in_envelope,
    short_period,
)
from gcs_estimator.uncertainty.metrics import IDENTIFIED, NOT_IDENTIFIED, WEAK
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import simulate

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from advice import FLOWN_AT_S, NO_MULTISTEP, SHORT_PERIOD, manoeuvre_overrides, throttle_step

SEED = 1
MULTISTEPS = ("3-2-1-1", "doublet")


@dataclass(frozen=True)
class Flown:
    """The NOC flight without multisteps, its advice, and the flight with the advised
    multistep added."""

    first: VehicleResult
    advice: Advice
    label: str
    """The advised multistep flown."""
    after: VehicleResult
    after_config: AircraftConfig


def _run(config: AircraftConfig) -> VehicleResult:
    f = simulate(config, seed=SEED)
    return run_recording(config, f.t_s, f.inputs, f.measurements)


@pytest.fixture(scope="module")
def flown() -> Flown:
    config = load_config("noc_uav", NO_MULTISTEP)
    first = _run(config)
    advice = advice_of(first.result, first.summaries["IEKF"])
    assert advice is not None
    multistep = next(
        a.candidate
        for a in advice.advised
        if a.name in SHORT_PERIOD and a.candidate.kind in MULTISTEPS
    )
    after_config = load_config("noc_uav", NO_MULTISTEP + manoeuvre_overrides(multistep))
    return Flown(first, advice, multistep.label(), _run(after_config), after_config)


def test_advice_names_the_short_period_and_a_multistep(flown: Flown) -> None:
    """Without multisteps the short period's coefficients are not all identified; the
    advice names them, each with a manoeuvre, its amplitude and airspeed, and a
    multistep for at least one of them."""
    marks = dict(
        zip(
            flown.advice.names,
            (c.identifiability for c in flown.first.summaries["IEKF"].coefficients),
            strict=True,
        )
    )
    named = {a.name: a for a in flown.advice.advised}
    unidentified = {n for n, m in marks.items() if m != IDENTIFIED}
    assert set(named) == unidentified
    assert unidentified & set(SHORT_PERIOD)
    assert any(named[n].candidate.kind in MULTISTEPS for n in unidentified & set(SHORT_PERIOD))
    sigma_shown = {c.name: c.sigma for c in flown.first.summaries["IEKF"].coefficients}
    for a in flown.advice.advised:
        assert a.predicted_sigma <= a.sigma
        assert abs(a.candidate.airspeed_mps - 24.0) < 1.0
        # The advice speaks of the sigma the table shows, not the covariance's alone.
        assert a.trusted_sigma == pytest.approx(sigma_shown[a.name], rel=1e-9)
        assert a.predicted_trusted_sigma <= a.trusted_sigma
    text = "\n".join(flown.advice.lines())
    assert "3-2-1-1" in text or "doublet" in text


def test_a_manoeuvre_that_leaves_the_envelope_is_not_advised(flown: Flown) -> None:
    """The NOC UAV's propeller is strong: a 20 % throttle step held 6 s open loop, flown
    through the true model, gains over 15 % of airspeed and pitches up past 15 degrees
    (the simulator loops it), so the envelope refuses it, while a 1 degree doublet stays
    inside; no manoeuvre the run's advice names leaves it at the run's estimate."""
    config = flown.after_config
    model = build_model(config, gust_states=False)
    truth = np.array(config.truth, float)
    V = config.airframe.trim_airspeed_mps
    omega = short_period(model, truth, V)
    (step,) = candidate_flights(model, truth, Candidate("throttle step", 0.2, 6.0, V), 50.0, omega)
    (doublet,) = candidate_flights(model, truth, Candidate("doublet", 1.0, 0.3, V), 50.0, omega)
    assert not in_envelope(model, step)
    assert in_envelope(model, doublet)
    simulated = simulate(load_config("noc_uav", NO_MULTISTEP + _step_at(0.2)), seed=SEED)
    moved = np.abs(simulated.states[:, :3] - simulated.states[0, :3]).max(axis=0)
    assert moved[0] > ENVELOPE_SPEED * simulated.states[0, 0]
    assert moved[2] > np.radians(ENVELOPE_PITCH_DEG)
    beta = flown.first.result.filters["IEKF"].coefficients
    for a in flown.advice.advised:
        for f in candidate_flights(model, beta, a.candidate, 50.0, flown.advice.short_period_rad_s):
            assert in_envelope(model, f)


def test_an_estimate_that_does_not_hold_its_trim_says_so_and_what_to_fly() -> None:
    """A run that identified nothing can end on coefficients whose model does not hold its
    own trim (here the NOC UAV's with Cma's sign turned: statically unstable). No
    candidate can be predicted from them; the advice says that it is the estimate, not
    the manoeuvres, and names the manoeuvres that would identify it, where the true
    model's advice predicts each coefficient's sigma."""
    config = load_config("noc_uav")
    names = config.coefficient_names
    truth = np.array(config.truth, float)
    unstable = truth.copy()
    unstable[names.index("Cma")] = -truth[names.index("Cma")]
    cov = np.diag(np.full(len(names), 100.0))
    marks = [NOT_IDENTIFIED] * len(names)
    sigma, seen = config.filter.measurement_sigma, [True] * N_OBS
    lost = advise(config, unstable, cov, marks, sigma, seen)
    assert not lost.advised and not lost.predicted
    assert "does not hold its own trim" in lost.note and "doublets" in lost.note
    assert lost.lines()[0] == f"what to fly next: {lost.note}"
    assert lost.as_dict()["note"] == lost.note
    held = advise(config, truth, cov, marks, sigma, seen)
    assert not held.note and {a.name for a in held.advised} == set(names)


def _step_at(amplitude: float) -> list[str]:
    """The benchmark's overrides that add a throttle step of this amplitude at
    FLOWN_AT_S to the NOC flight."""
    config = load_config("noc_uav", NO_MULTISTEP)
    trim = simulate(config, seed=SEED).trim.inputs[1]
    c = Candidate("throttle step", amplitude, 6.0, config.airframe.trim_airspeed_mps)
    return manoeuvre_overrides(c, throttle_step(config, c, float(trim)))


def test_the_benchmark_flies_a_throttle_step_as_the_advice_does() -> None:
    """benchmarks/advice.py adds a throttle step as advice.candidate_flights flies it:
    the throttle up by the candidate's share of full throttle for its hold, then back to
    trim."""
    config = load_config("noc_uav", NO_MULTISTEP + _step_at(0.05))
    f = simulate(config, seed=SEED)
    throttle = f.inputs[:, 1]
    t = np.asarray(f.t_s)
    during = (t >= FLOWN_AT_S + 0.1) & (t < FLOWN_AT_S + 5.9)
    before, after = t < FLOWN_AT_S - 0.1, t > FLOWN_AT_S + 6.1
    trim = throttle[before].mean()
    assert np.ptp(throttle[before]) == 0.0
    assert throttle[during] == pytest.approx(trim + 0.05, abs=1e-3)
    assert throttle[after] == pytest.approx(trim, abs=1e-3)


def test_the_advised_multistep_flown_gives_the_sigma_predicted(flown: Flown) -> None:
    """Flying the advised multistep after the flight lowers every short-period
    coefficient's sigma, toward what the advice predicted (the factor is asserted over
    seeds by benchmarks/advice.py)."""
    before = flown.first.result.filters["IEKF"].sigma
    achieved = flown.after.result.filters["IEKF"].sigma
    predicted = flown.advice.predicted[flown.label]
    names = flown.advice.names
    for n in SHORT_PERIOD:
        i = names.index(n)
        ratio = achieved[i] / predicted[i]
        print(
            f"{n}: sigma {before[i]:.3g} -> achieved {achieved[i]:.3g}, predicted "
            f"{predicted[i]:.3g} (achieved / predicted {ratio:.2f})"
        )
        assert achieved[i] < before[i]
        assert predicted[i] < before[i]
        # Both fell: the one the better predicted fell further than the other by less
        # than what was gained.
        assert abs(achieved[i] - predicted[i]) < before[i] - min(achieved[i], predicted[i])


def test_theil_true_model_small_halved_cmq_misses_and_drops_the_mark(flown: Flown) -> None:
    """Validated on the window of its multistep, the true model predicts every judged
    channel (small Theil U); with Cmq halved the pitch channels' U grows severalfold,
    the check calls q missed, and Cmq's mark (identified by the run) drops to weak."""
    config = flown.after_config
    track = flown.after.result.filters["IEKF"].track
    assert track is not None
    rel = track.t - track.t[0]
    idx = np.flatnonzero((rel >= FLOWN_AT_S - 1.0) & (rel <= FLOWN_AT_S + 10.0))
    truth = np.array(config.truth, float)
    names = config.coefficient_names
    halved = truth.copy()
    halved[names.index("Cmq")] *= 0.5
    noise = np.asarray(flown.after.result.measurement_sigma, float)

    def held_out(beta: np.ndarray, label: str):  # type: ignore[no-untyped-def]
        return check(
            config,
            beta,
            np.zeros(0),
            track.t[idx],
            track.u[idx],
            track.y[idx],
            noise,
            "the multistep",
            label,
        )

    right, wrong = held_out(truth, "truth"), held_out(halved, "Cmq halved")
    u_right = {c.name: c for c in right.channels}
    u_wrong = {c.name: c for c in wrong.channels}
    assert not right.missed
    assert u_right["q"].judged and u_right["q"].theil < 0.1
    assert u_wrong["q"].theil > 3.0 * u_right["q"].theil
    assert u_wrong["qdot"].theil > 3.0 * u_right["qdot"].theil
    assert "q" in {c.name for c in wrong.missed}
    drops = wrong.drops(names, config.structure.axes)
    assert "Cmq" in drops
    missed = {c.name for c in wrong.missed}
    assert all(any(f"misses {m} " in why for m in missed) for why in drops.values())
    before = {c.name: c.identifiability for c in flown.after.summaries["IEKF"].coefficients}
    assert before["Cmq"] == IDENTIFIED
    from gcs_estimator.outputs.checks import _drop

    dropped, _ = _drop(flown.after, None, wrong)
    after = {c.name: c.identifiability for c in dropped.summaries["IEKF"].coefficients}
    assert after["Cmq"] == WEAK
    assert dropped.holdout_drops is not None
    assert dropped.holdout_drops["Cmq"].startswith("the model misses ")
    kept, _ = _drop(flown.after, None, right)
    assert {c.name: c.identifiability for c in kept.summaries["IEKF"].coefficients} == before


def test_checks_on_a_window_of_the_run(flown: Flown) -> None:
    """Checks (what the results sink runs) on a window of the run: the filter's own
    estimates predict it, nothing drops, and the advice is attached."""
    vehicle, refined = Checks(window=(FLOWN_AT_S - 1.0, FLOWN_AT_S + 10.0))(flown.after, None)
    assert refined is None
    assert vehicle.holdout is not None and vehicle.holdout.in_sample
    assert not vehicle.holdout_drops
    assert vehicle.advice is not None


def test_validate_on_the_command_line(tmp_path: Path) -> None:
    """`simulate --refine output-error --window 20:40 --validate 1:16`: the fit's
    estimates checked on the multisteps it was not fitted to (independent), in the
    table, the .md and the JSON's holdout, with the advice. The flight ends at 40 s:
    the 60 s one's last 20 s changed none of the check's figures (decision 0062)."""
    out = tmp_path / "run"
    argv = [
        "simulate", "--out", str(out), "--view", "off", "--set", "filter.structure_check=off",
        "--set", "simulation.manoeuvre.duration_s=40",
        "--refine", "output-error", "--window", "20:40", "--validate", "1:16",
    ]  # fmt: skip
    assert cli.main(argv) == 0
    data = json.loads((out / "results_sys1.json").read_text())
    holdout = data["holdout"]
    assert holdout["in_sample"] is False
    assert "output error" in holdout["coefficients_from"]
    channels = holdout["channels"]
    assert set(channels) == {"V", "alpha", "theta", "q", "qdot", "a_x", "a_z"}
    assert channels["q"]["judged"] and not channels["q"]["misses"]
    assert holdout["dropped"] == {}
    names = {a["name"] for a in data["advice"]["not_identified"]}
    marks = data["filters"]["IEKF"]["estimates"]
    assert names == {n for n, c in marks.items() if c["identifiability"] != IDENTIFIED}
    assert "held-out check" in (out / "results_sys1.md").read_text()


@pytest.mark.parametrize(
    ("value", "says"),
    [("60", "neither a file nor a window"), ("9:3", "neither a file nor a window")],
)
def test_validate_refuses_what_it_cannot_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str, says: str
) -> None:
    argv = ["simulate", "--out", str(tmp_path / "r"), "--view", "off", "--validate", value]
    assert cli.main(argv) == 2
    assert says in capsys.readouterr().err
