"""What a user should know before trusting a run's numbers (trust_warnings): a noise
model that does not fit, channels the filters' model misses, turbulence switched on and
off, estimates that moved more than their covariance allows, coefficients the data do
not identify or the two filters end apart on, signs no conventional aircraft has, and
what points at the setup (a channel never held, an elevator that never moved)."""

from __future__ import annotations

import json
import math
import shlex
from typing import TYPE_CHECKING, Any

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import ProcessNoise
from gcs_estimator.estimation.filters.core import FILTER_KINDS, FilterKind
from gcs_estimator.estimation.noise import CLEARLY, reading_z
from gcs_estimator.estimation.results import EstimatorResult
from gcs_estimator.model.channels import FLIGHT_STATES, OBS_NAMES
from gcs_estimator.outputs.text import fmt
from gcs_estimator.refine.result import FACTOR_TOLD
from gcs_estimator.uncertainty.metrics import IDENTIFIED, NOT_IDENTIFIED, FilterSummary
from gcs_estimator.uncertainty.result import VehicleResult
from gcs_estimator.uncertainty.sigma import DELAY_WARNING_SIGMA
from gcs_estimator.uncertainty.weighting import THRUST_PARTS

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined


NIS_RATIO_LIMIT = 3.0
"""Mean NIS this many times the channel count (or a third of it): the noise model is off."""
CHANNEL_NIS_LIMIT = 2.0
"""A channel's mean squared innovation this many times what the filter predicts (or less
than its inverse): that channel says the filter's model or its noise settings are off
there, where the whole NIS, averaged over the channels, may not."""
INFLATION_LIMIT = 2.0
"""A sigma to trust above this multiple of the covariance's (SigmaParts.inflation):
worth a warning."""
GUST_BURSTS = (0.02, 0.9)
"""A turbulence level applied in more than the first and less than the second share of
the final pass: on and off. Calm simulated flights stay below 1 %, turbulent ones at 100 %;
model misfit during manoeuvres reads as bursts (docs/decisions/0004)."""
COLOUR_LIMIT = 5.0
"""Residual colour above this on a channel: the model misses something the data hold."""
DISAGREE_SIGMAS = 3.0
"""The EKF and the IEKF ending further apart on a coefficient than this many of the larger
of their sigmas: the data do not settle it (both filters read the same frames, so
their estimates differ by far less than either sigma where the data fix a value)."""
PROCESS_NOISE_RATIO = 10.0
"""A flight state's process noise density the filter-error fit finds at least this many
times the configured one, where the filters' innovations are larger than they predict:
the model misses that much, and the density is advised (docs/decisions/0085) where the
fit's residuals are white (none above COLOUR_LIMIT: decision 0087)."""
FITTED_NOISE_RATIO = math.sqrt(CHANNEL_NIS_LIMIT)
"""A channel's measurement sigma the filter-error fit finds at least this many times the
one the filters used (a variance CHANNEL_NIS_LIMIT times theirs), where that channel's
innovations are larger than they predict: advised with the fit's process noise, where its
residuals are white (docs/decisions/0089)."""
ADVICE_HEAD = "to run again as these warnings advise:"


def trust_warnings(vehicle: VehicleResult, refined: Refined | None = None) -> list[str]:
    """What a user should know before trusting the numbers: a noise model that does not
    fit (NIS far from the channel count), a warm start that fitted few frames, a
    turbulence level switched on and off or one the whole pass found and the running
    level missed, coefficients the data do not identify, a filter
    that diverged and started again, residuals far from white in the whole-record
    fit, and what points at the setup: a channel the data never hold, an elevator that
    never moves, a coefficient of the sign no conventional aircraft has."""
    out: list[str] = []
    result = vehicle.result
    for kind, s in vehicle.summaries.items():
        if s.mean_channels > 0 and math.isfinite(s.mean_nis):
            ratio = s.mean_nis / s.mean_channels
            if ratio > NIS_RATIO_LIMIT or ratio < 1.0 / NIS_RATIO_LIMIT:
                out.append(
                    f"{kind}: mean NIS {s.mean_nis:.1f} over {s.mean_channels:.1f} channels: "
                    "the noise model does not fit these data, so its sigmas do not either "
                    "(check [filter.measurement_sigma] against the sensors)"
                )
        out += _channel_warnings(kind, s)
        threshold = result.config.filter.turbulence.detection_sigma
        if s.gust_pass_z >= threshold and s.gust_on_share < GUST_BURSTS[1]:
            out.append(
                f"{kind}: turbulence over the whole pass (σ_w {s.gust_pass_sigma:.2f} m/s, "
                f"{s.gust_pass_z:.1f} standard errors above zero) while a turbulence level "
                f"was applied in only {100 * s.gust_on_share:.0f} % of it: gusts too weak or "
                "too slow (a long scale length) for a few seconds of data to tell from "
                "calm; where none was applied the covariance's σ assumes calm air (the σ shown "
                "is widened where the estimates moved more than it allows); `refine` "
                "(auto) fits such a record by filter error"
            )
        elif GUST_BURSTS[0] < s.gust_on_share < GUST_BURSTS[1]:
            out.append(
                f"{kind}: the turbulence level was applied on and off, in "
                f"{100 * s.gust_on_share:.0f} % of the frames since the last restart: "
                "turbulence near the detection limit, or what the model misses during the "
                "manoeuvres read as turbulence (its process noise then discounts the most "
                "informative seconds); if the air was calm, compare a run with "
                "[filter.turbulence] adaptive = false"
            )
        moved = _moved(vehicle, kind, s)
        if moved:
            out.append(
                f"{kind}: estimates moved more than the covariance allows, over the run or "
                "with the channels weighted otherwise ("
                + ", ".join(moved)
                + "): the model misses something in these data (unmodelled aerodynamics, "
                "turbulence, sensor errors); the σ shown is the covariance's widened that much: "
                "trust it, not the covariance's"
            )
        weak = [c.name for c in s.coefficients if c.identifiability == NOT_IDENTIFIED]
        if weak:
            out.append(f"{kind}: not identified by these data: {', '.join(weak)}")
        out += _sign_warnings(kind, s)
    out += _disagreement_warning(vehicle)
    out += thrust_warnings(vehicle)
    out += hold_warnings(vehicle)
    out += _noise_warning(vehicle)
    out += _contradicted_warning(vehicle)
    out += _compatibility_warning(vehicle)
    out += _run_warnings(result)
    if refined is not None:
        out += _refined_warnings(refined)
    out += _process_noise_warning(vehicle, refined)
    out += _fitted_noise_warning(vehicle, refined)
    advised = advised_settings(vehicle, refined)
    if advised:
        out.append(f"{ADVICE_HEAD} {set_arguments(advised)}")
    return out


