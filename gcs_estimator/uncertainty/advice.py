"""What to fly next: the coefficients a run has not identified, and the manoeuvre that
would, with the sigma each would reach (decision 0052).

Each candidate manoeuvre (an elevator doublet or 3-2-1-1 at a few amplitudes and unit
lengths scaled to the short period, throttle steps, a speed sweep) is flown through the
model at the current estimate from trim at the current airspeed, with the filters' own
compiled Runge-Kutta steps (estimation.filters.fast.fly) and observation model. The
outputs' sensitivities to the coefficients and to the initial flight state are central
differences; weighted by the run's measurement noise they are the candidate's Fisher
information, the initial state eliminated (its Schur complement: a fit of the
manoeuvre would estimate where it started). Added to the run's information (the inverse
of the filter's final coefficient covariance), it predicts each coefficient's sigma after
the manoeuvre.

The candidate is flown open loop with no process noise: the output-error (calm air)
information. In turbulence a fit learns less from the same manoeuvre, so the prediction
is then a lower bound. A candidate whose flight at the estimate leaves the envelope
about its trim (in_envelope: airspeed, pitch attitude, angle of attack) is not advised
(decision 0074): a manoeuvre a pilot flies to identify the aircraft stays near the trim
the coefficients describe, and a flight that loops or dives learns "much" only by
leaving the model's range.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from gcs_estimator.arrays import BoolArray, FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.filters.core import MAX_STEP_S, FilterKind
from gcs_estimator.estimation.filters.fast import fly
from gcs_estimator.estimation.results import EstimatorResult
from gcs_estimator.ingest.telemetry.channel_sources import MIN_RATE_HZ
from gcs_estimator.model import compiled  # noqa: F401  (registers the equations with numba)
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model, build_model, trim
from gcs_estimator.model.channels import N_FLIGHT, N_OBS, OBS_NAMES
from gcs_estimator.model.equations import ModelArrays, observe
from gcs_estimator.uncertainty.metrics import (
    ALPHA,
    IDENTIFIED,
    NOT_IDENTIFIED,
    WEAK,
    FilterSummary,
    correlation_of,
    identifiability,
    without_alpha,
)

AMPLITUDES_DEG = (1.0, 2.0, 4.0)
"""Elevator amplitudes of the multistep candidates [deg]."""
UNIT_SCALES = (0.7, 1.0, 1.4)
"""Unit step lengths of the multistep candidates, times the one tuned to the short period."""
DOUBLET_TUNING = 2.3
"""A doublet's unit step [s] is this over the short period's natural frequency [rad/s]:
its spectrum peaks there (Jategaonkar 2015, ch. 2; Morelli and Klein 2016, ch. 9)."""
MULTISTEP_TUNING = 1.6
"""A 3-2-1-1's unit step [s] is this over the short period's natural frequency [rad/s]."""
THROTTLE_STEPS = (0.05, 0.1, 0.2)
"""Throttle step candidates (share of full throttle; a thrust model: of the trim thrust)."""
THROTTLE_HOLD_S = 6.0
"""A throttle step holds this long, then returns to trim for as long."""
SWEEP_SPEEDS = (0.85, 1.0, 1.15)
"""A speed sweep's stabilised points, times the current airspeed."""
SWEEP_HOLD_S = 5.0
"""How long each of the sweep's points is held [s]."""
SETTLE_PERIODS = 3.0
"""A multistep's record runs on this many short periods after its last step."""
MIN_SETTLE_S = 2.0
SAMPLE_RATE_HZ = 50.0
"""The candidates' sample rate where the run gives none."""
PILOT_MIN_UNIT_S = 0.3
"""The shortest multistep unit step advised [s]: a step a pilot can fly by hand and
repeat (a stick held for less than about a third of a second is a pulse, not a step);
an aircraft whose short period wants shorter steps gets them at this length, and the
prediction is for the step as advised."""
MIN_SAMPLES_PER_STEP = 3
"""A unit step must span at least this many samples of the fastest channel the short
period shows in (theta, q, a_z, alpha), or no channel of the record sees its edges."""
ENVELOPE_SPEED = 0.15
"""A candidate's airspeed stays within this share of its trim airspeed (the speed
sweep's own points: SWEEP_SPEEDS)."""
ENVELOPE_PITCH_DEG = 15.0
"""Its pitch attitude within this of trim [deg]: a climb or descent a pilot holds by
hand, not a zoom or a loop."""
ENVELOPE_ALPHA_DEG = 5.0
"""Its angle of attack within this of trim [deg]: the range where the coefficients' terms,
linear in alpha, describe the aircraft (a 3-2-1-1 of a few degrees moves it two or
three)."""
FD_STEP = 1e-5
"""Central-difference step, relative to a parameter's magnitude (at least 1e-3)."""


