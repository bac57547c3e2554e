"""A finished run's result files: its Table I as Markdown (table.py), everything as JSON
(results_json.py) and the history CSV (history_csv.py); what to check before trusting
them is diagnosis.py's."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gcs_estimator.outputs.history_csv import HistoryCsv, write_history_csv
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.outputs.table import final_table
from gcs_estimator.uncertainty.result import VehicleResult

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined


def write_results(
    out_dir: Path,
    vehicle: VehicleResult,
    extra: Mapping[str, Any] | None = None,
    stem: str = "results",
    refined: Refined | None = None,
    history: HistoryCsv | None = None,
) -> dict[str, Path]:
    """Write <stem>.json, <stem>.md and <stem>_history.csv into out_dir (the history: the
    rest of the one written as the run went, where given); return their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    data = results_dict(vehicle, extra, refined)
    paths = {
        "json": out_dir / f"{stem}.json",
        "markdown": out_dir / f"{stem}.md",
        "csv": out_dir / f"{stem}_history.csv",
    }
    paths["json"].write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    title = f"# {vehicle.result.config.airframe.name}: estimated aerodynamic coefficients\n\n"
    paths["markdown"].write_text(title + final_table(vehicle, refined), encoding="utf-8")
    write_history_csv(paths["csv"], vehicle.result, history)
    return paths
