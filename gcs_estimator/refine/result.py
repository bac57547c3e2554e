"""What a whole-record fit hands back: the fit (Refined), its progress, its failure."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.model.equations import MOTOR_K, PROP_COEF
from gcs_estimator.uncertainty.sigma import DELAY_WARNING_SIGMA, FitSigma

INPUT_NAMES: tuple[str, ...] = ("elevator", "throttle")
FACTOR_NAMES: dict[int, str] = {PROP_COEF: "thrust", MOTOR_K: "zero-thrust airspeed"}
"""The airframe constants (model.k indices) whose factor a fit can estimate, by name."""
"""The model's inputs whose delay a fit can estimate, by their index in the model's
inputs."""


FACTOR_TOLD = 0.5
"""A fitted factor whose sigma is below this share of its prior's was told apart by the
flight (the priors' information is then at most a quarter of the fit's)."""


def fit_label(method: str) -> str:
    """A fit's short name in tables and notes: "FE" for filter error (a Refined.method or
    a --method value), "OE" for output error."""
    return "FE" if method.replace("-", " ").startswith("filter error") else "OE"


@dataclass(frozen=True)
class Refined:
    """The maximum-likelihood fit of one record."""

    method: str
    """"output error" (no process noise) or "filter error" (process noise estimated:
    steady-state gain); ", noise held" added when the noise levels were held at the
    configured ones (filter error then runs the time-varying filter)."""
    names: tuple[str, ...]
    """Coefficient names."""
    coefficients: FloatArray
    sigma_parts: FitSigma
    """The coefficients' sigma to trust and its parts (uncertainty.sigma)."""
    correlation: FloatArray
    """Correlation of the coefficients [p x p] (from the Morelli-Klein covariance)."""
    identifiability: tuple[str, ...]
    bias_names: tuple[str, ...]
    biases: FloatArray
    bias_sigma: FloatArray
    """The fit's own sigma of the biases (FitSigma.within_fit: no filter compared)."""
    state0: FloatArray
    """Fitted initial flight state [V, alpha, theta, q]."""
    noise_sigma: FloatArray
    """Measurement noise sigma per observation channel [7] (NaN: not observed). Filter
    error with the noise estimated: what the innovations' variance leaves after the
    state's own uncertainty, sqrt(max(R - diag(C P C'), 0))."""
    process_noise: FloatArray
    """Process noise spectral density of V, alpha, theta, q (0 for output error; filter
    error: diag(F F'))."""
    residual_colour: FloatArray
    """Per channel: the information its residuals' autocorrelation leaves, relative to
    white residuals of the same variance, as seen through the parameters' sensitivities
    (trace of S^T Rvv S over trace of S^T rho(0) S): 1 for white residuals, larger when
    they are correlated in time (each sample then tells less)."""
    frames: int
    iterations: int
    converged: bool
    message: str
    choice: str = ""
    """Why this method, when it was chosen from the data ("auto": choose_method); empty
    when it was asked for by name."""
    delay_names: tuple[str, ...] = ()
    """The inputs whose delay relative to the response was fitted (decision 0044)."""
    delays_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    """Each one's delay behind the logged input [s], configured_delay_s included: positive
    where the response follows the logged input later than the model, flown on the input
    as logged, would."""
    configured_delay_s: float = 0.0
    """The delay the filters took the inputs with ([data] input_delay_s), from which the
    fit started."""
    delay_sigma_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    """Their sigma [s], from the fit's covariance (Morelli-Klein) and structure check as
    the biases' (NaN: the input never moved, so no delay was seen)."""

    factor_names: tuple[str, ...] = ()
    """The propeller model's guesses fitted as a factor on them (decision 0054)."""
    factors: FloatArray = field(default_factory=lambda: np.zeros(0))
    """Each one's factor on the airframe file's value (1: as derived or set)."""
    factor_sigma: FloatArray = field(default_factory=lambda: np.zeros(0))
    """Their sigma after the fit (the Morelli-Klein covariance, priors included)."""
    factor_prior_sigma: FloatArray = field(default_factory=lambda: np.zeros(0))
    """Their prior sigma (the airframe file's tolerance)."""

    def factor_text(self) -> str:
        """The fitted factors in words, and whether the flight told them from the drag
        (their sigma below FACTOR_TOLD of the prior's); "" where none was fitted."""
        parts = []
        for name, f, s, p in zip(
            self.factor_names,
            self.factors,
            self.factor_sigma,
            self.factor_prior_sigma,
            strict=True,
        ):
            told = math.isfinite(s) and s < FACTOR_TOLD * p
            how = "" if told else " (no better than the airframe file's guess)"
            parts.append(f"{name} x{f:.3f} ± {s:.3f}{how}")
        return ", ".join(parts)

    @property
    def label(self) -> str:
        """The fit's short name in tables and notes (fit_label)."""
        return fit_label(self.method)

    @property
    def sigma(self) -> FloatArray:
        """The coefficients' sigma to trust (FitSigma.sigma)."""
        return self.sigma_parts.sigma

    @property
    def crb_sigma(self) -> FloatArray:
        """The coefficients' Cramer-Rao sigma (white residuals assumed)."""
        return self.sigma_parts.cramer_rao

    @property
    def structure_sigma(self) -> FloatArray:
        """How far each coefficient depends on how much each channel is trusted (the fit
        re-made with one channel's weight halved at a time; decision 0017's check,
        applied to the whole-record fit): 0 where the model holds. Where the filter it
        started from was checked too (filter_structure_sigma), the larger of the two
        (decision 0031)."""
        return self.sigma_parts.structure

    @property
    def difference_sigma(self) -> FloatArray | None:
        """How far the fit lands from the filter it started from, beyond what their
        covariances allow (decision 0030); None for a fit not started from a filter's
        run."""
        return self.sigma_parts.difference

    @property
    def filter_structure_sigma(self) -> FloatArray | None:
        """The structure sigma of the filter the fit started from (its check of the same
        record; NaN where a coefficient was not checked), which structure_sigma does not
        fall below (decision 0031); None where the run made no check or refine_run was
        given a bare result."""
        return self.sigma_parts.filter_structure

    @property
    def sigma_within_fit(self) -> FloatArray:
        """The sigma from the fit alone: Morelli-Klein's with the structure sigma, without
        difference_sigma."""
        return self.sigma_parts.within_fit

    def delay_text(self) -> str:
        """The delays found, in words, and whether the filters' configured one is beyond
        3 sigma of them ("" where none was fitted)."""
        parts = []
        for name, d, s in zip(self.delay_names, self.delays_s, self.delay_sigma_s, strict=True):
            if not np.isfinite(s):
                parts.append(f"{name} not seen (it never moved)")
                continue
            text = f"{name} {1e3 * d:.1f} ± {1e3 * s:.1f} ms"
            if abs(d - self.configured_delay_s) > DELAY_WARNING_SIGMA * s:
                text += (
                    f" (the filters took {1e3 * self.configured_delay_s:.0f} ms: "
                    f"[data] input_delay_s = {max(d, 0.0):.3f} would fly them at it)"
                )
            parts.append(text)
        return ", ".join(parts)


class RefineProgress(NamedTuple):
    """Where a fit stands, after each Gauss-Newton iteration."""

    iterations: int
    """Gauss-Newton iterations so far."""
    cost: float
    """Negative log-likelihood (times 2, without its constant) the iteration started
    from."""
    step_sigma: float
    """Largest parameter step of the iteration, in sigmas (about); 0: none accepted."""
    runs: int
    """Filter runs (flights of the model over the record) so far."""


class RefineError(RuntimeError):
    """The fit could not be made (the model, flown over the record, leaves finite
    numbers from the start, or the record holds too few observations)."""
