"""What a run gives for one vehicle: the estimator's result, each filter's summary (the
sigma to trust and the marks) and the structure check."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.estimator import EstimatorResult, FilterKind
from gcs_estimator.uncertainty.advice import Advice
from gcs_estimator.uncertainty.holdout import Holdout
from gcs_estimator.uncertainty.metrics import FilterSummary
from gcs_estimator.uncertainty.weighting import StructureCheck


@dataclass(frozen=True)
class VehicleResult:
    """The end of one vehicle's run: the estimator's result and its summaries."""

    system_id: int
    result: EstimatorResult
    summaries: dict[FilterKind, FilterSummary]
    truth: FloatArray | None
    structure: StructureCheck | None = None
    """The structure check (weighting.py); None: not asked about (a result made
    without a session)."""
    updated: bool | None = None
    """Whether any frame updated a filter with a channel, where the result's tracks were
    left where they were made (a filter worker's, without_tracks); None: read the
    tracks."""
    advice: Advice | None = None
    """What to fly next (advice.advice_of); None: not computed."""
    holdout: Holdout | None = None
    """The held-out check (--validate; decision 0051); None: not asked for."""
    holdout_drops: dict[str, str] | None = None
    """The coefficients whose marks the held-out check dropped to weak, each with why."""
    compatibility: dict[str, Any] | None = None
    """The data compatibility check of the run's frames (ingest/compat.py of_frames,
    Compatibility.as_dict: a link's or a tlog's, which no reader checked); None: not made
    here (a log's is made as it is read, and is in the run's notes)."""

    def without_tracks(self) -> VehicleResult:
        """This result without its time histories (what a filter worker sends back: they
        are in the history CSV it wrote), with whether any frame updated a filter."""
        filters = {k: f._replace(track=None) for k, f in self.result.filters.items()}
        result = self.result._replace(filters=filters)
        return replace(self, result=result, updated=self.any_update())

    def any_update(self) -> bool:
        """Whether any frame updated either filter with a channel (a result without
        tracks counts as updated)."""
        if self.updated is not None:
            return self.updated
        return any(
            f.track is None or bool(np.any(f.track.n_used > 0))
            for f in self.result.filters.values()
        )