def advised_settings(vehicle: VehicleResult, refined: Refined | None = None) -> dict[str, Any]:
    """The settings the warnings advise, as `--set` keys and their values: the sensor
    biases the compatibility check finds and the filters do not estimate, each channel's
    sigma where the data read it clearly noisier than configured, the process noise the
    filter-error fit finds where the filters' innovations are larger than they predict
    and the measurement sigma it finds with it (where its residuals are white), and the
    input delay the fit finds where one value fits every input; with measurement_noise =
    "auto", "config" where a reading the innovations contradict or a fitted sigma would
    otherwise be read below again (_readings_held, decision 0091). Empty: nothing to
    change. A run with them applied advises none of them again (decision 0085). Not
    advised: a channel's sigma where its innovations are as large as the filters predict
    (the roughness read is motion they carry), nor a bias the compatibility check's
    velocity stage finds in moving air (decision 0088)."""
    out: dict[str, Any] = {}
    told = list(vehicle.result.config.sensors.bias_states)
    missing = _missing_biases(vehicle)
    if missing:
        out["sensors.bias_states"] = [*told, *missing]
    high = _channels_high(vehicle)
    for name, sigma in _noisier_channels(vehicle):
        if name in high:
            out[f"filter.measurement_sigma.{name}"] = float(f"{sigma:.4g}")
    fitted: list[tuple[str, float]] = []
    if refined is not None and residuals_white(refined):
        out |= process_noise_settings(vehicle, refined)
        fitted = fitted_noise(vehicle, refined)
        for name, sigma in fitted:
            key = f"filter.measurement_sigma.{name}"
            out[key] = max(out.get(key, 0.0), float(f"{sigma:.4g}"))
    if vehicle.result.config.filter.measurement_noise == "auto" and (
        fitted or contradicted_readings(vehicle)
    ):
        out |= _readings_held(vehicle, out)
    delay = _delay_advised(refined)
    if delay is not None:
        out["data.input_delay_s"] = float(f"{delay:.3f}")
    return out


def _taken_readings(vehicle: VehicleResult) -> list[tuple[str, float, float]]:
    """The channels whose final pass took the data's reading of their noise
    (measurement_noise = "auto": clearly below the configured sigma), with the sigma
    used and the configured one."""
    result = vehicle.result
    if result.noise_reading is None or not result.measurement_sigma:
        return []
    configured = result.config.filter.measurement_sigma
    return [
        (n, float(u), float(c))
        for n, u, c, read in zip(
            OBS_NAMES, result.measurement_sigma, configured, result.noise_reading.sigma, strict=True
        )
        if u < c and math.isclose(u, read, rel_tol=1e-9)
    ]


def contradicted_readings(vehicle: VehicleResult) -> list[tuple[str, float, float]]:
    """The taken readings (_taken_readings) whose channel's innovations some filter finds
    CHANNEL_NIS_LIMIT times larger than it predicts: samples that change less from one
    to the next than their error does, as an autopilot's filtered airspeed does (decision
    0091). The reading takes only the noise that is white at the sample rate."""
    high = _channels_high(vehicle)
    return [r for r in _taken_readings(vehicle) if r[0] in high]


