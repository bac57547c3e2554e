"""Maximum likelihood over a whole record: `refine`, the fit of one record from a start.

All fits integrate the model as the filters predict (flights: the filters' own Runge-Kutta
steps of at most max_step_s, the configured input hold, air density per sample, sensor
placement); the sensitivities are forward differences (problem). The method is output
error (output_error: no process noise) or filter error (filter_error: a steady-state gain,
its process noise and the innovations' covariance estimated with the parameters; or, with
the noise held, output_error's iterations on the time-varying filter at the held levels).
The fit's sigma to trust and its parts come from sigma.fit_sigma.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from gcs_estimator import blas
from gcs_estimator.arrays import BoolArray, FloatArray, IntArray
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_FLIGHT, N_OBS
from gcs_estimator.refine import filter_error
from gcs_estimator.refine.covariance import sandwich
from gcs_estimator.refine.output_error import Report, gauss_newton
from gcs_estimator.refine.problem import Problem, thread_pool
from gcs_estimator.refine.result import (
    FACTOR_NAMES,
    INPUT_NAMES,
    Refined,
    RefineError,
    RefineProgress,
)
from gcs_estimator.refine.structure import STRUCTURE_ITERATIONS, structure_sigma
from gcs_estimator.uncertainty.metrics import correlation_of, identifiability
from gcs_estimator.uncertainty.sigma import FilterEstimate, FitSigma, difference_sigma, fit_sigma


class _Progress:
    """The fits' reports (iteration, cost, step), numbered on across the main fit and its
    re-weighted ones, as RefineProgress with the filter runs so far."""

    def __init__(self, progress: Callable[[RefineProgress], None] | None, prob: Problem) -> None:
        self.progress = progress
        self.prob = prob
        self.iterations = 0

    def report(self, it: int, cost: float, step: float) -> None:
        self.iterations += 1
        if self.progress is not None:
            self.progress(RefineProgress(self.iterations, cost, step, self.prob.runs))


class _Fitted(NamedTuple):
    """Where a fit ended, and what its uncertainty is computed from."""

    x: FloatArray
    """The augmented state at t[0]: flight states, coefficients, biases."""
    process_noise: FloatArray
    """Process noise spectral density of the flight states [n_dynamic]."""
    noise_sigma: FloatArray
    """Measurement noise sigma per channel [7] (NaN: not observed)."""
    e: FloatArray
    """The whitened residuals [N x 7]."""
    J: FloatArray
    """Their sensitivities [N*7 x p], the state's free entries first."""
    refit: Callable[[FloatArray], FloatArray]
    """The fit re-made from its end with the channels' variances times a scale [7]: the
    state's free entries (structure_sigma)."""
    iterations: int
    converged: bool
    prior_rows: FloatArray
    """The factors' priors' rows over J's columns (Problem.prior; none: 0 rows)."""


class _Start(NamedTuple):
    """What a fit starts from."""

    prob: Problem
    x: FloatArray
    """The augmented state at t[0]."""
    free: IntArray
    """The entries of x the observations see: those fitted."""
    observed: BoolArray
    """The channels observed [7]."""
    q: FloatArray
    """Process noise spectral density of the flight states [n_dynamic]."""
    r: FloatArray
    """Noise variance per channel [7]."""


def _steady_fit(start: _Start, iterations: int, report: Report) -> _Fitted:
    """Filter error with a steady-state gain, its process noise and the innovations'
    covariance estimated with the parameters (filter_error)."""
    prob, x, free, observed, q, r = start
    sf = filter_error.SteadyFilter(prob, x, free, observed)
    theta0 = np.concatenate([x[free], np.log(np.sqrt(np.maximum(q, filter_error.Q_FLOOR)))])
    theta, r, total, converged = filter_error.fit(sf, theta0, r, iterations, report)
    x, f = sf.unpack(theta)
    k = len(free)

    def refit(scale: FloatArray) -> FloatArray:
        again = filter_error.fit(sf, theta, r * scale, STRUCTURE_ITERATIONS, report, relax=False)
        return again[0][:k]

    raw = sf.run(theta, r)
    assert raw is not None
    e = sf.whitened(raw, r)
    J = filter_error.jacobian(sf, theta, r, e)
    _, prior_rows = sf.prior(theta)
    gain = sf.gain(theta, r)
    assert gain is not None
    _, _, P, C = gain
    state_var = np.zeros(N_OBS)
    state_var[sf.obs] = np.einsum("ij,jk,ik->i", C, P, C)
    noise = np.where(observed, np.sqrt(np.maximum(r - state_var, 0.0)), np.nan)
    return _Fitted(x, f * f, noise, e, J, refit, total, converged, prior_rows)


