"""Results as Parquet tables: a batch's coefficients and flight summaries (one file
each for the whole batch), and a run's history (one row per frame, both filters side by
side).

The batch tables (decision 0042): one row per log, vehicle, filter and coefficient
(COEFFICIENT_COLUMNS), and one per log and vehicle (SUMMARY_COLUMNS). Every row carries
the log's path, its SHA-256, the config's SHA-256, the tool's version, the flight's time
and the vehicle's identity, so rows from many batches can be concatenated and still say
where they came from. A log that failed is one row of each table with `status` "failed",
its error, and nothing estimated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from gcs_estimator.config import POWER_COLUMNS
from gcs_estimator.estimation.filters.core import FilterKind
from gcs_estimator.estimation.history import Track
from gcs_estimator.estimation.results import EstimatorResult
from gcs_estimator.model.channels import OBS_NAMES, TURN_INPUTS
from gcs_estimator.uncertainty.result import VehicleResult

TABLE_VERSION = 1
"""The tables' layout; a reader refuses another."""

LOG_COLUMNS: dict[str, str] = {
    "log": "string",
    "log_sha256": "string",
    "config_sha256": "string",
    "version": "string",
    "flight_time_utc": "timestamp",
    "vehicle": "string",
    "system_id": "int32",
    "autopilot_uid": "string",
    "status": "string",
    "error": "string",
}
"""Columns of every row of both batch tables: where the row came from. flight_time_utc:
the log's first receive time (a .tlog) or the file's modification time; vehicle: the
user's name for it (a vehicle map), else "uid:<UID>" where the log carries the
autopilot's unique id (AUTOPILOT_VERSION), else "sys<ID>"; status: "ok" or "failed"."""

COEFFICIENT_COLUMNS: dict[str, str] = {
    **LOG_COLUMNS,
    "filter": "string",
    "coefficient": "string",
    "estimate": "float64",
    "sigma": "float64",
    "identifiability": "string",
    "truth": "float64",
}
"""One row per log, vehicle, filter and coefficient: the estimate, the sigma to trust
(sigma.trusted_sigma) and its identifiability mark; truth where the config has one."""

SUMMARY_COLUMNS: dict[str, str] = {
    **LOG_COLUMNS,
    "frames": "int64",
    "flight_s": "float64",
    "mean_nis_ekf": "float64",
    "mean_nis_iekf": "float64",
    "warnings": "int32",
    "seconds": "float64",
    "decode_s": "float64",
    "filter_s": "float64",
    "write_s": "float64",
    "worker": "string",
    "folder": "string",
}
"""One row per log and vehicle: frames, the flight's length, both filters' mean NIS, the
trust warnings, and where the time went (decode_s: reading and decoding; filter_s: the
filters and their summaries, the structure check's replays included; write_s: the result
files and history)."""


def _arrow_type(name: str) -> Any:
    import pyarrow as pa

    types = {
        "string": pa.string(),
        "int32": pa.int32(),
        "int64": pa.int64(),
        "float64": pa.float64(),
        "timestamp": pa.timestamp("us", tz="UTC"),
    }
    return types[name]


def schema(columns: Mapping[str, str]) -> Any:
    """The Arrow schema of a table's columns, with its layout version in the metadata."""
    import pyarrow as pa

    fields = [pa.field(n, _arrow_type(t)) for n, t in columns.items()]
    return pa.schema(fields, metadata={"gcs_estimator_table_version": str(TABLE_VERSION)})


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def coefficient_rows(base: Mapping[str, Any], vehicle: VehicleResult) -> list[dict[str, Any]]:
    """A vehicle's rows of the coefficient table: per filter and coefficient."""
    rows = []
    for kind, summary in vehicle.summaries.items():
        for c in summary.coefficients:
            rows.append(
                {
                    **base,
                    "filter": kind,
                    "coefficient": c.name,
                    "estimate": _finite(c.estimate),
                    "sigma": _finite(c.sigma),
                    "identifiability": c.identifiability,
                    "truth": _finite(c.truth),
                }
            )
    return rows


def summary_row(
    base: Mapping[str, Any], vehicle: VehicleResult, warnings: int, times: Mapping[str, float]
) -> dict[str, Any]:
    """A vehicle's row of the summary table."""
    result = vehicle.result
    nis = {k: _finite(s.mean_nis) for k, s in vehicle.summaries.items()}
    track = next((f.track for f in result.filters.values() if f.track is not None), None)
    flight = None
    if track is not None and len(track.t) > 1:
        flight = float(track.t[-1] - track.t[0])
    return {
        **base,
        "frames": result.frames,
        "flight_s": flight,
        "mean_nis_ekf": nis.get("EKF"),
        "mean_nis_iekf": nis.get("IEKF"),
        "warnings": warnings,
        **{k: times.get(k) for k in ("seconds", "decode_s", "filter_s", "write_s")},
    }


def failed_row(base: Mapping[str, Any], error: str) -> dict[str, Any]:
    """The one row of a log that failed (either table: the other columns empty)."""
    return {**base, "status": "failed", "error": error}


