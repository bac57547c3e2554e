"""How numbers and notes read in the tables, the warnings and the terminal."""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence

from gcs_estimator.arrays import FloatArray
from gcs_estimator.model.channels import OBS_NAMES

TERMINAL_WIDTH = 100
"""Columns the terminal's lines may take (its table, status lines and notes)."""


def fmt(v: float | None, digits: int = 4) -> str:
    """A coefficient's value: `digits` decimals, or significant digits below 1e-3 ("-":
    none)."""
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.{digits}g}" if abs(v) < 1e-3 and v != 0 else f"{v:.{digits}f}"


def fmt_sigma(v: float) -> str:
    """A sigma: two significant digits ("-": none)."""
    return f"{v:.2g}" if math.isfinite(v) else "-"


def fmt_time(v: float | None) -> str:
    """A time [s] to a tenth ("never": none)."""
    return "never" if v is None or not math.isfinite(v) else f"{v:.1f}"


def channel_text(values: FloatArray | Sequence[float]) -> str:
    """'V 0.13, alpha 0.001, ...' for the channels with a value."""
    return ", ".join(
        f"{n} {v:.3g}" for n, v in zip(OBS_NAMES, values, strict=True) if math.isfinite(v)
    )


def wrap(text: str, width: int = TERMINAL_WIDTH, first: str = "") -> str:
    """text wrapped to `width` columns between its words (a word, a path or a key stays
    whole), after `first` on the first line and indented two columns on the rest."""
    return textwrap.fill(
        text,
        width,
        initial_indent=first,
        subsequent_indent="  ",
        break_long_words=False,
        break_on_hyphens=False,
    )


def bullets(items: Sequence[str], width: int | None = None) -> str:
    """Markdown list items, one a line, or wrapped to `width` columns with the item's
    continuation indented under its text."""
    if width is None:
        return "".join(f"- {item}\n" for item in items)
    return "".join(wrap(item, width, "- ") + "\n" for item in items)
