"""PX4 ULog files through pyulog: only the topics a preset asks for, as arrays per topic."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gcs_estimator.ingest.flightdata import FlightDataError


class ULogError(FlightDataError):
    """A file is not a ULog pyulog can read."""


@dataclass
class ULogData:
    """The asked topics of a ULog (first instance of each unless asked otherwise), its
    parameters and its info fields."""

    path: Path
    topics: dict[tuple[str, int], dict[str, NDArray[np.generic]]]
    params: dict[str, float]
    info: dict[str, object]
    size_bytes: int = 0
    dropouts: int = 0
    extra: dict[str, object] = field(default_factory=dict)

    def topic(self, name: str, instance: int = 0) -> dict[str, NDArray[np.generic]] | None:
        return self.topics.get((name, instance))

    def has(self, name: str, column: str | None = None) -> bool:
        t = self.topic(name)
        return t is not None and len(t.get("timestamp", ())) > 0 and (column is None or column in t)


def read(
    path: str | Path, topics: Sequence[str], progress: Callable[[float], None] | None = None
) -> ULogData:
    """Read the named topics of a ULog (pyulog parses only those)."""
    from pyulog import ULog  # imported here: only a ULog needs it

    p = Path(path)
    if progress is not None:
        progress(0.0)
    try:
        u = ULog(str(p), message_name_filter_list=list(topics))
    except (OSError, ValueError, IndexError, TypeError) as exc:  # pyulog's errors
        raise ULogError(f"{p}: not a ULog pyulog can read: {exc}") from exc
    if progress is not None:
        progress(1.0)
    data = {(d.name, d.multi_id): dict(d.data) for d in u.data_list}
    params = {k: float(v) for k, v in u.initial_parameters.items()}
    for _t, name, value in getattr(u, "changed_parameters", []):
        params[name] = float(value)
    return ULogData(
        p,
        data,
        params,
        dict(u.msg_info_dict),
        size_bytes=p.stat().st_size,
        dropouts=len(u.dropouts),
        extra={"start_us": u.start_timestamp, "last_us": u.last_timestamp},
    )
