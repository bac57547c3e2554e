"""The model checked on what it was not fitted to: per channel Theil's inequality
coefficient and RMS error of the identified model's prediction of a held-out segment,
and the marks that drop where it misses (decision 0051). The prediction itself is
refine.holdout's (the model flown with the filters' compiled steps).

Theil's inequality coefficient (Jategaonkar 2015, ch. 11),

    U = sqrt(mean((y - ym)^2)) / (sqrt(mean(y^2)) + sqrt(mean(ym^2))),

is 0 for a perfect prediction and 1 for none; flight-test practice reads U < 0.3 as
good agreement. U is taken on each channel's variation about its mean over the segment
(a channel's level, airspeed's 24 m/s say, would otherwise make any prediction look
good), and only where that variation stands clear of the sensor's noise (JUDGED_SNR):
a channel the segment hardly moves cannot show whether the model predicts it.

The verdict reads the model's share of U: the numerator with the sensor's noise taken
out, sqrt(max(mean((y - ym)^2) - sigma^2, 0)). The noise alone gives the exact model a U
of up to 0.14 on alpha's small variation on the NOC flight, while halving Cmq moves q's
model share from 0.01-0.03 to 0.17 and qdot's to 0.15 over a multistep (seeds 2 and 5,
1-16 s, re-anchored every 10 s); THEIL_LIMIT sits between. It is tighter than the
0.3 of flight-test practice because it is on the variation, without the noise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.model.channels import N_OBS, OBS_NAMES
from gcs_estimator.uncertainty.metrics import IDENTIFIED, WEAK, FilterSummary

THEIL_LIMIT = 0.12
"""A judged channel whose model share of U (module docstring) is above this misses the
held-out segment."""
JUDGED_SNR = 3.0
"""A channel is judged where the RMS of its measured variation is at least this many
times its noise sigma."""
CHANNEL_AXES: dict[str, tuple[str, ...]] = {
    "V": ("CD",),
    "alpha": ("CL",),
    "theta": ("Cm",),
    "q": ("Cm",),
    "qdot": ("Cm",),
    "a_x": ("CD",),
    "a_z": ("CL",),
}
"""The coefficients (by axis) whose equation drives each channel most directly: the
drag equation the airspeed and a_x, the lift equation alpha and a_z, the pitching
moment q, its rate and the pitch angle it integrates to."""


def theil(y: FloatArray, ym: FloatArray) -> float:
    """Theil's inequality coefficient of the prediction ym of y (NaN: both all zero)."""
    num = math.sqrt(float(np.mean((y - ym) ** 2)))
    den = math.sqrt(float(np.mean(y * y))) + math.sqrt(float(np.mean(ym * ym)))
    return num / den if den > 0.0 else math.nan


@dataclass(frozen=True)
class ChannelFit:
    """One channel's prediction of the held-out segment."""

    name: str
    samples: int
    theil: float
    theil_model: float
    """U with the sensor's noise taken out of its numerator: the model's share."""
    rms_error: float
    """RMS of measured - predicted [SI]."""
    judged: bool
    """Whether the segment moved the channel clear of its noise (JUDGED_SNR)."""

    @property
    def misses(self) -> bool:
        return self.judged and self.theil_model > THEIL_LIMIT


def channel_fits(
    y: FloatArray,
    predicted: FloatArray,
    mask: FloatArray,
    noise_sigma: Sequence[float] | FloatArray,
) -> tuple[ChannelFit, ...]:
    """Each observed channel's Theil U and RMS error over the samples in mask [N x 7]."""
    out = []
    for c in range(N_OBS):
        rows = mask[:, c] > 0.0
        n = int(rows.sum())
        if n < 2:
            continue
        yc, pc = y[rows, c], predicted[rows, c]
        mean = float(np.mean(yc))
        spread = math.sqrt(float(np.mean((yc - mean) ** 2)))
        sd = float(noise_sigma[c])
        judged = math.isfinite(sd) and spread >= JUDGED_SNR * sd
        rms = math.sqrt(float(np.mean((yc - pc) ** 2)))
        u = theil(yc - mean, pc - mean)
        excess = math.sqrt(max(rms * rms - sd * sd, 0.0)) if math.isfinite(sd) else rms
        share = u * excess / rms if rms > 0.0 else 0.0
        out.append(ChannelFit(OBS_NAMES[c], n, u, share, rms, judged))
    return tuple(out)


@dataclass(frozen=True)
class Holdout:
    """The held-out check of one run."""

    segment: str
    """What was held out, in words (a window of the record, or another log)."""
    coefficients_from: str
    """Whose estimates were checked (a filter's or refine's)."""
    method: str
    """How the model was flown over the segment, in words."""
    channels: tuple[ChannelFit, ...]
    t: FloatArray
    """The segment's times [N] (the record's clock)."""
    measured: FloatArray
    """[N x 7], NaN where missing."""
    predicted: FloatArray
    """[N x 7], NaN where missing."""
    in_sample: bool = False
    """Whether the estimates were fitted to these frames too (then it is no held-out test)."""

    @property
    def missed(self) -> tuple[ChannelFit, ...]:
        return tuple(c for c in self.channels if c.misses)

    def drops(self, names: Sequence[str], axes: Sequence[str]) -> dict[str, str]:
        """The coefficients whose marks drop to weak, each with why."""
        out: dict[str, str] = {}
        for fit in self.missed:
            for name, axis in zip(names, axes, strict=True):
                if axis in CHANNEL_AXES[fit.name] and name not in out:
                    out[name] = (
                        f"the model misses {fit.name} on {self.segment} (held out; Theil U "
                        f"{fit.theil:.2f}, its model share {fit.theil_model:.2f} > {THEIL_LIMIT:g})"
                    )
        return out

    def lines(self) -> list[str]:
        """The check in words: one line per channel."""
        head = f"held-out check on {self.segment} ({self.coefficients_from}; {self.method})"
        if self.in_sample:
            head += "; the estimates saw these frames too: not independent"
        out = [head + ":"]
        for c in self.channels:
            verdict = "MISSES" if c.misses else ("good" if c.judged else "not moved: not judged")
            out.append(
                f"  {c.name:<5} U {c.theil:5.2f} (model {c.theil_model:4.2f})  "
                f"RMS error {c.rms_error:.3g}  "
                f"({c.samples} samples; {verdict})"
            )
        return out

    def as_dict(self) -> dict[str, Any]:
        return {
            "segment": self.segment,
            "coefficients_from": self.coefficients_from,
            "method": self.method,
            "in_sample": self.in_sample,
            "theil_limit": THEIL_LIMIT,
            "channels": {
                c.name: {
                    "theil": c.theil,
                    "theil_model": c.theil_model,
                    "rms_error": c.rms_error,
                    "samples": c.samples,
                    "judged": c.judged,
                    "misses": c.misses,
                }
                for c in self.channels
            },
        }


def dropped_marks(
    marks: Sequence[str], names: Sequence[str], drops: dict[str, str]
) -> tuple[str, ...]:
    """marks with each identified coefficient in `drops` weak."""
    return tuple(
        WEAK if (n in drops and m == IDENTIFIED) else m for n, m in zip(names, marks, strict=True)
    )


def dropped_summary(s: FilterSummary, drops: dict[str, str]) -> FilterSummary:
    """A filter's summary with the marks in `drops` dropped to weak."""
    coefficients = tuple(
        replace(c, identifiability=WEAK)
        if c.name in drops and c.identifiability == IDENTIFIED
        else c
        for c in s.coefficients
    )
    return replace(s, coefficients=coefficients)
