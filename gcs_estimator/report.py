"""Results people can use: the paper's Table I as Markdown, JSON, and CSV time histories."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from gcs_estimator.config import POWER_COLUMNS
from gcs_estimator.estimator import FILTER_KINDS, Estimator, EstimatorResult, FilterKind
from gcs_estimator.metrics import FilterSummary, percent_error
from gcs_estimator.model.channels import FLIGHT_STATES, OBS_NAMES
from gcs_estimator.session import VehicleResult


def _fmt(v: float | None, digits: int = 4) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.{digits}g}" if abs(v) < 1e-3 and v != 0 else f"{v:.{digits}f}"


def _time(v: float | None) -> str:
    return "never" if v is None or not math.isfinite(v) else f"{v:.1f}"


def markdown_table(
    summaries: Mapping[FilterKind, FilterSummary], truth_label: str = "truth"
) -> str:
    """Table I layout: one row per coefficient, estimate and sigma per filter, plus the
    true (or reference) value, error in percent and in sigmas when it is known."""
    kinds: list[FilterKind] = [k for k in FILTER_KINDS if k in summaries]
    if not kinds:
        return "(no estimates yet)\n"
    first = summaries[kinds[0]]
    has_truth = any(c.truth is not None for c in first.coefficients)
    head = ["coefficient"] + ([truth_label] if has_truth else [])
    for k in kinds:
        head += [f"{k} estimate", f"{k} σ"]
        if has_truth:
            head += [f"{k} error %", f"{k} error/σ"]
        head += [f"{k} settled by s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, c0 in enumerate(first.coefficients):
        row = [c0.name] + ([_fmt(c0.truth)] if has_truth else [])
        for k in kinds:
            c = summaries[k].coefficients[i]
            row += [_fmt(c.estimate), f"{c.sigma:.2g}"]
            if has_truth:
                row += [
                    "-" if c.error_pct is None else f"{c.error_pct:+.2f}",
                    "-" if c.z is None else f"{c.z:+.1f}",
                ]
            row += [_time(c.converged_final_s)]
        lines.append("| " + " | ".join(row) + " |")
    notes = []
    for k in kinds:
        s = summaries[k]
        note = (
            f"{k}: {s.steps} updates, mean NIS {s.mean_nis:.2f} over {s.mean_channels:.1f} channels"
        )
        if s.nees is not None:
            note += f", coefficient NEES {s.nees:.1f} (dof {len(s.coefficients)})"
        note += f", turbulence σ_w {s.gust_sigma:.2f} m/s"
        notes.append(note)
    lines.append("")
    lines.append(
        "σ: one standard deviation from the filter covariance. Settled by: time after which "
        "the estimate stays within 5 % of its final value."
    )
    lines += [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"


def live_table(estimator: Estimator) -> str:
    """The current estimates as a Markdown table (cheap: no history is read)."""
    current = estimator.snapshot()
    if not current:
        return "(waiting for data)\n"
    truth = estimator.config.truth
    kinds = [k for k in FILTER_KINDS if k in current]
    head = ["coefficient"] + ([estimator.config.truth_label] if truth else [])
    for k in kinds:
        head += [f"{k} estimate", f"{k} ±2σ"] + ([f"{k} error %"] if truth else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, name in enumerate(estimator.names):
        row = [name] + ([_fmt(truth[i])] if truth else [])
        for k in kinds:
            snap = current[k]
            x = float(snap.coefficients[i])
            row += [_fmt(x), f"{2 * snap.sigma[i]:.2g}"]
            if truth:
                err = percent_error(x, truth[i])
                row.append("-" if err is None else f"{err:+.2f}")
        lines.append("| " + " | ".join(row) + " |")
    gusts = ", ".join(f"{k} {current[k].gust_sigma:.2f}" for k in kinds)
    return f"{estimator.frames} frames; turbulence σ_w [m/s]: {gusts}\n\n" + "\n".join(lines) + "\n"


def final_table(vehicle: VehicleResult) -> str:
    """The finished run's Table I (with convergence times), as in results.md, and what
    the run estimated beside the coefficients or fitted to start them."""
    result = vehicle.result
    notes = []
    for kind, f in result.filters.items():
        if result.bias_names:
            biases = ", ".join(
                f"{n.removesuffix('_bias')} {b:+.3g} ± {s:.2g}"
                for n, b, s in zip(result.bias_names, f.biases, f.bias_sigma, strict=True)
            )
            notes.append(f"{kind} sensor biases [SI]: {biases}")
    if result.warm_start_samples is not None:
        cd, cl, cm = result.warm_start_samples
        notes.append(
            f"equation-error warm start: fitted CD, CL, Cm on {cd}, {cl}, {cm} of "
            f"{result.warm_start_frames} frames"
        )
    table = markdown_table(vehicle.summaries, result.config.truth_label)
    return table + "".join(f"- {n}\n" for n in notes)


def results_dict(vehicle: VehicleResult, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
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
            "warm_start": None if result.warm_start is None else result.warm_start.tolist(),
            "warm_start_samples": result.warm_start_samples,
            "warm_start_frames": result.warm_start_frames,
            "failed_updates": {k: f.health.failed_updates for k, f in result.filters.items()},
            "divergences": {k: f.health.divergences for k, f in result.filters.items()},
            "covariance_repairs": {
                k: f.health.covariance_repairs for k, f in result.filters.items()
            },
        },
        "config": _jsonable(config.raw),
    }
    for kind, s in vehicle.summaries.items():
        out["filters"][kind] = {
            "mean_nis": _num(s.mean_nis),
            "mean_nis_whole_flight": _num(s.mean_nis_all),
            "mean_channels": _num(s.mean_channels),
            "turbulence_sigma_w_mps": s.gust_sigma,
            "nees": _num(s.nees),
            "updates": s.steps,
            "estimates": {
                c.name: {
                    "estimate": c.estimate,
                    "sigma": c.sigma,
                    "truth": c.truth,
                    "error_pct": _num(c.error_pct),
                    "error_sigmas": _num(c.z),
                    "settled_s": _num(c.converged_final_s),
                    "within_5pct_of_truth_s": _num(c.converged_truth_s),
                }
                for c in s.coefficients
            },
            "sensor_biases": {
                name: {"estimate": float(b), "sigma": float(sd)}
                for name, b, sd in zip(
                    result.bias_names,
                    result.filters[kind].biases,
                    result.filters[kind].bias_sigma,
                    strict=True,
                )
            },
        }
    if extra:
        out.update(extra)
    return out


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


def write_history_csv(path: Path, result: EstimatorResult) -> None:
    """Time histories, one row per filter and frame: estimates and sigmas of every state
    and coefficient, NIS, channels used, and the frame's inputs and measurements."""
    names = list(FLIGHT_STATES) + list(result.names)
    power = POWER_COLUMNS[result.config.propulsion.input_name]

    def cell(v: float) -> str:
        return repr(float(v)) if np.isfinite(v) else ""

    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(
            ["filter", "t_s"]
            + names
            + [f"sigma_{n}" for n in names]
            + ["nis", "channels", "in_elevator_rad", f"in_{power}", "in_air_density_kgpm3"]
            + [f"meas_{n}" for n in OBS_NAMES]
        )
        for kind, fr in result.filters.items():
            tr = fr.track
            if tr is None:
                continue
            for i in range(len(tr.t)):
                row = [kind, repr(float(tr.t[i]))]
                row += [repr(float(v)) for v in tr.x[i]]
                row += [repr(float(v)) for v in tr.sigma[i]]
                row += [cell(tr.nis[i]), str(int(tr.n_used[i]))]
                row += [cell(v) for v in tr.u[i]]
                row += [cell(v) for v in tr.y[i]]
                w.writerow(row)


def write_results(
    out_dir: Path,
    vehicle: VehicleResult,
    extra: Mapping[str, Any] | None = None,
    stem: str = "results",
) -> dict[str, Path]:
    """Write <stem>.json, <stem>.md and <stem>_history.csv into out_dir; return their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    data = results_dict(vehicle, extra)
    paths = {
        "json": out_dir / f"{stem}.json",
        "markdown": out_dir / f"{stem}.md",
        "csv": out_dir / f"{stem}_history.csv",
    }
    paths["json"].write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    title = f"# {vehicle.result.config.airframe.name}: estimated aerodynamic coefficients\n\n"
    paths["markdown"].write_text(title + final_table(vehicle), encoding="utf-8")
    write_history_csv(paths["csv"], vehicle.result)
    return paths
