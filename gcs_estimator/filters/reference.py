"""The reference backend of the step contract (filters.core): plain numpy and scipy.

Textbook symbols, the generic hybrid filter (filters.hybrid) on the model's callables,
no compiler. The compiled backend (filters.fast) is tested against it.
"""

from __future__ import annotations

import math

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.filters import core, hybrid
from gcs_estimator.filters.core import FilterState, GustState, StepInfo, Tuning
from gcs_estimator.filters.hybrid import Belief
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_OBS


def gust_match(e: FloatArray, s: FloatArray, G: FloatArray) -> tuple[float, float]:
    """Weighted covariance-matching sums of one step (see core.GustState):
    num = sum w (min(e^2, 25 S) - S), den = sum w G, w = G / (2 S^2), over the channels
    whose innovation e and its sigma s are present."""
    S = s * s
    ok = np.isfinite(e) & (S > 0.0)
    if not ok.any():
        return 0.0, 0.0
    e, S, G = e[ok], S[ok], G[ok]
    w = G / (2.0 * S * S)
    num = float(np.sum(w * (np.minimum(e * e, core.GUST_CLIP * S) - S)))
    den = float(np.sum(w * G))
    return num, den


def adapt_gust(
    gust: GustState,
    tuning: Tuning,
    model: Model,
    dt: float,
    x: FloatArray,
    u: FloatArray,
    e: FloatArray,
    s: FloatArray,
    applied: float,
) -> GustState:
    """Move the gust variance towards the level at which the innovations are as large as
    the filter predicts (core.GustState)."""
    if not tuning.adaptive or not dt > 0.0:
        return gust
    sens, age = gust.sens, gust.sens_age
    if age >= core.GUST_SENSITIVITY_EVERY:
        _, H = model.h(x, u)
        sens = H**2 @ tuning.gust_unit
        age = 0
    age += 1
    num, den = gust_match(e, s, dt * sens)
    if not den > 0.0:
        return gust._replace(sens=sens, sens_age=age)
    # Each step estimates the level as the one its process noise used plus a correction:
    # averaged over the pass (for the next restart) and running.
    estimate = applied + num / den
    gain = min(1.0, dt / tuning.adapt_time_s)
    info = gust.info + gain * (den - gust.info) if gust.info > 0.0 else den
    var = max(gust.var + gain * (estimate - gust.var), core.GUST_VAR_FLOOR)
    return GustState(
        var, info, gain, gust.pass_num + den * estimate, gust.pass_den + den, sens, age
    )


def kernel_step(
    state: FilterState, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model
) -> tuple[FilterState, StepInfo, bool]:
    """Predict with the held inputs, update with y, adapt the gust level (core contract)."""
    u_prev = state.u if np.isfinite(state.u).all() else u
    dt = t - state.t
    q, applied = core.process_noise(state, tuning)
    prior = hybrid.propagate(
        lambda x: model.f(x, u_prev), Belief(state.x, state.P), np.diag(q), dt, tuning.max_step_s
    )
    e = np.full(N_OBS, np.nan)
    s = np.full(N_OBS, np.nan)
    failed = False
    try:
        post, upd = hybrid.iekf_update(
            lambda x: model.h(x, u),
            prior,
            y,
            tuning.R,
            iterations=tuning.iterations,
            tolerance=tuning.tolerance,
            gate=tuning.gate,
            relinearise=tuning.relinearise,
        )
    except (np.linalg.LinAlgError, ValueError):  # not positive definite, or not finite
        post, failed = prior, True
        nis, n_used, iterations = math.nan, 0, 0
    else:
        e[upd.used] = upd.innovation
        s[upd.used] = np.sqrt(np.diag(upd.S))
        nis, n_used, iterations = upd.nis, int(upd.used.sum()), upd.iterations
    variances = np.diag(post.P)
    healthy = bool(variances.min() > 0.0) and math.isfinite(float(post.x.sum() + post.P.sum()))
    gust = adapt_gust(state.gust, tuning, model, dt, post.x, u, e, s, applied)
    new = FilterState(post.x, post.P, t, np.array(u, float), state.t_start, gust)
    info = StepInfo(
        sigma=np.sqrt(np.maximum(variances, 0.0)),
        nis=float(nis),
        n_used=n_used,
        iterations=iterations,
        innovation=e,
        innovation_sigma=s,
        gust_sigma=math.sqrt(applied),
        failed=failed,
    )
    return new, info, healthy