@dataclass(frozen=True)
class Candidate:
    """One manoeuvre: an elevator doublet or 3-2-1-1 (amplitude in deg, unit step in s),
    a throttle step (amplitude a share of full throttle) or a speed sweep."""

    kind: str
    amplitude: float
    unit_s: float
    airspeed_mps: float

    def label(self) -> str:
        if self.kind in ("doublet", "3-2-1-1"):
            return (
                f"elevator {self.kind} ±{self.amplitude:g}°, unit {self.unit_s:.2f} s, "
                f"at {self.airspeed_mps:.0f} m/s"
            )
        if self.kind == "throttle step":
            return (
                f"throttle step +{100 * self.amplitude:.0f} % for {self.unit_s:g} s and back, "
                f"at {self.airspeed_mps:.0f} m/s"
            )
        lo, hi = SWEEP_SPEEDS[0] * self.airspeed_mps, SWEEP_SPEEDS[-1] * self.airspeed_mps
        return f"speed sweep {lo:.0f}-{hi:.0f} m/s, {self.unit_s:g} s steady at each"

    def as_dict(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "amplitude": self.amplitude,
            "amplitude_unit": "deg" if self.kind in ("doublet", "3-2-1-1") else "throttle",
            "unit_s": self.unit_s,
            "airspeed_mps": self.airspeed_mps,
            "label": self.label(),
        }


STEPS: dict[str, tuple[float, ...]] = {
    "doublet": (1.0, -1.0),
    "3-2-1-1": (1.0, 1.0, 1.0, -1.0, -1.0, 1.0, -1.0),
}
"""Each multistep's sign per unit step (the simulator's 3-2-1-1: +A 3, -A 2, +A 1, -A 1)."""


def elevator_offsets(kind: str, amplitude_rad: float, unit_s: float, t: FloatArray) -> FloatArray:
    """A multistep's elevator offset from trim at times t (from its start) [rad]."""
    signs = STEPS[kind]
    k = np.floor(t / unit_s).astype(np.int64)
    inside = (k >= 0) & (k < len(signs))
    out = np.zeros(t.shape[0])
    out[inside] = amplitude_rad * np.asarray(signs)[k[inside]]
    return out


@njit(cache=True, nogil=True)
def flown(
    x0: FloatArray, t: FloatArray, u: FloatArray, m: ModelArrays, max_step: float
) -> FloatArray:  # pragma: no cover
    """The model's outputs h(x) [N x 7] flown from x0 at t[0] through the inputs u
    (linear between samples), by the filters' own steps (fast.fly)."""
    N = t.shape[0]
    out = np.empty((N, N_OBS))
    x = x0.copy()
    for i in range(N):
        if i > 0:
            x = fly(x, u[i - 1], u[i], t[i] - t[i - 1], max_step, m)
        h, _ = observe(x, u[i], m)
        out[i] = h
    return out


@dataclass(frozen=True)
class Flight:
    """A candidate's record: the start state, times and inputs (the model's whole input
    rows, trim everywhere the manoeuvre does not move them)."""

    x0: FloatArray
    t: FloatArray
    u: FloatArray