def _gauss_newton_fit(start: _Start, iterations: int, hold_noise: bool, report: Report) -> _Fitted:
    """Output error, the noise estimated (R in closed form inside each iteration) or
    held; with process noise held too, the time-varying filter at the held levels
    (output_error)."""
    prob, x, free, observed, q, r = start
    relax = None if hold_noise else observed
    x, r, total, converged = gauss_newton(prob, x, free, q, r, iterations, relax, report)
    e, _, _, _ = prob.run(x, q, r)
    J = prob.jacobian(x, free, q, r, e)
    noise = np.where(observed, np.sqrt(r), np.nan)

    def refit(scale: FloatArray) -> FloatArray:
        again = gauss_newton(prob, x, free, q, r * scale, STRUCTURE_ITERATIONS, None, report)
        return again[0][free]

    return _Fitted(x, q, noise, e, J, refit, total, converged, prob.prior(x, free)[1])


def _over_state(n: int, free: IntArray, values: FloatArray) -> FloatArray:
    """values [len(free)] placed at the free entries of an augmented state [n], NaN at
    the others (parameters the observations do not see have no sigma)."""
    out = np.full(n, np.nan)
    out[free] = values
    return out


def _sigmas(
    model: Model,
    n_extra: int,
    end: _Fitted,
    free: IntArray,
    observed: BoolArray,
    mask: FloatArray,
    compared: FilterEstimate | None,
) -> tuple[FitSigma, FloatArray, FloatArray, FloatArray]:
    """The coefficients' sigma to trust with its parts, the sigma of the biases and of the
    n_extra delays and factors that follow the state, the coefficients' correlation and
    each channel's residual colour."""
    n, k = end.x.shape[0], len(free)
    J3 = end.J.reshape(end.e.shape[0], N_OBS, end.J.shape[1])
    prior = end.prior_rows.T @ end.prior_rows
    Minv, cov_mk, colour = sandwich(J3, end.e, mask, observed, prior)
    # The state's free entries lead the parameters (filter error's log F follow them).
    crb = _over_state(n, free, np.sqrt(np.diag(Minv)[:k]))
    mk_var = _over_state(n, free, np.diag(cov_mk)[:k])
    own = _over_state(n, free, structure_sigma(J3, k, observed, end.x[free], end.refit, prior))
    cs, bs = model.coefficients, model.biases
    floor = None
    difference = None
    trusted = None
    if compared is not None:
        difference = difference_sigma(end.x[cs], crb[cs], compared)
        if compared.structure is not None:
            floor = np.asarray(compared.structure, float)
        trusted = compared.trusted
    parts = fit_sigma(crb[cs], mk_var[cs], own[cs], floor, difference, trusted)
    full = np.zeros((n, n))
    full[np.ix_(free, free)] = cov_mk[:k, :k]
    bias_sigma = fit_sigma(crb[bs], mk_var[bs], own[bs]).sigma
    ds = np.arange(model.n, model.n + n_extra)  # the delays, then the factors
    delay_sigma = fit_sigma(crb[ds], mk_var[ds], own[ds]).sigma
    return parts, np.concatenate([bias_sigma, delay_sigma]), correlation_of(full[cs, cs]), colour


def _record(
    model: Model, t_s: FloatArray, inputs: FloatArray, observations: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, BoolArray]:
    """t, the model's inputs, the observations (0 where missing), the mask of samples and
    the channels observed (at least 10 samples: the others' samples are not used)."""
    t = np.ascontiguousarray(t_s, dtype=float)
    if t.shape[0] < 10 or np.any(np.diff(t) <= 0.0):
        raise RefineError("the fit needs at least 10 frames in increasing time order")
    u = np.ascontiguousarray([model.inputs(row) for row in inputs], dtype=float)
    y = np.asarray(observations, float)
    mask = np.isfinite(y).astype(float)
    observed = mask.sum(axis=0) >= 10
    mask[:, ~observed] = 0.0
    y = np.ascontiguousarray(np.where(mask > 0, y, 0.0))
    return t, u, y, mask, observed