def _readings_held(vehicle: VehicleResult, advised: dict[str, Any]) -> dict[str, Any]:
    """What keeps a measurement sigma where the advice puts it: with "auto" the next run
    would take a reading clearly below it again (a contradicted reading, or a fitted
    sigma on a channel whose samples read smooth). So measurement_noise = "config", each
    reading that held (its innovations as the filters predict) kept as its channel's
    sigma, and a contradicted channel at its configured sigma unless advised otherwise."""
    out: dict[str, Any] = {"filter.measurement_noise": "config"}
    wrong = {n for n, _, _ in contradicted_readings(vehicle)}
    for name, used, _ in _taken_readings(vehicle):
        key = f"filter.measurement_sigma.{name}"
        if name not in wrong and key not in advised:
            out[key] = float(f"{used:.4g}")
    return out


def _contradicted_warning(vehicle: VehicleResult) -> list[str]:
    """The readings the innovations contradict (contradicted_readings), and the advice."""
    found = contradicted_readings(vehicle)
    if not found:
        return []
    named = ", ".join(f"{n} {u:.3g} (configured {c:.3g})" for n, u, c in found)
    return [
        f"the noise read from the samples was taken below the configured σ on {named}, "
        "and those channels' innovations are larger than the filters predict: their "
        "samples are smoother than their error (an autopilot's filtered channel, or one "
        'held between samples); advised: measurement_noise = "config", the configured σ '
        "there and the other readings kept (docs/decisions/0091)"
    ]


def set_argv(settings: dict[str, Any]) -> list[str]:
    """The settings as command-line arguments, `--set KEY=VALUE` each (lists and strings
    as JSON, which TOML reads too; numbers as they are)."""
    argv = []
    for key, value in settings.items():
        text = json.dumps(value) if isinstance(value, list | str) else f"{value:g}"
        argv += ["--set", f"{key}={text}"]
    return argv


def set_arguments(settings: dict[str, Any]) -> str:
    """set_argv as a shell takes it."""
    return " ".join(shlex.quote(a) for a in set_argv(settings))


def _channels_high(vehicle: VehicleResult) -> set[str]:
    """The channels whose innovations some filter finds CHANNEL_NIS_LIMIT times larger
    than it predicts (_channel_warnings)."""
    return {
        n
        for s in vehicle.summaries.values()
        for n, v in zip(OBS_NAMES, s.channel_nis, strict=True)
        if math.isfinite(v) and v > CHANNEL_NIS_LIMIT
    }


def air_moved(vehicle: VehicleResult) -> bool:
    """Whether some filter found the air moving over its final pass: a turbulence level
    applied in more than GUST_BURSTS[0] of it, or found over the whole pass."""
    threshold = vehicle.result.config.filter.turbulence.detection_sigma
    return any(
        s.gust_on_share > GUST_BURSTS[0] or s.gust_pass_z >= threshold
        for s in vehicle.summaries.values()
    )


def _innovations_high(vehicle: VehicleResult) -> bool:
    """Whether some channel's innovations are CHANNEL_NIS_LIMIT times larger than a
    filter predicts (_channel_warnings)."""
    return bool(_channels_high(vehicle))


def residuals_white(refined: Refined) -> bool:
    """Whether the fit's residuals are white on every channel (colour at most
    COLOUR_LIMIT): what the fit leaves is random, as process noise is. Coloured
    residuals are a systematic miss of the model; process noise set for it brings the
    filters' NIS in line but not their coefficients' sigma, which then falls short of
    their error (the JSBSim mission set, decision 0087)."""
    colour = np.asarray(refined.residual_colour, float)
    colour = colour[np.isfinite(colour)]
    return bool(colour.size) and float(colour.max()) <= COLOUR_LIMIT


def process_noise_settings(vehicle: VehicleResult, refined: Refined | None) -> dict[str, float]:
    """The process noise densities the filter-error fit finds (_process_noise_found) as
    `--set` keys, whether or not they are advised (residuals_white)."""
    return {
        f"filter.process_noise.{name}": float(f"{density:.4g}")
        for name, density in _process_noise_found(vehicle, refined)
    }


def _process_noise_found(
    vehicle: VehicleResult, refined: Refined | None
) -> list[tuple[str, float]]:
    """The flight states whose process noise density the filter-error fit finds at least
    PROCESS_NOISE_RATIO times the configured one, with that density, where the filters'
    innovations are larger than they predict (none otherwise)."""
    if refined is None or refined.label != "FE" or not _innovations_high(vehicle):
        return []
    configured = vehicle.result.config.filter.process_noise.states
    return [
        (name, float(found))
        for name, found, told in zip(FLIGHT_STATES, refined.process_noise, configured, strict=True)
        if math.isfinite(found) and found >= PROCESS_NOISE_RATIO * told and found > 0.0
    ]


