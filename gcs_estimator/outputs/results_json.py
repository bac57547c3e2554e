"""The run's results as JSON: everything a script needs (estimates, the sigma to trust
and its parts, convergence, consistency, the structure check, the whole-record fit, the
warnings and the config used)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.results import EstimatorResult
from gcs_estimator.model.channels import FLIGHT_STATES, OBS_NAMES
from gcs_estimator.outputs.diagnosis import advised_settings, refine_advised, trust_warnings
from gcs_estimator.uncertainty.metrics import CoefficientSummary, FilterSummary, percent_error
from gcs_estimator.uncertainty.result import VehicleResult
from gcs_estimator.uncertainty.weighting import VARIANCE_FACTOR

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined


def results_dict(
    vehicle: VehicleResult,
    extra: Mapping[str, Any] | None = None,
    refined: Refined | None = None,
) -> dict[str, Any]:
    """Everything a script needs: estimates, sigmas, convergence, NIS, config used."""
    result = vehicle.result
    config = result.config
    out: dict[str, Any] = {
        "aircraft": config.airframe.name,
        "config_source": config.source,
        "truth_label": config.truth_label if vehicle.truth is not None else None,
        "coefficients": list(result.names),
        "filters": {},
        "diagnostics": {
            "frames": result.frames,
            "restarts_done": result.restarts_done,
            "gaps": result.gaps,
            "frames_out_of_order": result.frames_out_of_order,
            "segments": result.segments,
            "flights": list(result.flights),
            "frames_banked_out": result.frames_banked_out,
            "warm_start": None if result.warm_start is None else result.warm_start.tolist(),
            "warm_start_samples": result.warm_start_samples,
            "warm_start_frames": result.warm_start_frames,
            "measurement_noise": config.filter.measurement_noise,
            "measurement_sigma": dict(zip(OBS_NAMES, result.measurement_sigma, strict=True)),
            "noise_differences": None
            if result.noise_reading is None
            else dict(zip(OBS_NAMES, result.noise_reading.differences, strict=True)),
            "noise_reading": None
            if result.noise_reading is None
            else dict(zip(OBS_NAMES, result.noise_reading.sigma, strict=True)),
            "compatibility": vehicle.compatibility,
            "advised_settings": advised_settings(vehicle, refined),
            "advised_refine": refine_advised(vehicle, refined),
            "structure_check": _structure_dict(vehicle),
            "failed_updates": {k: f.health.failed_updates for k, f in result.filters.items()},
            "divergences": {k: f.health.divergences for k, f in result.filters.items()},
            "covariance_repairs": {
                k: f.health.covariance_repairs for k, f in result.filters.items()
            },
        },
        "warnings": trust_warnings(vehicle, refined),
        "refined": None if refined is None else refined_dict(refined, vehicle.truth),
        "holdout": None
        if vehicle.holdout is None
        else {**vehicle.holdout.as_dict(), "dropped": dict(vehicle.holdout_drops or {})},
        "advice": None if vehicle.advice is None else vehicle.advice.as_dict(),
        "config": _jsonable(config.raw),
    }
    for kind, s in vehicle.summaries.items():
        out["filters"][kind] = _filter_dict(s, result)
    if extra:
        out.update(extra)
    return out


def _filter_dict(s: FilterSummary, result: EstimatorResult) -> dict[str, Any]:
    """One filter's figures: consistency, turbulence, estimates, sensor biases."""
    f = result.filters[s.kind]
    return {
        "mean_nis": _num(s.mean_nis),
        "mean_nis_whole_flight": _num(s.mean_nis_all),
        "mean_channels": _num(s.mean_channels),
        "turbulence_sigma_w_mps": s.gust_sigma,
        "turbulence_pass_sigma_w_mps": s.gust_pass_sigma,
        "turbulence_pass_z": _num(s.gust_pass_z),
        "nees": _num(s.nees),
        "innovation_mean_square": {
            n: _num(v) for n, v in zip(OBS_NAMES, s.channel_nis, strict=True)
        },
        "updates": s.steps,
        "estimates": {c.name: coefficient_dict(c) for c in s.coefficients},
        "sensor_biases": {
            name: {"estimate": float(b), "sigma": float(sd)}
            for name, b, sd in zip(result.bias_names, f.biases, f.bias_sigma, strict=True)
        },
    }


def coefficient_dict(c: CoefficientSummary) -> dict[str, Any]:
    """One coefficient's figures: its estimate, the sigma to trust and what it is made
    of (sigma.SigmaParts), its error against truth, convergence and mark."""
    parts = c.sigma_parts
    return {
        "estimate": c.estimate,
        "sigma": c.sigma,
        "sigma_parts": {
            "covariance": parts.covariance,
            "movement_factor": _num(parts.movement_factor),
            "structure": _num(parts.structure),
            "inflation": _num(parts.inflation),
        },
        "truth": c.truth,
        "error_pct": _num(c.error_pct),
        "error_sigmas": _num(c.z),
        "settled_s": _num(c.converged_final_s),
        "within_5pct_of_truth_s": _num(c.converged_truth_s),
        "identifiability": c.identifiability,
        "relative_sigma": _num(c.sigma / abs(c.estimate) if c.estimate else None),
        "most_correlated_with": c.correlated_with or None,
        "correlation": c.correlation,
    }