@blas.one_thread_during
def refine(
    model: Model,
    t_s: FloatArray,
    inputs: FloatArray,
    observations: FloatArray,
    start: FloatArray,
    noise_sigma: FloatArray,
    process_noise: FloatArray,
    max_step_s: float,
    linear_inputs: bool = True,
    estimate_process_noise: bool = True,
    iterations: int = 100,
    progress: Callable[[RefineProgress], None] | None = None,
    hold_noise: bool = False,
    threads: int | None = None,
    compared: FilterEstimate | None = None,
    delayed: Sequence[int] = (),
    factors: Sequence[tuple[int, float]] = (),
    pieces: Sequence[tuple[int, FloatArray]] = (),
) -> Refined:
    """Maximum likelihood over the record (t_s [N], inputs [N x 2 or 3], observations
    [N x 7], NaN where missing), from the augmented state `start` (flight states at
    t_s[0], coefficients, biases), by the package docstring's methods: output error
    (estimate_process_noise False), filter error with a steady-state gain (the process
    noise distribution and the innovations' covariance estimated with the parameters), or
    with hold_noise the noise levels kept at noise_sigma and process_noise (the sensors'
    and the air's known levels; filter error then runs the time-varying filter) and only
    the parameters fitted. `progress` hears after each Gauss-Newton iteration where the
    fit stands. The sensitivities' columns run in `threads` threads (default: the cores
    this process may use); the fit is the same whatever their number. compared: the
    filter's estimate the fit started from (refine_run), whose difference and structure
    sigma the fit's sigma takes in (sigma.fit_sigma). delayed: the model inputs (0 the
    elevator, 1 the throttle or thrust) whose delay relative to the response is fitted
    with the other parameters (from 0; decision 0044): the coefficients' sigma then
    includes what the data leave undecided about the inputs' timing. factors: airframe
    constants (an index into model.k, and a prior 1-sigma relative to the configured value)
    whose factor is fitted with the other parameters, from 1 with that prior (the
    propeller's thrust and zero-thrust airspeed; decision 0054): the coefficients' sigma
    then includes what the data leave undecided about them. pieces: where the
    record is several pieces (segments, flights: decision 0050), each further piece's
    first frame and its flight states' start [N_FLIGHT]: each piece is flown from its own
    flight states, fitted with the shared coefficients, biases, delays and factors."""
    t, u, y, mask, observed = _record(model, t_s, inputs, observations)
    lags = np.asarray(delayed, dtype=np.int64)
    firsts = np.array([first for first, _ in pieces], dtype=np.int64)
    prob = Problem(model, t, u, y, mask, max_step_s, linear_inputs, lags, factors, firsts)
    prob.pool = thread_pool(threads)
    starts = [np.asarray(s, float)[:N_FLIGHT] for _, s in pieces]
    x = np.concatenate(
        [np.asarray(start, float), np.zeros(lags.size), np.ones(len(factors)), *starts]
    )
    nd = model.arrays.n_dynamic
    q = np.asarray(process_noise, float)[:nd].copy() if estimate_process_noise else np.zeros(nd)
    r = np.where(observed, np.asarray(noise_sigma, float) ** 2, 1.0)
    e0, _, _, ok = prob.run(x, q, r)
    if not ok:
        raise RefineError(
            "the model, flown from the start values, does not stay finite; fit a shorter "
            "window (--window FROM:TO), or first the settings the warnings advise"
        )
    # Parameters the observations do not see (a bias of a channel without data) stay.
    probe = prob.jacobian(x, np.arange(x.shape[0]), q, r, e0)
    free = np.flatnonzero(np.linalg.norm(probe, axis=0) > 0.0)
    counter = _Progress(progress, prob)
    begin = _Start(prob, x, free, observed, q, r)
    if estimate_process_noise and not hold_noise:
        end = _steady_fit(begin, iterations, counter.report)
    else:
        end = _gauss_newton_fit(begin, iterations, hold_noise, counter.report)
    parts, extra_sigma, corr, colour = _sigmas(
        model, lags.size + len(factors), end, free, observed, mask, compared
    )
    n_bias = len(model.bias_names)
    coefficients = end.x[model.coefficients].copy()
    method = "filter error" if estimate_process_noise else "output error"
    if hold_noise:
        method += ", noise held"
    done = (
        "converged" if end.converged else f"stopped after {end.iterations} Gauss-Newton iterations"
    )
    return Refined(
        method=method,
        names=model.names,
        coefficients=coefficients,
        sigma_parts=parts,
        correlation=corr,
        identifiability=identifiability(coefficients, parts.sigma, corr),
        bias_names=model.bias_names,
        biases=end.x[model.biases].copy(),
        bias_sigma=extra_sigma[:n_bias],
        state0=end.x[:N_FLIGHT].copy(),
        noise_sigma=end.noise_sigma,
        process_noise=end.process_noise.copy(),
        residual_colour=colour,
        frames=int(t.shape[0]),
        iterations=counter.iterations,
        converged=end.converged,
        message=f"{done} ({prob.runs} filter runs)",
        delay_names=tuple(INPUT_NAMES[i] for i in lags),
        delays_s=end.x[model.n : prob.factor_start].copy(),
        delay_sigma_s=extra_sigma[n_bias : n_bias + lags.size],
        factor_names=tuple(FACTOR_NAMES[i] for i, _ in factors),
        factors=end.x[prob.factor_start : prob.pieces_start].copy(),
        factor_sigma=extra_sigma[n_bias + lags.size :],
        factor_prior_sigma=prob.factor_sigma.copy(),
    )