def _trimmed(model: Model, beta: FloatArray, airspeed: float) -> tuple[FloatArray, FloatArray]:
    """The augmented state and the model's input row of level trim at `airspeed`."""
    tr = trim(model, beta, airspeed)
    x0 = model.augment(tr.state, beta)
    return x0, model.inputs(tr.inputs)


def short_period(model: Model, beta: FloatArray, airspeed: float) -> float:
    """The short period's natural frequency at trim [rad/s]: the fastest mode of the
    flight states' Jacobian (a complex pair, or the largest real root)."""
    x0, u0 = _trimmed(model, beta, airspeed)
    _, F = model.f(x0, u0)
    lam = np.linalg.eigvals(F[:N_FLIGHT, :N_FLIGHT])
    return float(np.max(np.abs(lam)))


def candidate_flights(
    model: Model, beta: FloatArray, c: Candidate, rate_hz: float, omega_sp: float
) -> list[Flight]:
    """The record(s) of candidate c: one for a multistep or a throttle step, one per
    stabilised point for a speed sweep."""
    dt = 1.0 / rate_hz
    if c.kind == "speed sweep":
        out = []
        for share in SWEEP_SPEEDS:
            x0, u0 = _trimmed(model, beta, share * c.airspeed_mps)
            t = np.arange(0.0, c.unit_s, dt)
            out.append(Flight(x0, t, np.tile(u0, (t.shape[0], 1))))
        return out
    x0, u0 = _trimmed(model, beta, c.airspeed_mps)
    if c.kind == "throttle step":
        t = np.arange(0.0, 2.0 * c.unit_s, dt)
        u = np.tile(u0, (t.shape[0], 1))
        propeller = eq.throttle_driven(model.k)
        step = c.amplitude if propeller else c.amplitude * abs(float(u0[1]))
        u[t < c.unit_s, 1] = min(u0[1] + step, 1.0) if propeller else u0[1] + step
        return [Flight(x0, t, u)]
    span = len(STEPS[c.kind]) * c.unit_s
    settle = max(SETTLE_PERIODS * 2.0 * math.pi / max(omega_sp, 1e-3), MIN_SETTLE_S)
    t = np.arange(0.0, span + settle, dt)
    u = np.tile(u0, (t.shape[0], 1))
    u[:, 0] += elevator_offsets(c.kind, math.radians(c.amplitude), c.unit_s, t)
    return [Flight(x0, t, u)]


def in_envelope(model: Model, f: Flight, max_step: float = MAX_STEP_S) -> bool:
    """Whether candidate flight f, flown at the estimate, stays within the envelope about
    its start (ENVELOPE_SPEED, ENVELOPE_PITCH_DEG, ENVELOPE_ALPHA_DEG; the model's own
    flight states, whatever the sensors)."""
    m = model.arrays
    x = f.x0.copy()
    V0, a0, th0 = float(x[0]), float(x[1]), float(x[2])
    alpha_band, pitch_band = math.radians(ENVELOPE_ALPHA_DEG), math.radians(ENVELOPE_PITCH_DEG)
    for i in range(1, f.t.shape[0]):
        x = fly(x, f.u[i - 1], f.u[i], float(f.t[i] - f.t[i - 1]), max_step, m)
        if not (
            np.all(np.isfinite(x[:N_FLIGHT]))
            and abs(x[0] - V0) <= ENVELOPE_SPEED * V0
            and abs(x[1] - a0) <= alpha_band
            and abs(x[2] - th0) <= pitch_band
        ):
            return False
    return True


