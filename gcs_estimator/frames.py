"""The unit that flows from every source to the estimator: one synchronised frame."""

from __future__ import annotations

from dataclasses import dataclass

from gcs_estimator.arrays import FloatArray


@dataclass(frozen=True)
class Frame:
    """Synchronised inputs and observations of one vehicle at one vehicle time."""

    system_id: int
    t_vehicle_s: float
    """Vehicle clock [s] (the data's time for recordings)."""
    t_recv_s: float
    """Receive time of the newest sample in the frame [s since epoch]; the data's time
    for recordings."""
    inputs: FloatArray
    """[elevator rad, throttle 0..1 or thrust N]."""
    y: FloatArray
    """Observations [7] (model.channels), NaN where the channel is missing."""
    clock_reset: bool = False
    """First frame after the vehicle clock went back (the filters rebase their time)."""
    inputs_known: bool = True
    """False when an input sample of this frame was lost while the input changed: its
    value is a guess, and so is the state predicted with it."""
