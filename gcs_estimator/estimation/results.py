"""What a run of the estimator hands on: each filter's end (FilterResult), the run's
(EstimatorResult), a cheap look at the current estimates (Snapshot), and what went wrong
in a filter (Health). The view, the report and the metrics read these."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.filters.core import FilterKind, FilterState, Tuning
from gcs_estimator.estimation.history import Track
from gcs_estimator.estimation.noise import NoiseReading
from gcs_estimator.model.aircraft import Model


class Snapshot(NamedTuple):
    """A filter's current coefficient estimates (cheap: no history is read)."""

    coefficients: FloatArray
    sigma: FloatArray
    gust_sigma: float


@dataclass
class Health:
    """What went wrong in one filter over all passes (each step reports it)."""

    failed_updates: int = 0
    """Updates skipped because an innovation covariance was not positive definite."""
    covariance_repairs: int = 0
    """Times P lost positive definiteness to rounding and was repaired."""
    divergences: int = 0
    """Times the belief went non-finite and the filter started again from its prior."""

    def add(self, failed: int, repaired: int, diverged: int) -> None:
        self.failed_updates += failed
        self.covariance_repairs += repaired
        self.divergences += diverged


class FilterResult(NamedTuple):
    """The end of one filter's run."""

    kind: FilterKind
    coefficients: FloatArray
    sigma: FloatArray
    covariance: FloatArray
    """Coefficient covariance [p x p]."""
    gust_sigma: float
    """Turbulence level (vertical gust sigma) the filter ended with [m/s]."""
    biases: FloatArray
    """Estimated sensor biases ([sensors] bias_states; empty when none) [SI]."""
    bias_sigma: FloatArray
    health: Health
    track: Track | None
    """Time histories (None when the estimator keeps none)."""
    gust_pass_sigma: float = 0.0
    """Turbulence level averaged over the final pass, information-weighted [m/s]
    (GustState.pass_average)."""
    gust_pass_z: float = math.nan
    """That average in its standard errors (GustState.pass_z; NaN: nothing measured, as
    with [filter.turbulence] adaptive = false)."""

    @staticmethod
    def of(
        kind: FilterKind,
        s: FilterState,
        tuning: Tuning,
        model: Model,
        health: Health,
        track: Track | None,
    ) -> FilterResult:
        """The result of filter `kind` whose belief is s, stepped with `tuning`."""
        coef, biases = model.coefficients, model.biases
        cov = s.P[coef, coef]
        gust = s.gust.applied(tuning.detection2)
        return FilterResult(
            kind=kind,
            coefficients=s.x[coef].copy(),
            sigma=np.sqrt(np.diag(cov)),
            covariance=cov,
            gust_sigma=math.sqrt(gust),
            biases=s.x[biases].copy(),
            bias_sigma=np.sqrt(np.diag(s.P))[biases],
            health=health,
            track=track,
            gust_pass_sigma=math.sqrt(s.gust.pass_average()),
            gust_pass_z=s.gust.pass_z(),
        )


class EstimatorResult(NamedTuple):
    """What a run produced: all the view, the report and the metrics need."""

    config: AircraftConfig
    names: tuple[str, ...]
    frames: int
    restarts_done: int
    warm_start: FloatArray | None
    """Equation-error coefficients the first restart started from (None: no restart)."""
    filters: dict[FilterKind, FilterResult]
    bias_names: tuple[str, ...] = ()
    """Names of the estimated sensor biases, e.g. ("q_bias",)."""
    warm_start_samples: tuple[int, int, int] | None = None
    """Frames the warm start fitted per axis (CD, CL, Cm), of `warm_start_frames`."""
    warm_start_frames: int = 0
    gaps: int = 0
    """Frames after which the flight states started afresh (filters.core.MAX_GAP_S)."""
    frames_out_of_order: int = 0
    """Frames skipped because they were not after the previous one."""
    frames_banked_out: int = 0
    """Frames banked beyond [filter] bank_limit_deg: predicted through, not used in the
    update."""
    final_pass_from: int = 0
    """First frame whose history row is the final pass's (after the last restart's swap)."""
    state_names: tuple[str, ...] = ()
    """Every element of the augmented state, in order (flight states, gust states where
    modelled, coefficients, biases): the columns of a track's x and sigma."""
    measurement_sigma: tuple[float, ...] = ()
    """Measurement noise sigma per channel the final pass used (the configured, or the
    data's reading where [filter] measurement_noise = "auto" took it)."""
    noise_reading: NoiseReading | None = None
    """Each channel's noise as read from the data (None: none read); the final pass used
    it only where it was clearly below the configured sigma (noise.reading_z)."""
    segments: dict[str, Any] | None = None
    """The segments the filters stepped in and the frames left out, by reason
    (segments.Plan.as_json; live, the Gate's counts); None: every frame was used."""
    fresh_frames: tuple[int, ...] = ()
    """The frames (of the history) at which a segment or a flight began after frames
    left out: the flight states started afresh there (refine flies each piece from its
    own)."""
    flights: tuple[dict[str, Any], ...] = ()
    """With several flights of one airframe, each flight's part (Estimator.flight_parts):
    its frames, and per filter the coefficients and sigma after it and the share of each
    coefficient's variance it removed."""