def flight_information(
    model: Model, f: Flight, weights: FloatArray, max_step: float = MAX_STEP_S
) -> FloatArray | None:
    """The Fisher information [p x p] on the coefficients of one record: the outputs'
    sensitivities to [initial flight state, coefficients] by central differences,
    weighted by 1/sigma per channel (0: not observed), the initial state eliminated
    (Schur complement). None: the model left finite numbers."""
    params = np.concatenate([np.arange(N_FLIGHT), np.arange(model.n)[model.coefficients]])
    m = model.arrays
    t = np.ascontiguousarray(f.t)
    u = np.ascontiguousarray(f.u)
    J = np.empty((t.shape[0] * N_OBS, params.shape[0]))
    for col, j in enumerate(params):
        h = FD_STEP * max(abs(float(f.x0[j])), 1e-3)
        xp, xm = f.x0.copy(), f.x0.copy()
        xp[j] += h
        xm[j] -= h
        d = (flown(xp, t, u, m, max_step) - flown(xm, t, u, m, max_step)) / (2.0 * h)
        if not np.all(np.isfinite(d)):
            return None
        J[:, col] = (d * weights).ravel()
    M = J.T @ J
    k = N_FLIGHT
    S, B, C = M[:k, :k], M[:k, k:], M[k:, k:]
    out: FloatArray = C - B.T @ np.linalg.pinv(S) @ B
    return 0.5 * (out + out.T)


def candidates(
    airspeed: float, omega_sp: float, min_unit_s: float = PILOT_MIN_UNIT_S
) -> list[Candidate]:
    """Every candidate manoeuvre at `airspeed`, the multisteps' unit steps tuned to the
    short period's natural frequency omega_sp [rad/s], none shorter than min_unit_s."""
    out: list[Candidate] = []
    for kind, tuning in (("doublet", DOUBLET_TUNING), ("3-2-1-1", MULTISTEP_TUNING)):
        base = tuning / max(omega_sp, 1e-3)
        for scale in UNIT_SCALES:
            for amp in AMPLITUDES_DEG:
                c = Candidate(kind, amp, round(max(scale * base, min_unit_s), 2), airspeed)
                if c not in out:
                    out.append(c)
    out += [Candidate("throttle step", a, THROTTLE_HOLD_S, airspeed) for a in THROTTLE_STEPS]
    out.append(Candidate("speed sweep", 0.0, SWEEP_HOLD_S, airspeed))
    return out


@dataclass(frozen=True)
class Advised:
    """The best candidate for one coefficient not identified."""

    name: str
    sigma: float
    """The coefficient's sigma now (the filter's covariance)."""
    mark: str
    candidate: Candidate
    predicted_sigma: float
    """Its sigma predicted after the candidate."""
    predicted_mark: str
    """The mark predicted after it (identifiability)."""
    widen: float = 1.0
    """The sigma to trust over the covariance's now (movement, structure), which the
    prediction keeps: the table shows sigma * widen."""

    @property
    def trusted_sigma(self) -> float:
        """The sigma to trust now, as the table shows it."""
        return self.sigma * self.widen

    @property
    def predicted_trusted_sigma(self) -> float:
        """The sigma to trust predicted after the candidate."""
        return self.predicted_sigma * self.widen