def _process_noise_warning(vehicle: VehicleResult, refined: Refined | None) -> list[str]:
    """Where the filters' innovations are larger than they predict: the process noise the
    filter-error fit finds (the model's misses as the motion they leave between samples),
    or, without that fit and with the process noise as shipped, the command that finds
    it."""
    if not _innovations_high(vehicle):
        return []
    found = _process_noise_found(vehicle, refined)
    if found:
        configured = dict(
            zip(FLIGHT_STATES, vehicle.result.config.filter.process_noise.states, strict=True)
        )
        named = ", ".join(f"{n} {v:.3g} (configured {configured[n]:.3g})" for n, v in found)
        head = (
            "FE finds the flight states driven beyond the model, as process noise "
            f"densities per second: {named}: the motion the "
            "model misses between samples (aerodynamics the structure lacks, the turns' "
            "coupling, turbulence, a thrust the throttle does not give)"
        )
        assert refined is not None  # found only from a fit
        if residuals_white(refined):
            return [
                f"{head}; the filters set so ([filter.process_noise]) count on it, and their "
                "covariance and NIS fit the data"
            ]
        colour = np.asarray(refined.residual_colour, float)
        worst = int(np.nanargmax(colour))
        return [
            f"{head}; but the fit's residuals are coloured ({OBS_NAMES[worst]} "
            f"{colour[worst]:.0f} times white): a systematic miss, not random motion, so it "
            "is not advised: set so, the filters' NIS fits the data while their "
            "coefficients' σ falls short of their error (docs/decisions/0087); this run's "
            "σ, widened by its checks, is the one to trust"
        ]
    if refine_advised(vehicle, refined) is None:
        return []  # the fit found no more than configured, or the user set it already
    return [
        "a whole-record fit by filter error (`--refine filter-error`) finds the process "
        "noise that carries what the filters' model misses and whether that miss is "
        "random; where it is, it names the [filter.process_noise] densities that would let "
        "their covariance count on it"
    ]


def fitted_noise(vehicle: VehicleResult, refined: Refined | None) -> list[tuple[str, float]]:
    """The channels whose innovations are larger than the filters predict where the
    filter-error fit finds their measurement sigma FITTED_NOISE_RATIO times the one the
    filters used, with the sigma it finds. The fit estimates the measurement noise and the
    process noise together: its densities are what the flight states need beside that
    noise, not beside the filters' smaller one."""
    if refined is None or refined.label != "FE":
        return []
    high = _channels_high(vehicle)
    sigmas = _sigma_told(vehicle)
    return [
        (name, float(found))
        for name, found, told in zip(OBS_NAMES, refined.noise_sigma, sigmas, strict=True)
        if name in high and math.isfinite(found) and found >= FITTED_NOISE_RATIO * told
    ]


def _sigma_told(vehicle: VehicleResult) -> FloatArray:
    """Each channel's measurement sigma the filters were told: the larger of the one the
    final pass used (the data's reading, where "auto" took it) and the configured one,
    so that a sigma already set as advised is not advised again."""
    config = vehicle.result.config.filter.measurement_sigma
    used = vehicle.result.measurement_sigma or config
    told: FloatArray = np.maximum(np.asarray(used, float), np.asarray(config, float))
    return told


def _fitted_noise_warning(vehicle: VehicleResult, refined: Refined | None) -> list[str]:
    """The measurement noise the filter-error fit finds above the filters' on the channels
    whose innovations are larger than they predict (fitted_noise), and whether it is
    advised (with the fit's process noise, where its residuals are white)."""
    found = fitted_noise(vehicle, refined)
    if not found:
        return []
    assert refined is not None  # found only from a fit
    told = dict(zip(OBS_NAMES, _sigma_told(vehicle), strict=True))
    named = ", ".join(f"{n} {v:.3g} (the filters were told {told[n]:.3g})" for n, v in found)
    head = (
        f"FE finds the measurement noise larger than the filters took it, as σ: {named}: "
        "what the model cannot follow from one sample to the next on these channels"
    )
    if residuals_white(refined):
        return [
            f"{head}; set so ([filter.measurement_sigma]), the filters take the noise the fit "
            "found beside its process noise (docs/decisions/0089)"
        ]
    return [f"{head}; not advised, as the fit's process noise is not (residuals coloured)"]


def refine_advised(vehicle: VehicleResult, refined: Refined | None = None) -> str | None:
    """The whole-record fit the warnings advise (`--refine METHOD`), or None: filter error
    where some channel's innovations are larger than the filters predict, the run had no
    filter-error fit and the process noise is as shipped (_process_noise_warning)."""
    if not _innovations_high(vehicle) or _process_noise_found(vehicle, refined):
        return None
    told = vehicle.result.config.filter.process_noise.states
    if (refined is not None and refined.label == "FE") or told != ProcessNoise().states:
        return None
    return "filter-error"


def _delay_advised(refined: Refined | None) -> float | None:
    """The input delay [s] the fit's delay warning advises, where one value fits every
    input whose delay it saw (within DELAY_WARNING_SIGMA of their sigma); None where no
    input is late or early, or where they disagree."""
    if refined is None:
        return None
    seen = [
        (float(d), float(sd))
        for d, sd in zip(refined.delays_s, refined.delay_sigma_s, strict=True)
        if math.isfinite(sd) and sd > 0.0
    ]
    late = [
        (d, sd) for d, sd in seen if abs(d - refined.configured_delay_s) > DELAY_WARNING_SIGMA * sd
    ]
    if not late:
        return None
    value = max(min(late, key=lambda p: p[1])[0], 0.0)
    if all(abs(d - value) <= DELAY_WARNING_SIGMA * sd for d, sd in seen):
        return value
    return None