def _structure_dict(vehicle: VehicleResult) -> dict[str, Any] | None:
    """The structure check (weighting.py): the channels re-weighted and how far each
    moved each estimate, or why it was not made."""
    check = vehicle.structure
    if check is None:
        return None
    if check.skipped:
        return {"skipped": check.skipped}
    names = vehicle.result.names
    return {
        "skipped": None,
        "variance_factor": VARIANCE_FACTOR,
        "channels": list(check.channels),
        "moves": {
            kind: {
                ch: dict(zip(names, (float(v) for v in row), strict=True))
                for ch, row in zip(check.channels, moves, strict=True)
            }
            for kind, moves in check.moves.items()
        },
        "tolerances": dict(check.tolerances),
        "found": {
            key: {"offset": _num(where), "sigma": _num(sd)}
            for key, (where, sd) in check.found.items()
        },
        "sigma_parts": {
            part: {kind: dict(zip(names, map(float, v), strict=True)) for kind, v in by.items()}
            for part, by in check.parts.items()
        },
        "hold": {
            "input_hold": check.input_hold,
            "likelihood_change": _num(check.hold_change),
            "preferred": check.hold_preferred or None,
        },
    }


def refined_dict(refined: Refined, truth: FloatArray | None) -> dict[str, Any]:
    """The whole-record fit as JSON."""
    return {
        "method": refined.method,
        "method_choice": refined.choice or None,
        "frames": refined.frames,
        "converged": refined.converged,
        "message": refined.message,
        "noise_sigma": {
            n: _num(float(v)) for n, v in zip(OBS_NAMES, refined.noise_sigma, strict=True)
        },
        "process_noise_density": {
            n: float(v) for n, v in zip(FLIGHT_STATES, refined.process_noise, strict=True)
        },
        "residual_colour": {
            n: _num(float(v)) for n, v in zip(OBS_NAMES, refined.residual_colour, strict=True)
        },
        "initial_state": dict(zip(FLIGHT_STATES, map(float, refined.state0), strict=True)),
        "estimates": {
            n: {
                "estimate": float(refined.coefficients[i]),
                "sigma": _num(float(refined.sigma[i])),
                "sigma_parts": _refined_parts(refined, i),
                "identifiability": refined.identifiability[i],
                "truth": None if truth is None else float(truth[i]),
                "error_pct": None
                if truth is None
                else _num(percent_error(float(refined.coefficients[i]), float(truth[i]))),
            }
            for i, n in enumerate(refined.names)
        },
        "correlation": refined.correlation.tolist(),
        "sensor_biases": {
            n: {"estimate": float(b), "sigma": _num(float(s))}
            for n, b, s in zip(refined.bias_names, refined.biases, refined.bias_sigma, strict=True)
        },
        "input_delays_s": {
            n: {"estimate": float(d), "sigma": _num(float(s))}
            for n, d, s in zip(
                refined.delay_names, refined.delays_s, refined.delay_sigma_s, strict=True
            )
        },
        "configured_input_delay_s": refined.configured_delay_s,
        "propeller_factors": {
            n: {"estimate": float(f), "sigma": _num(float(s)), "prior_sigma": float(p)}
            for n, f, s, p in zip(
                refined.factor_names,
                refined.factors,
                refined.factor_sigma,
                refined.factor_prior_sigma,
                strict=True,
            )
        },
    }


def _refined_parts(refined: Refined, i: int) -> dict[str, float | None]:
    """What the fit's sigma of coefficient i is made of (refine.Refined, its sigma_parts)."""
    difference = refined.difference_sigma
    floor = refined.filter_structure_sigma
    trusted = refined.sigma_parts.filter_trusted
    return {
        "cramer_rao": _num(float(refined.crb_sigma[i])),
        "structure": _num(float(refined.structure_sigma[i])),
        "difference": None if difference is None else _num(float(difference[i])),
        "filter_structure": None if floor is None else _num(float(floor[i])),
        # the filter's sigma to trust, which the fit's does not fall below (decision 0057)
        "filter_trusted": None if trusted is None else _num(float(trusted[i])),
    }


def _num(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def _jsonable(data: Any) -> Any:
    if isinstance(data, Mapping):
        return {str(k): _jsonable(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [_jsonable(v) for v in data]
    if hasattr(data, "isoformat"):
        return data.isoformat()
    return data