@dataclass(frozen=True)
class Advice:
    """What to fly next (advise)."""

    names: tuple[str, ...]
    airspeed_mps: float
    short_period_rad_s: float
    advised: tuple[Advised, ...]
    """One per coefficient not identified, in the structure's order."""
    predicted: dict[str, FloatArray] = field(default_factory=dict)
    """Each candidate's label: every coefficient's predicted sigma."""
    note: str = ""
    """Why no advice could be made, where none could."""
    slow: tuple[tuple[str, float], ...] = ()
    """Channels the run sampled below the rate their motion needs (MIN_RATE_HZ), with
    their rate [Hz]: no manoeuvre makes up for them, a faster log or stream does."""

    def rates_line(self) -> list[str]:
        """A line on the channels sampled too slowly ([] when none was)."""
        if not self.slow:
            return []
        listed = ", ".join(f"{n} {r:.1f} Hz (needs {MIN_RATE_HZ[n]:g})" for n, r in self.slow)
        return [
            f"  first, faster data: {listed}; raise the telemetry stream rates or use the "
            "autopilot's onboard log (.bin, .ulg): the predictions below are at the rates "
            "this run had"
        ]

    def lines(self) -> list[str]:
        """The advice in words: a line per coefficient not identified."""
        if self.note:
            return [f"what to fly next: {self.note}", *self.rates_line()]
        if not self.advised:
            return ["what to fly next: nothing; every coefficient is identified"]
        head = (
            f"what to fly next (at {self.airspeed_mps:.1f} m/s; short period "
            f"{self.short_period_rad_s:.1f} rad/s; calm-air prediction):"
        )
        out = [head, *self.rates_line()]
        for a in self.advised:
            verdict = a.predicted_mark
            out.append(
                f"  {a.name} ({a.mark}, σ {a.trusted_sigma:.3g}): {a.candidate.label()} -> "
                f"σ {a.predicted_trusted_sigma:.3g} ({verdict})"
            )
        return out

    def as_dict(self) -> dict[str, object]:
        return {
            "airspeed_mps": self.airspeed_mps,
            "short_period_rad_s": self.short_period_rad_s,
            "note": self.note,
            "slow_channels_hz": dict(self.slow),
            "not_identified": [
                {
                    "name": a.name,
                    "mark": a.mark,
                    "sigma": a.trusted_sigma,
                    "sigma_covariance": a.sigma,
                    "manoeuvre": a.candidate.as_dict(),
                    "predicted_sigma": a.predicted_trusted_sigma,
                    "predicted_sigma_covariance": a.predicted_sigma,
                    "predicted_mark": a.predicted_mark,
                }
                for a in self.advised
            ],
            "candidates": {
                k: dict(zip(self.names, map(float, v), strict=True))
                for k, v in self.predicted.items()
            },
        }


def information_of(covariance: FloatArray) -> FloatArray:
    """The information a covariance holds (its pseudo-inverse, symmetric)."""
    info = np.linalg.pinv(0.5 * (covariance + covariance.T))
    out: FloatArray = 0.5 * (info + info.T)
    return out


def predict(
    model: Model,
    beta: FloatArray,
    info: FloatArray,
    c: Candidate,
    weights: FloatArray,
    rate_hz: float,
    omega_sp: float,
) -> FloatArray | None:
    """The coefficients' covariance after candidate c, from the information `info` now
    (None: the candidate left the envelope or the model's range)."""
    total = info.copy()
    for f in candidate_flights(model, beta, c, rate_hz, omega_sp):
        if not in_envelope(model, f):
            return None
        more = flight_information(model, f, weights)
        if more is None:
            return None
        total += more
    cov = np.linalg.pinv(total)
    out: FloatArray = 0.5 * (cov + cov.T)
    return out


RANK = {IDENTIFIED: 0, WEAK: 1, NOT_IDENTIFIED: 2}


