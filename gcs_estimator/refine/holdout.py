"""The held-out check (decision 0051): the identified model, driven by a segment's
measured inputs from its measured state, against its measured response.

The model is flown with refine's own compiled flight (flights.innovations without process
noise: output error, the filters' Runge-Kutta steps), re-anchored at the measured state
every ANCHOR_S seconds: open loop over minutes, an unstable phugoid would diverge and
the metric would judge the phugoid's growth rather than the coefficients; over a few
seconds the short period and the forces show, and a wrong damping or stiffness misses.
A flight state that is not measured at an anchor (alpha without a vane) is the filter's
estimate there where the segment is from the run, else alpha = theta (level flight).
"""

from __future__ import annotations

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.filters.core import MAX_STEP_S
from gcs_estimator.model.aircraft import Model, build_model
from gcs_estimator.model.channels import N_FLIGHT, N_OBS
from gcs_estimator.refine.flights import innovations
from gcs_estimator.uncertainty.holdout import Holdout, channel_fits

ANCHOR_S = 10.0
"""The model is re-anchored at the measured flight state this often [s]."""
MIN_FRAMES = 10


def _anchor_state(
    model: Model,
    y0: FloatArray,
    estimate: FloatArray | None,
    biases: FloatArray,
) -> FloatArray:
    """The flight state [4] at an anchor: measured (less its bias), else the run's
    estimate, else alpha from theta and q 0 (NaN airspeed: no anchor)."""
    on = np.zeros(N_FLIGHT)
    for ch, b in zip(model.arrays.bias_channel, biases, strict=True):
        if ch < N_FLIGHT:
            on[ch] += b
    x = y0[:N_FLIGHT] - on
    if estimate is not None:
        x = np.where(np.isfinite(x), x, estimate[:N_FLIGHT])
    defaults = np.array([np.nan, x[2], np.nan, 0.0])
    x = np.where(np.isfinite(x), x, defaults)
    return x


def predict_segment(
    config: AircraftConfig,
    coefficients: FloatArray,
    biases: FloatArray,
    t: FloatArray,
    inputs: FloatArray,
    y: FloatArray,
    states: FloatArray | None = None,
    anchor_s: float = ANCHOR_S,
) -> FloatArray:
    """The model's prediction [N x 7] (NaN where y is) of the segment (t [N], the model's
    inputs [N x m] as recorded, y [N x 7] NaN where missing), re-anchored every
    anchor_s at the measured state (states [N x >= 4]: the run's estimates, for what is
    not measured)."""
    model = build_model(config, gust_states=False)
    u_all = np.ascontiguousarray([model.inputs(row) for row in inputs], dtype=float)
    mask_all = np.isfinite(y).astype(float)
    y0 = np.where(mask_all > 0, y, 0.0)
    out = np.full((t.shape[0], N_OBS), np.nan)
    q = np.zeros(model.arrays.n_dynamic)
    r = np.ones(N_OBS)
    linear = config.data.input_hold == "linear"
    start = 0
    while start < t.shape[0] - 1:
        stop = int(np.searchsorted(t, t[start] + anchor_s, side="right"))
        stop = max(stop, start + 2)
        idx = slice(start, stop)
        x0 = np.zeros(model.n)
        x0[:N_FLIGHT] = _anchor_state(
            model, y[start], None if states is None else states[start], biases
        )
        if not np.all(np.isfinite(x0[:N_FLIGHT])):  # no airspeed to start from
            start = stop
            continue
        x0[model.coefficients] = coefficients
        x0[model.biases] = biases
        _, _, raw, ok = innovations(
            x0,
            np.ascontiguousarray(t[idx]),
            np.ascontiguousarray(u_all[idx]),
            np.ascontiguousarray(y0[idx]),
            np.ascontiguousarray(mask_all[idx]),
            model.arrays,
            q,
            r,
            MAX_STEP_S,
            linear,
        )
        if ok:
            out[idx] = np.where(mask_all[idx] > 0, y0[idx] - raw, np.nan)
        start = stop
    return out


def check(
    config: AircraftConfig,
    coefficients: FloatArray,
    biases: FloatArray,
    t: FloatArray,
    inputs: FloatArray,
    y: FloatArray,
    noise_sigma: FloatArray,
    segment: str,
    coefficients_from: str,
    states: FloatArray | None = None,
    in_sample: bool = False,
) -> Holdout:
    """The held-out check of the estimates on one segment (predict_segment), each
    channel's Theil U and RMS error (uncertainty.holdout)."""
    keep = np.concatenate([[True], np.diff(t) > 0.0])
    t, inputs, y = t[keep], inputs[keep], y[keep]
    states = None if states is None else states[keep]
    if t.shape[0] < MIN_FRAMES:
        raise ValueError(f"--validate: {segment} has {t.shape[0]} frames; {MIN_FRAMES} needed")
    predicted = predict_segment(config, coefficients, biases, t, inputs, y, states)
    mask = (np.isfinite(y) & np.isfinite(predicted)).astype(float)
    fits = channel_fits(np.nan_to_num(y), np.nan_to_num(predicted), mask, noise_sigma)
    method = f"the model re-anchored at the measured state every {ANCHOR_S:g} s"
    return Holdout(segment, coefficients_from, method, fits, t, y, predicted, in_sample)
