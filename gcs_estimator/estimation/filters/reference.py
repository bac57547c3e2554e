"""The reference backend of the step contract (filters.core): plain numpy and scipy.

Textbook symbols, the generic hybrid filter (filters.hybrid) on the model's callables,
no compiler. The compiled backend (filters.fast) is tested against it.
"""

from __future__ import annotations

import math

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.filters import core, hybrid
from gcs_estimator.estimation.filters.core import FilterState, StepInfo, Tuning
from gcs_estimator.estimation.filters.hybrid import Belief
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_OBS


def kernel_step(
    state: FilterState, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model
) -> tuple[FilterState, StepInfo, bool]:
    """Predict, update with y, adapt the gust level (core contract)."""
    u_prev, u_end = core.input_path(state.u, u, tuning.linear_inputs)
    dt = t - state.t
    q, applied = core.process_noise(state, tuning)

    def f(x: FloatArray, s: float) -> tuple[FloatArray, FloatArray]:
        return model.f(x, u_prev + s * (u_end - u_prev))

    prior = hybrid.propagate(f, Belief(state.x, state.P), np.diag(q), dt, tuning.max_step_s)
    e = np.full(N_OBS, np.nan)
    s = np.full(N_OBS, np.nan)
    failed = False
    try:
        post, upd = hybrid.iekf_update(
            lambda x: model.h(x, u),
            prior,
            y,
            core.measurement_noise(tuning, applied, dt),
            iterations=tuning.iterations,
            relinearise=tuning.relinearise,
            judged=model.coefficients,
        )
    except (np.linalg.LinAlgError, ValueError):  # not positive definite, or not finite
        post, failed = prior, True
        nis, n_used, iterations = math.nan, 0, 0
    else:
        e[upd.used] = upd.innovation
        s[upd.used] = np.sqrt(np.diag(upd.S))
        nis, n_used, iterations = upd.nis, int(upd.used.sum()), upd.iterations
    variances = np.diag(post.P)
    healthy = (
        bool(variances.min() > 0.0)
        and math.isfinite(float(post.x.sum() + post.P.sum()))
        and core.plausible(post.x, tuning.state_max)
    )
    gust = core.adapt_gust(state.gust, tuning, model.arrays, t, dt, post.x, u, e, s, applied)
    new = FilterState(post.x, post.P, t, np.array(u, float), gust)
    info = StepInfo(
        sigma=np.sqrt(np.maximum(variances, 0.0)),
        nis=float(nis),
        n_used=n_used,
        iterations=iterations,
        innovation=e,
        innovation_sigma=s,
        gust_sigma=math.sqrt(applied),
        gust_pass_sigma=math.sqrt(gust.pass_average()),
        failed=failed,
    )
    return new, info, healthy