def _channel_warnings(kind: str, s: FilterSummary) -> list[str]:
    """The channels whose innovations over the final pass are far larger, or far smaller,
    than the filter predicts (FilterSummary.channel_nis)."""
    pairs = [(n, v) for n, v in zip(OBS_NAMES, s.channel_nis, strict=True) if math.isfinite(v)]
    high = [f"{n} {v:.1f}" for n, v in pairs if v > CHANNEL_NIS_LIMIT]
    low = [f"{n} {v:.2f}" for n, v in pairs if v < 1.0 / CHANNEL_NIS_LIMIT]
    out = []
    if high:
        out.append(
            f"{kind}: innovations larger than the filter predicts on "
            + ", ".join(high)
            + " (their mean square over the predicted σ², 1 expected): the model or the "
            "noise settings miss something these channels show (aerodynamics the "
            "structure lacks, turbulence, a sensor noisier or placed otherwise than the "
            "airframe file says), and the filter counts on them more than it should: "
            "trust the σ shown, not the covariance's"
        )
    if low:
        out.append(
            f"{kind}: innovations smaller than the filter predicts on "
            + ", ".join(low)
            + ": their [filter.measurement_sigma] is larger than these data show, so the "
            "filters use them less than they could"
        )
    return out


def _disagreement_warning(vehicle: VehicleResult) -> list[str]:
    """The coefficients on which the two filters end more than DISAGREE_SIGMAS apart.

    Both read the same frames, so where the data fix a coefficient they end close
    together. Where they leave a ridge (coefficients whose combination alone the flight
    fixes: CLq and CLadot, say), the IEKF's relinearisation can follow it far from where
    the EKF stays, while each filter's covariance, taken at its own point, still calls the
    coefficient identified. Not-identified coefficients are left out: the table says so
    already."""
    summaries = [vehicle.summaries[k] for k in FILTER_KINDS if k in vehicle.summaries]
    if len(summaries) < 2:
        return []
    a, b = summaries[0], summaries[1]
    apart = []
    for ca, cb in zip(a.coefficients, b.coefficients, strict=True):
        if NOT_IDENTIFIED in (ca.identifiability, cb.identifiability):
            continue
        sigma = max(ca.sigma, cb.sigma)
        if abs(ca.estimate - cb.estimate) > DISAGREE_SIGMAS * sigma:
            apart.append(f"{ca.name} {fmt(ca.estimate)} against {fmt(cb.estimate)}")
    if not apart:
        return []
    return [
        f"the {a.kind} and the {b.kind} end more than {DISAGREE_SIGMAS:g} σ apart on "
        + ", ".join(apart)
        + ": the data do not settle these coefficients (a ridge of the fit, or one filter "
        "led off by a bad stretch of data), whatever their σ say; compare `refine` and a "
        "run with fewer coefficients"
    ]


def _noise_warning(vehicle: VehicleResult) -> list[str]:
    """What the measurement noise read from the data says (docs/decisions/0014): which
    channels read clearly noisier than configured (kept at the configured sigma)."""
    configured = dict(zip(OBS_NAMES, vehicle.result.config.filter.measurement_sigma, strict=True))
    noisier = _noisier_channels(vehicle)
    above = [f"{n} {r / configured[n]:.1f}×" for n, r in noisier]
    if not above:
        return []
    high = _channels_high(vehicle)
    fitting = [n for n, _ in noisier if n not in high]
    return [
        "the data read noisier than the configured σ on "
        + ", ".join(above)
        + " (the configured σ was kept): noisier sensors than configured, or motion "
        "as rough as noise (gusts of a short scale length, which the filters' process "
        "noise carries); if the sensors are that noisy, set [filter.measurement_sigma] "
        "for them"
        + (
            f"; not advised on {', '.join(fitting)}, whose innovations are as large as the "
            "filters predict: the roughness is motion they carry (decision 0088)"
            if fitting
            else ""
        )
    ]


ESTIMABLE_BIASES: dict[tuple[str, str], str] = {
    ("q", "bias"): "q",
    ("a_x", "bias"): "a_x",
    ("a_z", "bias"): "a_z",
    ("alpha", "bias"): "alpha",
}
"""The compatibility check's findings the filters can estimate with the coefficients
([sensors] bias_states), by the channel they name there."""


def _noisier_channels(vehicle: VehicleResult) -> list[tuple[str, float]]:
    """The channels the data read clearly noisier than configured (reading_z above
    CLEARLY), with the sigma read."""
    result = vehicle.result
    if result.noise_reading is None:
        return []
    configured = np.array(result.config.filter.measurement_sigma, float)
    reading = np.array(result.noise_reading.sigma)
    z = reading_z(reading, np.array(result.noise_reading.differences), configured)
    return [(n, float(r)) for n, r, zc in zip(OBS_NAMES, reading, z, strict=True) if zc > CLEARLY]


