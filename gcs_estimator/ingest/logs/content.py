"""What a preset finds in a log: each channel's samples with its source, the vehicle, and
when it flew. The readers (dataflash, ulog) give arrays; a preset (presets) says which
message or topic gives which channel; reader.py turns a LogContent into a Recording."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gcs_estimator.arrays import FloatArray

Span = tuple[float, float]
"""A time interval [s] on the log's clock."""

MEASURED = ("airspeed", "alpha", "theta", "q", "qdot", "a_x", "a_z")
"""The observation channels, in the Recording's column order."""
INPUTS = ("elevator", "throttle", "rho")
AUX = ("phi", "p", "r", "vz", "wind_n", "wind_e", "psi", "vn", "ve", "vd")
"""Signals carried on the Recording for later use (roll, roll and yaw rates, vertical speed
positive down, the wind's north and east components, the heading (unwrapped: no jump at
north), the GPS velocity north, east, down), unused by the filters; the data
compatibility check (ingest/compat.py) reads them."""


@dataclass(frozen=True)
class Signal:
    """One channel's samples in SI (angles in radians, throttle 0..1; the elevator as the
    autopilot's normalised command, -1..1, positive nose-up) and where they came from."""

    t_s: FloatArray
    values: FloatArray
    source: str
    """Message and field, e.g. "IMU.GyrY", with what was done to it."""

    def __post_init__(self) -> None:
        """Samples without a number dropped, the rest in time order, a repeated time once."""
        keep = np.isfinite(self.t_s) & np.isfinite(self.values)
        t, v = (self.t_s, self.values) if keep.all() else (self.t_s[keep], self.values[keep])
        step = np.diff(t)
        if np.any(step < 0):  # out of order: the rare case, sorted
            order = np.argsort(t, kind="stable")
            t, v = t[order], v[order]
            step = np.diff(t)
        if np.any(step == 0):
            fresh = np.concatenate([[True], step > 0])
            t, v = t[fresh], v[fresh]
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "values", v)

    def rate_hz(self, span: Span | None = None) -> float:
        t = self.t_s if span is None else self.t_s[(self.t_s >= span[0]) & (self.t_s <= span[1])]
        if len(t) < 2:
            return 0.0
        return float((len(t) - 1) / (t[-1] - t[0])) if t[-1] > t[0] else 0.0


@dataclass
class LogContent:
    """A log as a preset reads it."""

    autopilot: str
    """Firmware and version, e.g. "ArduPlane V4.2.3"."""
    vehicle: str
    """What flew, in words: "fixed-wing", "QuadPlane (VTOL)", "multirotor", ..."""
    fixed_wing: bool
    """Whether the vehicle flies on a wing at all (a VTOL does, between hovers)."""
    span_s: Span
    airborne: list[Span] | None
    """When the vehicle was in the air, from the autopilot's own judgement; None: the log
    does not say."""
    airborne_source: str = ""
    hover: list[Span] = field(default_factory=list)
    """Airborne intervals in which a VTOL flew as a multirotor."""
    signals: dict[str, Signal] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    elevator_normalised: bool = True
    """The elevator signal is the autopilot's -1..1 command (the travel turns it into
    degrees); False: it is already an angle in radians, positive nose-up."""
