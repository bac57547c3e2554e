"""The history CSV: one row per filter and frame, written as the run goes."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from gcs_estimator.config import POWER_COLUMNS
from gcs_estimator.estimation.filters.core import FilterKind
from gcs_estimator.estimation.history import Track
from gcs_estimator.estimation.results import EstimatorResult
from gcs_estimator.model.channels import OBS_NAMES, TURN_INPUTS


class HistoryCsv:
    """The history CSV, written as the run goes: one row per filter and frame with the
    estimates and sigmas of every state and coefficient, NIS, channels used, and the
    frame's inputs and measurements.

    Rows come in blocks of frames (append), each block the EKF's rows then the IEKF's,
    so within a filter the rows are in frame order; a stop then writes only the last
    block, whatever the flight's length, and the file holds what was processed even if
    the process is killed.

    Each value is written as the shortest text that reads back as the number kept: the
    estimates and sigmas to the history's float32 (history.HISTORY_DTYPE, 7 significant
    digits), times, inputs and measurements to float64; an empty cell where a value is
    missing. Arrow's CSV writer formats whole columns (an hour's history in seconds)."""

    def __init__(self, path: Path, state_names: Sequence[str], power_input: str) -> None:
        names = list(state_names)
        power = POWER_COLUMNS[power_input]
        self.header = (
            ["filter", "t_s"]
            + names
            + [f"sigma_{n}" for n in names]
            + ["nis", "channels", "in_elevator_rad", f"in_{power}", "in_air_density_kgpm3"]
            + list(TURN_INPUTS)
            + [f"meas_{n}" for n in OBS_NAMES]
        )
        self.rows = 0
        """Frames written so far (per filter)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO | None = open(path, "wb")  # noqa: SIM115 (closed by close())
        self._fh.write((",".join(self.header) + "\n").encode())
        self._fh.flush()

    def append(self, tracks: Mapping[FilterKind, Track], stop: int) -> None:
        """Frames rows..stop of each filter's track (a track may be longer)."""
        import pyarrow as pa
        import pyarrow.csv as pacsv

        if self._fh is None or stop <= self.rows:
            return
        options = pacsv.WriteOptions(include_header=False, quoting_style="none")
        a = self.rows
        for kind, tr in tracks.items():
            n = min(stop, len(tr.t))
            if n <= a:
                continue
            columns = [
                pa.array([kind] * (n - a)),
                pa.array(np.asarray(tr.t[a:n], float)),
                *_arrow_columns(tr.x[a:n]),
                *_arrow_columns(tr.sigma[a:n]),
                *_arrow_columns(tr.nis[a:n, None], blank_nan=True),
                pa.array(np.asarray(tr.n_used[a:n]).astype(np.int64)),
                *_arrow_columns(tr.u[a:n], blank_nan=True),
                *_arrow_columns(tr.y[a:n], blank_nan=True),
            ]
            pacsv.write_csv(pa.table(columns, names=self.header), self._fh, options)
        self._fh.flush()
        self.rows = stop

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def write_history_csv(path: Path, result: EstimatorResult, csv: HistoryCsv | None = None) -> None:
    """The whole history CSV of a run (HistoryCsv); given the one written as the run
    went, only the frames it does not hold yet, then it is closed."""
    if csv is None:
        csv = HistoryCsv(path, result.state_names, result.config.propulsion.input_name)
    tracks = {k: f.track for k, f in result.filters.items() if f.track is not None}
    csv.append(tracks, max((len(t.t) for t in tracks.values()), default=0))
    csv.close()


def _arrow_columns(values: np.ndarray, blank_nan: bool = False) -> list[Any]:
    """Each column of a [N x k] array as an Arrow array (NaN as a missing value: an empty
    cell, where blank_nan)."""
    import pyarrow as pa

    return [pa.array(np.asarray(c), from_pandas=blank_nan) for c in np.asarray(values).T]