VELOCITY_STAGE = frozenset({"airspeed", "alpha", "vz", "vn", "ve", "vd", "a_x", "a_z"})
"""The channels whose findings the compatibility check's velocity stage makes
(ingest/compat.py). It takes the air-relative velocity as the integrated accelerations
less a steady wind; gusts move it otherwise, and the stage reads them as these channels'
errors (on the simulator in light turbulence, with sensors that have none, an alpha bias
of many degrees far beyond its sigma: tests/test_sensors.py, decision 0088)."""


def _gust_findings(vehicle: VehicleResult) -> list[dict[str, Any]]:
    """The significant findings that may be the gusts (VELOCITY_STAGE in moving air)."""
    found = vehicle.compatibility
    if not found or not air_moved(vehicle):
        return []
    return [f for f in found["findings"] if f["significant"] and f["channel"] in VELOCITY_STAGE]


def _missing_biases(vehicle: VehicleResult) -> list[str]:
    """The bias states the compatibility check's significant findings name that the
    filters do not estimate ([sensors] bias_states), but for those that may be the gusts
    (_gust_findings)."""
    found = vehicle.compatibility
    if not found:
        return []
    told = set(vehicle.result.config.sensors.bias_states)
    gusts = _gust_findings(vehicle)
    return sorted(
        {
            ESTIMABLE_BIASES[(f["channel"], f["kind"])]
            for f in found["findings"]
            if f["significant"] and (f["channel"], f["kind"]) in ESTIMABLE_BIASES and f not in gusts
        }
        - told
    )


def _compatibility_warning(vehicle: VehicleResult) -> list[str]:
    """What the data compatibility check of a link's frames found beyond the noise
    (VehicleResult.compatibility; docs/decisions/0084), with the setting that carries
    each bias the filters can estimate and do not."""
    found = vehicle.compatibility
    if not found:
        return []
    significant = [f for f in found["findings"] if f["significant"]]
    if not significant:
        return []
    told = vehicle.result.config.sensors.bias_states
    named = ", ".join(
        f"{f['channel']} {f['kind']} {f['value']:+.3g}{' ' + f['unit'] if f['unit'] else ''} "
        f"({f['z']:+.1f} σ)"
        for f in significant
    )
    missing = _missing_biases(vehicle)
    fix = (
        "; the filters estimate a bias with the coefficients where told: [sensors] "
        f"bias_states = {json.dumps([*told, *missing])}"
        if missing
        else ""
    )
    gusts = _gust_findings(vehicle)
    moving = (
        "; the filters found the air moving, and the check takes the wind as steady, so "
        "what it finds on "
        + ", ".join(sorted({f["channel"] for f in gusts}))
        + " may be the gusts rather than the sensors (not advised: decision 0088)"
        if gusts
        else ""
    )
    return [
        "the frames' kinematics (the data compatibility check: the rates and accelerations "
        "integrated against the angles, airspeed and climb rate) find beyond the noise: "
        + named
        + ": sensor errors the filters take as motion"
        + moving
        + fix
    ]


EXPECTED_SIGNS: dict[str, tuple[int, str]] = {
    "CD0": (
        1,
        "drag is positive: the model's thrust falls short of the aircraft's (the "
        "propeller's guesses in the airframe file, the throttle's PWM range in [link]), or "
        "alpha's level is off",
    ),
    "CLa": (1, "lift grows with alpha: is alpha read with its sign reversed?"),
    "Cmq": (-1, "pitch damping opposes the pitch rate: is q read with its sign reversed?"),
    "Cmde": (
        -1,
        "an elevator deflected trailing edge down (positive here) pitches the nose down: "
        "is the elevator read with its sign reversed ([link] elevator_us_per_rad, or the "
        "data's elevator column)?",
    ),
    "CLde": (
        1,
        "an elevator deflected trailing edge down (positive here) adds lift: is the "
        "elevator read with its sign reversed?",
    ),
}
"""Signs every conventional aircraft's coefficients have (docs/model.md's conventions),
and what an estimate of the other sign most likely means."""

SIGN_SIGMAS = 3.0
"""An estimate of the unexpected sign is named when it stands this many of its
sigmas from zero."""

STILL_ELEVATOR_RAD = math.radians(0.1)
"""An elevator that moves less than this over a whole flight [rad] did not move: no
manoeuvre, or the elevator read from the wrong servo or column."""

OPTIONAL_CHANNELS = ("qdot", "h_dot")
"""Observation channels a flight may lack with nothing to warn of (the warm start
differentiates q; the README's CSV layout lets qdot be empty; a climb rate matters only
without alpha, and the warning about alpha then says what its absence costs)."""