def advise(
    config: AircraftConfig,
    beta: FloatArray,
    covariance: FloatArray,
    marks: Sequence[str],
    noise_sigma: Sequence[float],
    observed: Sequence[bool] | BoolArray,
    airspeed_mps: float | None = None,
    rate_hz: float = SAMPLE_RATE_HZ,
    trusted_sigma: Sequence[float] | None = None,
    channel_rates_hz: Sequence[float] | None = None,
) -> Advice:
    """What to fly next after a run that ended on coefficients beta with covariance
    `covariance` [p x p] and these marks, its channels observed (`observed` [7]) with
    noise sigma `noise_sigma` [7], at `airspeed_mps` (default: the trim airspeed), its
    samples at rate_hz. Every candidate is flown (module docstring); for each
    coefficient not identified, the one that leaves it the best mark (identifiability,
    of the predicted sigma widened as trusted_sigma widens the covariance's now, and the
    predicted correlations), then the smallest sigma. channel_rates_hz [N_OBS]: each
    channel's own sample rate where it is slower than rate_hz: a channel sampled at a
    quarter of the rate carries a quarter of the information (its noise taken twice as
    large), and the multisteps' unit steps span MIN_SAMPLES_PER_STEP of the fastest
    short-period channel's samples."""
    model = build_model(config, gust_states=False)
    beta = np.asarray(beta, float)
    names = config.coefficient_names
    V = float(config.airframe.trim_airspeed_mps if airspeed_mps is None else airspeed_mps)
    sd = np.asarray(noise_sigma, float)
    ok = np.asarray(observed, bool) & np.isfinite(sd) & (sd > 0)
    rates = (
        np.full(N_OBS, rate_hz)
        if channel_rates_hz is None
        else np.clip(np.nan_to_num(np.asarray(channel_rates_hz, float)), 1e-6, rate_hz)
    )
    sd = sd * np.sqrt(rate_hz / rates)
    weights = np.where(ok, 1.0 / np.where(ok, sd, 1.0), 0.0)
    min_unit = max(PILOT_MIN_UNIT_S, MIN_SAMPLES_PER_STEP / _fastest_short_period(rates, ok))
    slow = tuple(
        (n, float(r))
        for n, r, seen in zip(OBS_NAMES, rates, ok, strict=True)
        if seen and r < MIN_RATE_HZ.get(n, 0.0)
    )
    try:
        omega = short_period(model, beta, V)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return Advice(names, V, math.nan, (), note=f"no trim at {V:.1f} m/s ({exc})", slow=slow)
    covariance = np.asarray(covariance, float)
    now = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    # The sigma the marks read is the covariance's widened (movement, structure): the
    # prediction keeps each coefficient's widening.
    widen = (
        np.ones_like(now)
        if trusted_sigma is None
        else np.maximum(np.asarray(trusted_sigma, float) / np.maximum(now, 1e-300), 1.0)
    )
    info = information_of(covariance)
    predicted: dict[str, FloatArray] = {}
    marks_after: dict[str, tuple[str, ...]] = {}
    by: dict[str, Candidate] = {}
    for c in candidates(V, omega, min_unit):
        cov = predict(model, beta, info, c, weights, rate_hz, omega)
        if cov is None:
            continue
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        predicted[c.label()] = sd
        after = identifiability(beta, sd * widen, correlation_of(cov))
        # No alpha at all: no manoeuvre fixes what only alpha tells (metrics.without_alpha).
        marks_after[c.label()] = after if ok[ALPHA] else without_alpha(names, after)
        by[c.label()] = c
    if not predicted:
        return Advice(names, V, omega, (), note=_none_flown(model, beta, V, rate_hz), slow=slow)
    advised = []
    for i, (name, mark) in enumerate(zip(names, marks, strict=True)):
        if mark == IDENTIFIED:
            continue
        best = min(predicted, key=lambda k: (RANK[marks_after[k][i]], float(predicted[k][i])))
        advised.append(
            Advised(
                name,
                float(now[i]),
                mark,
                by[best],
                float(predicted[best][i]),
                marks_after[best][i],
                float(widen[i]),
            )
        )
    return Advice(names, V, omega, tuple(advised), predicted, slow=slow)


UNFORCED_S = 2.0 * THROTTLE_HOLD_S
"""How long the model at the estimate is flown from trim with no input to tell whether it
holds its trim: as long as the longest candidate."""
UPSET_ALPHA_DEG = 0.5
"""The angle of attack it starts that far off trim: at exact trim even an unstable model
stays put."""


