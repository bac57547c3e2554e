"""Recorded flights as the filters take them: each flight's segments (estimation/
segments.py), and several flights of one airframe in a row, one set of coefficients from
all of them (decision 0050).

The flights follow one another on one clock: each is shifted to begin FLIGHT_SPACING_S
after the one before ends, its first frame used starting the flight states afresh (the
coefficients and their covariance carried). The segments keep each flight's own times.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, ConfigError
from gcs_estimator.estimation import segments
from gcs_estimator.estimation.segments import Limits, Plan, Window
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.runtime.session import RecordingSource

FLIGHT_SPACING_S = 10.0
"""Time between one flight's last frame and the next one's first on the run's clock [s]:
more than the filters' longest prediction, so that nothing is flown across."""


class NoSegmentError(ConfigError):
    """No frame of the record lies in a segment the model covers: nothing to estimate."""


def limits_of(config: AircraftConfig, windows: Sequence[Window] = ()) -> Limits:
    """The segments' limits for the airframe (its trim airspeed) and the --window given."""
    return Limits(
        config.airframe.trim_airspeed_mps,
        max_bank_rad=math.radians(config.filter.bank_limit_deg),
        windows=tuple(windows),
    )


def plan_of(rec: Recording, limits: Limits, flight: int = 0) -> Plan:
    """A recording's segments (segments.find over its airspeed and its aux signals)."""
    return segments.find(rec.t_s, rec.measurements[:, 0], rec.aux, limits, flight)


def _inputs(recs: Sequence[Recording]) -> FloatArray:
    """The recordings' inputs in a row, with an air density column (NaN: the airframe's)
    where some has one."""
    width = max(r.inputs.shape[1] for r in recs)
    parts = []
    for r in recs:
        pad = np.full((len(r), width - r.inputs.shape[1]), np.nan)
        parts.append(np.hstack([r.inputs, pad]))
    return np.vstack(parts)


def source_of(recs: Sequence[Recording], names: Sequence[str], limits: Limits) -> RecordingSource:
    """The flights' frames in a row for the filters, only those of their segments (a
    NoSegmentError where none has one, naming what was left out)."""
    plans = [plan_of(r, limits, j) for j, r in enumerate(recs)]
    offsets = np.cumsum([0] + [len(r) for r in recs[:-1]]).tolist()
    plan = segments.merged(plans, offsets)
    if not plan.segments:
        raise NoSegmentError(
            f"{', '.join(names)}: no segment the model covers ({plan.summary()}): nothing to "
            "estimate (a --window outside the flight, or [airframe] trim_airspeed_mps far "
            "from the airspeeds flown?)"
        )
    times: list[FloatArray] = []
    end = 0.0
    for j, r in enumerate(recs):
        shift = 0.0 if j == 0 else end + FLIGHT_SPACING_S - float(r.t_s[0])
        times.append(r.t_s + shift)
        end = float(times[-1][-1])
    known = None
    if any(r.inputs_known is not None for r in recs):
        known = np.concatenate(
            [r.inputs_known if r.inputs_known is not None else np.ones(len(r), bool) for r in recs]
        )
    flights = [(n, o) for n, o in zip(names, offsets, strict=True)] if len(recs) > 1 else []
    return RecordingSource(
        np.concatenate(times),
        _inputs(recs),
        np.vstack([r.measurements for r in recs]),
        known,
        plan=plan,
        flights=flights,
    )


def what_flew(account: str | None) -> str | None:
    """What a flight's log says flew (its account's autopilot and vehicle, the firmware's
    version left out: one aircraft may be updated between flights); None for a data file,
    which does not say."""
    if not account:
        return None
    _, _, rest = account.partition(": ")
    autopilot, _, rest = rest.partition(", ")
    vehicle = rest.partition(", ")[0]
    return f"{autopilot.split(' ')[0]} {vehicle}".strip()


def check_one_aircraft(flew: Sequence[tuple[str, str | None]]) -> None:
    """Refuse flights whose logs say different vehicles flew (ConfigError naming two)."""
    known = [(name, what) for name, what in flew if what is not None]
    for name, what in known[1:]:
        first, kind = known[0]
        if what != kind:
            raise ConfigError(
                f"the logs say different aircraft flew ({first}: {kind}; {name}: {what}): "
                "flights estimated together must be of one aircraft (one airframe file); "
                "estimate them apart"
            )


def tlog_recording(path: str, config: AircraftConfig) -> Recording:
    """A .tlog's flight as a Recording: the frames its first vehicle's messages make, as
    a replay would step them (the link decodes and synchronises them; ingest.sources)."""
    from gcs_estimator.ingest.sources import TlogSource
    from gcs_estimator.ingest.telemetry.link import link_of
    from gcs_estimator.stop import Stop

    link = link_of(config)
    source = TlogSource([path], link)
    frames = [f for f in source.frames(Stop()) if f is not None]
    source.close()
    if frames:
        first = frames[0].system_id
        frames = [f for f in frames if f.system_id == first]
    if not frames:
        raise ConfigError(f"{path}: no frame could be made of its messages: nothing to estimate")
    kept, last = [], -np.inf
    for f in frames:  # in time order: a frame not after the one before is skipped
        if f.t_vehicle_s > last:
            kept.append(f)
            last = f.t_vehicle_s
    width = max(len(f.inputs) for f in kept)
    inputs = np.full((len(kept), width), np.nan)
    for i, f in enumerate(kept):
        inputs[i, : len(f.inputs)] = f.inputs
    return Recording(
        np.array([f.t_vehicle_s for f in kept]),
        inputs,
        np.array([f.y for f in kept], float),
        config.propulsion.input_name,
        inputs_known=np.array([f.inputs_known for f in kept]),
    )