def _sign_warnings(kind: str, s: FilterSummary) -> list[str]:
    """Estimates of the sign no conventional aircraft's coefficient has (EXPECTED_SIGNS),
    SIGN_SIGMAS of their sigma from zero: a sensor or the elevator read with its
    sign reversed, most likely; for CD0, a thrust model short of the aircraft's."""
    out = []
    for c in s.coefficients:
        sign, why = EXPECTED_SIGNS.get(c.name, (0, ""))
        if sign and sign * c.estimate < -SIGN_SIGMAS * c.sigma:
            out.append(
                f"{kind}: {c.name} came out {c.estimate:+.4g} "
                f"({abs(c.estimate) / c.sigma:.0f} σ from zero), of the sign no "
                f"conventional aircraft's has: {why}"
            )
    return out


def _run_warnings(result: EstimatorResult) -> list[str]:
    """A channel the data never held, an elevator that never moved, a filter that
    diverged, a warm start that fitted few frames."""
    out: list[str] = []
    track = next((f.track for f in result.filters.values() if f.track is not None), None)
    if track is not None and len(track.y):
        held = np.any(np.isfinite(track.y), axis=0)
        none = [
            name
            for c, name in enumerate(OBS_NAMES)
            if not held[c] and name not in OPTIONAL_CHANNELS
        ]
        elevator = track.u[:, 0]
        if np.isfinite(elevator).any() and np.nanmax(elevator) - np.nanmin(elevator) < (
            STILL_ELEVATOR_RAD
        ):
            out.append(
                "the elevator did not move in this flight (less than "
                f"{math.degrees(STILL_ELEVATOR_RAD):g} deg): the moment "
                "coefficients cannot be told apart; if the aircraft did manoeuvre, the "
                "elevator is read from the wrong place ([link] elevator_servo, or "
                "[data.columns] elevator)"
            )
        if none:
            out.append(
                f"no {', '.join(none)} in these data at all: the filters ran without "
                f"{'it' if len(none) == 1 else 'them'}, and what only "
                f"{'it tells' if len(none) == 1 else 'they tell'} is not identified (a column "
                "the file lacks, or a message the vehicle does not send)"
                + _without_alpha_text(none, bool(held[OBS_NAMES.index("h_dot")]))
            )
    for kind, f in result.filters.items():
        if f.health.divergences:
            out.append(
                f"{kind}: the estimate diverged {f.health.divergences} time(s) and started "
                "again from the prior there (a long gap early in the flight, or bad data); "
                "the history shows absurd values before each"
            )
    if result.warm_start_samples is not None and result.warm_start_frames > 0:
        least = min(result.warm_start_samples)
        if least < 0.5 * result.warm_start_frames:
            cd, cl, cm = result.warm_start_samples
            out.append(
                f"the equation-error warm start fitted CD, CL, Cm on only {cd}, {cl}, {cm} of "
                f"{result.warm_start_frames} frames (gaps or missing channels)"
            )
    if result.frames_banked_out:
        limit = result.config.filter.bank_limit_deg
        out.append(
            f"{result.frames_banked_out} of {result.frames} frames banked beyond {limit:g} deg "
            "were predicted through but not used in the update ([filter] bank_limit_deg)"
        )
    return out


def _moved(vehicle: VehicleResult, kind: FilterKind, s: FilterSummary) -> list[str]:
    """The coefficients (but those not identified) whose sigma the corrections for what
    the model misses widen beyond INFLATION_LIMIT: the movement and the channels'
    weights; the parts for what the data cannot decide (timing, sensor placement, the
    noise floor: decision 0047) are priors, not a sign of a model error."""
    check = vehicle.structure
    weights = None
    if check is not None and "weights" in check.parts:
        weights = check.parts["weights"].get(kind)
    out = []
    for i, c in enumerate(s.coefficients):
        parts = c.sigma_parts
        factor = parts.inflation
        if weights is not None and parts.covariance > 0.0:
            m = parts.movement_factor if math.isfinite(parts.movement_factor) else 1.0
            factor = math.hypot(m * parts.covariance, float(weights[i])) / parts.covariance
        if factor > INFLATION_LIMIT and c.identifiability != NOT_IDENTIFIED:
            out.append(f"{c.name} ×{factor:.1f}")
    return out


THRUST_SHARE = 0.5
"""A coefficient whose propeller part (the structure check's thrust and zero-thrust
airspeed parts) is at least this share of its sigma to trust is held back by the thrust,
not by the data (decision 0054)."""


def thrust_warnings(vehicle: VehicleResult) -> list[str]:
    """Where the flight cannot tell the drag from the thrust the airframe file guesses
    (the structure check's propeller parts dominate a coefficient's sigma and it is not
    identified), in plain words; and where the flight puts the thrust apart from the
    guess, where (decision 0054)."""
    check = vehicle.structure
    if check is None or check.skipped:
        return []
    found = check.found.get("thrust_scale")
    if found is not None and math.isfinite(found[1]):
        prior = check.tolerances.get("thrust", 0.0) / math.sqrt(3.0)
        if found[1] < THRUST_SHARE * prior:  # the flight tells the thrust from the drag
            if abs(found[0]) <= DELAY_WARNING_SIGMA * found[1]:
                return []
            return [
                f"this flight puts the thrust at ×{1.0 + found[0]:.3f} ± {found[1]:.3f} of the "
                "airframe file's: the filters fly the file's, so their drag (and what moves "
                "with it) is off by the difference, which their σ includes; `refine` fits "
                "the thrust with the coefficients"
            ]
    names = vehicle.result.names
    held: dict[str, None] = {}
    for kind, summary in vehicle.summaries.items():
        for i, c in enumerate(summary.coefficients):
            propeller = [check.parts[p][kind][i] for p in THRUST_PARTS if p in check.parts]
            part = float(np.hypot.reduce(propeller)) if propeller else 0.0
            if c.identifiability != IDENTIFIED and part >= THRUST_SHARE * c.sigma:
                held[names[i]] = None
    if not held:
        return []
    return [
        f"{_and(list(held))} and thrust cannot be told apart in this flight: fly "
        "throttle steps or a glide "
        "(the thrust is the airframe file's guess within its tolerance, which their σ "
        "includes)"
    ]


