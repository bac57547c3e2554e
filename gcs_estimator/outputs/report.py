"""A finished run's result files: its Table I as Markdown (table.py), everything as JSON
(results_json.py) and the history, as Parquet (tables.py) or CSV (history_csv.py); what
to check before trusting them is diagnosis.py's."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gcs_estimator.outputs.history_csv import HistoryCsv, write_history_csv
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.outputs.table import final_table
from gcs_estimator.outputs.tables import HistoryParquet, write_history_parquet
from gcs_estimator.uncertainty.result import VehicleResult

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined


def write_results(
    out_dir: Path,
    vehicle: VehicleResult,
    extra: Mapping[str, Any] | None = None,
    stem: str = "results",
    refined: Refined | None = None,
    history: HistoryCsv | HistoryParquet | None = None,
    history_format: str = "parquet",
) -> dict[str, Path]:
    """Write <stem>.json, <stem>.md and <stem>_history.csv (or .parquet) into out_dir (the
    history: the rest of the one written as the run went, where given); return their
    paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    data = results_dict(vehicle, extra, refined)
    paths = {
        "json": out_dir / f"{stem}.json",
        "markdown": out_dir / f"{stem}.md",
        history_format: history_path(out_dir, stem, history_format),
    }
    paths["json"].write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    title = f"# {vehicle.result.config.airframe.name}: estimated aerodynamic coefficients\n\n"
    paths["markdown"].write_text(title + final_table(vehicle, refined), encoding="utf-8")
    if isinstance(history, HistoryParquet) or (history is None and history_format == "parquet"):
        write_history_parquet(paths[history_format], vehicle.result, history)
    else:
        write_history_csv(paths[history_format], vehicle.result, history)
    return paths


def history_path(out_dir: Path, stem: str, history_format: str) -> Path:
    """A vehicle's history file: <stem>_history.csv or <stem>_history.parquet."""
    return out_dir / f"{stem}_history.{history_format}"


def open_history(
    out_dir: Path, stem: str, history_format: str, state_names: list[str], power: str
) -> HistoryCsv | HistoryParquet:
    """A history file to write as the run goes, in the format asked for."""
    path = history_path(out_dir, stem, history_format)
    if history_format == "parquet":
        return HistoryParquet(path, state_names, power)
    return HistoryCsv(path, state_names, power)