def _none_flown(model: Model, beta: FloatArray, airspeed: float, rate_hz: float) -> str:
    """Why no candidate was predicted: the model at the estimate does not hold its own
    trim (flown with no input from UPSET_ALPHA_DEG off it, it leaves the envelope: its
    coefficients, not the manoeuvres, are the trouble), or every candidate left the
    envelope."""
    x0, u0 = _trimmed(model, beta, airspeed)
    x0[1] += math.radians(UPSET_ALPHA_DEG)
    t = np.arange(0.0, UNFORCED_S, 1.0 / rate_hz)
    if in_envelope(model, Flight(x0, t, np.tile(u0, (t.shape[0], 1)))):
        return "every candidate left the envelope about trim or the model's range"
    return (
        f"the model at the current estimate does not hold its own trim at {airspeed:.0f} "
        f"m/s (flown with no input it leaves the envelope within {UNFORCED_S:g} s): its "
        "coefficients are too uncertain to predict a manoeuvre from; fly elevator doublets "
        "and 3-2-1-1s of a few degrees and throttle steps on wings-level legs, then run "
        "again, and the advice will predict from what they identify"
    )


SHORT_PERIOD_CHANNELS = ("alpha", "theta", "q", "a_z")
"""The channels the short period shows in, whose fastest sets the shortest unit step."""


def _fastest_short_period(rates: FloatArray, observed: BoolArray) -> float:
    """The fastest observed short-period channel's rate [Hz] (inf: none observed)."""
    picked = [
        float(r)
        for n, r, o in zip(OBS_NAMES, rates, observed, strict=True)
        if o and n in SHORT_PERIOD_CHANNELS
    ]
    return max(picked) if picked else math.inf


FLYING_SHARE = 0.5
"""Flight: an airspeed of at least this share of the trim airspeed (not the landing roll)."""


def advice_of(
    result: EstimatorResult, summary: FilterSummary | None, kind: FilterKind = "IEKF"
) -> Advice | None:
    """What to fly next after a finished run, from filter `kind`'s final estimate and
    covariance, its marks and sigma to trust (summary), the channels the record observed
    at the run's measurement noise, its sample rate and the median airspeed of its flight
    (FLYING_SHARE: not the take-off or landing; the airspeed the next flight will fly;
    the live view takes the latest instead). None: the run kept no history, has no such
    filter, or observed no channel at all."""
    fr = result.filters.get(kind)
    if fr is None or fr.track is None or len(fr.track.t) < 2 or summary is None:
        return None
    t, y = np.asarray(fr.track.t), np.asarray(fr.track.y)
    observed: BoolArray = np.asarray(np.isfinite(y).any(axis=0), dtype=bool)
    if not observed.any():  # nothing measured: no manoeuvre's information to predict
        return None
    flying = np.isfinite(y[:, 0]) & (
        y[:, 0] >= FLYING_SHARE * result.config.airframe.trim_airspeed_mps
    )
    recent = y[flying, 0]
    airspeed = float(np.median(recent)) if recent.size else None  # the flight's usual airspeed
    steps = np.diff(t)
    steps = steps[steps > 0]
    rate = 1.0 / float(np.median(steps)) if steps.size else SAMPLE_RATE_HZ
    # Each channel's rate: the frame rate times the share of frames that carry it.
    channel_rates = rate * np.isfinite(y).mean(axis=0) if len(y) else None
    noise = result.measurement_sigma or result.config.filter.measurement_sigma
    return advise(
        result.config,
        fr.coefficients,
        fr.covariance,
        [c.identifiability for c in summary.coefficients],
        noise,
        observed,
        airspeed,
        rate,
        [c.sigma for c in summary.coefficients],
        channel_rates,
    )


def live_advice(
    config: AircraftConfig, coefficients: FloatArray, sigma: FloatArray, airspeed_mps: float
) -> Advice:
    """What to fly next while flying, from a filter's current estimate and sigma alone
    (the live snapshot has no correlations: the covariance taken diagonal, the marks
    from the sigma), every channel observed at the config's measurement noise."""
    beta = np.asarray(coefficients, float)
    sd = np.asarray(sigma, float)
    marks = identifiability(beta, sd, np.eye(sd.shape[0]))
    return advise(
        config,
        beta,
        np.diag(sd * sd),
        marks,
        config.filter.measurement_sigma,
        [True] * N_OBS,
        airspeed_mps if math.isfinite(airspeed_mps) else None,
    )