def hold_warnings(vehicle: VehicleResult) -> list[str]:
    """Where the data fit the inputs held the other way between samples decisively better
    than the run's [data] input_hold (decision 0071): the run's estimates sit at the end
    the data reject, which their σ includes; the setting to change."""
    check = vehicle.structure
    if check is None or check.skipped:
        return []
    preferred = check.hold_preferred
    ran = check.input_hold
    if not preferred or preferred == ran:
        return []
    how = {
        "previous": "held at each sample until the next (the commands change at the samples)",
        "linear": "moving linearly from sample to sample",
    }
    return [
        f"the data fit the inputs {how[preferred]} better than [data] input_hold = "
        f'"{ran}" (-2 log likelihood {check.hold_change:+.0f}): the σ shown includes the whole '
        f'move between the two; set [data] input_hold = "{preferred}" for this vehicle'
    ]


def _and(names: list[str]) -> str:
    """ "a", "a and b", "a, b and c"."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def _refined_warnings(refined: Refined) -> list[str]:
    out = []
    loose = [
        n
        for n, sd, prior in zip(
            refined.factor_names, refined.factor_sigma, refined.factor_prior_sigma, strict=True
        )
        if not (math.isfinite(sd) and sd < FACTOR_TOLD * prior)
    ]
    if loose:
        out.append(
            f"{refined.label} cannot tell the drag from the propeller's {' and '.join(loose)} "
            f"in this flight ({refined.factor_text()}): fly throttle steps or a glide"
        )
    coloured = [
        f"{n} {v:.0f}"
        for n, v in zip(OBS_NAMES, refined.residual_colour, strict=True)
        if math.isfinite(v) and v > COLOUR_LIMIT
    ]
    if coloured:
        hint = (
            "; in turbulence, `--method filter-error` lets a filter follow the gusts"
            if refined.method == "output error"
            else ""
        )
        fit = refined.label
        out.append(
            f"{fit} residuals far from white (" + ", ".join(coloured) + "): the model misses "
            f"something (turbulence, unmodelled aerodynamics); trust {fit} σ, not "
            "Cramer-Rao's" + hint
        )
    if refined.difference_sigma is not None:
        apart = [
            f"{n} ×{s / a:.1f}"
            for n, s, a, mark in zip(
                refined.names,
                refined.sigma,
                refined.sigma_within_fit,
                refined.identifiability,
                strict=True,
            )
            if a > 0.0 and s > INFLATION_LIMIT * a and mark != NOT_IDENTIFIED
        ]
        if apart:
            fit = refined.label
            out.append(
                f"{fit} lands further from the filter it started from than both covariances "
                "allow (" + ", ".join(apart) + " on its σ): the two weigh the record "
                "differently, and where the model misses part of the aircraft (unmodelled "
                "aerodynamics, turbulence it models otherwise) each settles on its own "
                f"compromise; {fit} σ includes the difference (docs/decisions/0030)"
            )
    late = [
        n
        for n, d, sd in zip(
            refined.delay_names, refined.delays_s, refined.delay_sigma_s, strict=True
        )
        if math.isfinite(sd) and abs(d - refined.configured_delay_s) > DELAY_WARNING_SIGMA * sd
    ]
    if late:
        out.append(
            f"{refined.label} finds the response later or earlier than the filters took the "
            f"inputs ({refined.delay_text()}): the filters' estimates carry the timing error "
            "and lie apart from the fit; run again with the delay set "
            "(docs/decisions/0044)"
        )
    if not refined.converged:
        out.append(f"{refined.label}: {refined.message}")
    return out


def _without_alpha_text(missing: list[str], climb_rate: bool) -> str:
    """What a record without alpha loses, where alpha is among the missing channels: with
    a climb rate, alpha's level is told from the flight path in calm air only (decision
    0049); without one, never."""
    if "alpha" not in missing:
        return ""
    if climb_rate:
        return (
            "; alpha is taken from the climb rate and the pitch angle (the flight path), "
            "which tells its level in calm air only: where the vertical wind moved, the "
            "intercepts and alpha derivatives are not identified"
        )
    return (
        "; without alpha the intercepts and alpha derivatives are not identified and every "
        "other coefficient is weak at best"
    )