def write_table(rows: Sequence[Mapping[str, Any]], columns: Mapping[str, str], path: Path) -> Path:
    """The rows as a Parquet file (zstd-compressed); a column a row lacks is empty."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    sch = schema(columns)
    data = {n: [_cell(r.get(n), t) for r in rows] for n, t in columns.items()}
    table = pa.table(data, schema=sch)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    pq.write_table(table, tmp, compression="zstd")
    tmp.replace(path)  # a reader never sees half a table
    return path


def _cell(value: Any, kind: str) -> Any:
    if value is None:
        return None
    if kind == "timestamp" and isinstance(value, str):
        return datetime.fromisoformat(value)
    if kind.startswith("float") and isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def read_rows(path: Path) -> list[dict[str, Any]]:
    """A batch table's rows (checked to be this layout's)."""
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    meta = table.schema.metadata or {}
    version = meta.get(b"gcs_estimator_table_version")
    if version != str(TABLE_VERSION).encode():
        raise ValueError(
            f"{path}: not a gcs-estimator batch table of layout {TABLE_VERSION} "
            f"(found {version!r}); write it again with `gcs-estimator batch`"
        )
    rows: list[dict[str, Any]] = table.to_pylist()
    return rows


HISTORY_FORMATS = ("parquet", "csv")
"""How a run's history is written: Parquet (the default) or CSV (history_csv.py)."""


class HistoryParquet:
    """A run's history as Parquet, written as the run goes (HistoryCsv's interface): one
    row per frame with its time, inputs and measurements once, then each filter's
    estimates and sigmas of every state and coefficient, NIS and channels used (columns
    EKF_<state>, EKF_sigma_<state>, EKF_nis, EKF_channels, the same for IEKF). The
    estimates and sigmas are float32 as the history keeps them; floats are stored
    byte-split and zstd-compressed. A block of frames is a row group; the file is
    readable once closed (a killed process leaves no footer: the CSV is the format for
    that)."""

    def __init__(self, path: Path, state_names: Sequence[str], power_input: str) -> None:
        self.path = path
        self.names = list(state_names)
        self.power = POWER_COLUMNS[power_input]
        self.rows = 0
        """Frames written so far."""
        self._writer: Any = None
        path.parent.mkdir(parents=True, exist_ok=True)

    def _columns(self, tracks: Mapping[FilterKind, Track], a: int, n: int) -> dict[str, Any]:
        import pyarrow as pa

        first = next(iter(tracks.values()))
        cols: dict[str, Any] = {"t_s": pa.array(np.asarray(first.t[a:n], float))}
        inputs = ("in_elevator_rad", f"in_{self.power}", "in_air_density_kgpm3", *TURN_INPUTS)
        for k, name in enumerate(inputs):
            cols[name] = pa.array(np.asarray(first.u[a:n, k], float))
        for k, name in enumerate(OBS_NAMES):
            cols[f"meas_{name}"] = pa.array(np.asarray(first.y[a:n, k], float), from_pandas=True)
        for kind, tr in tracks.items():
            x = np.asarray(tr.x[a:n], np.float32)
            s = np.asarray(tr.sigma[a:n], np.float32)
            for k, name in enumerate(self.names):
                cols[f"{kind}_{name}"] = pa.array(x[:, k])
                cols[f"{kind}_sigma_{name}"] = pa.array(s[:, k])
            cols[f"{kind}_nis"] = pa.array(np.asarray(tr.nis[a:n], np.float32), from_pandas=True)
            cols[f"{kind}_channels"] = pa.array(np.asarray(tr.n_used[a:n]).astype(np.int8))
        return cols

    def append(self, tracks: Mapping[FilterKind, Track], stop: int) -> None:
        """Frames rows..stop (tracks may be longer)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        if not tracks:
            return
        n = min([stop, *(len(tr.t) for tr in tracks.values())])
        if n <= self.rows:
            return
        table = pa.table(self._columns(tracks, self.rows, n))
        if self._writer is None:
            floats = [f.name for f in table.schema if pa.types.is_floating(f.type)]
            self._writer = pq.ParquetWriter(
                self.path,
                table.schema,
                compression="zstd",
                use_byte_stream_split=floats,
                use_dictionary=False,
                write_statistics=False,
            )
        self._writer.write_table(table)
        self.rows = n

    def close(self) -> None:
        if self._writer is None:  # no frame: an empty file would not be Parquet
            self._writer = False
            return
        if self._writer:
            self._writer.close()
            self._writer = False


def write_history_parquet(
    path: Path, result: EstimatorResult, history: HistoryParquet | None = None
) -> None:
    """The whole history of a run as Parquet; given the one written as the run went,
    only the frames it does not hold yet, then it is closed."""
    if history is None:
        history = HistoryParquet(path, result.state_names, result.config.propulsion.input_name)
    tracks = {k: f.track for k, f in result.filters.items() if f.track is not None}
    history.append(tracks, max((len(t.t) for t in tracks.values()), default=0))
    history.close()
