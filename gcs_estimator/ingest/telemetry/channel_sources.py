"""Which message each of a vehicle's channels is taken from, and at what rate it arrives.

Real vehicles send one signal in several messages: ArduPlane the pitch rate in RAW_IMU,
SCALED_IMU2, SCALED_IMU3 and ATTITUDE.pitchspeed, PX4 in HIGHRES_IMU and ATTITUDE. Each
reading is a different sensor or filter with its own noise, lag and bias, so a channel's
stream takes one source at a time, never two interleaved (decision 0038): the one that
arrives fastest, and of equally fast ones the first in PRIORITY. A channel changes its
source only when another one arrives clearly faster (SWITCH_RATIO, both measured over
MIN_SAMPLES or more), or while the first few samples are still coming in and a better
source turns up (the first packets of a stream: ATTITUDE often comes before the IMU).
Every change is counted and said. Rates are measured by receive time, so a replay of a
recording measures what the live run did.

Nothing here reads a wall clock or a socket.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from gcs_estimator.ingest.telemetry.decode import Sample
from gcs_estimator.model.channels import OBS_NAMES, Channel

IMU_SOURCES = ("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")
"""IMU messages, best first at equal rates: HIGHRES_IMU (SI floats, PX4), the first IMU
(SCALED_IMU; ArduPilot's RAW_IMU is its first IMU too, scaled), then the second and third."""
PRIORITY: dict[str, tuple[str, ...]] = {
    "q": (*IMU_SOURCES, "ATTITUDE"),
    "a_x": IMU_SOURCES,
    "a_z": IMU_SOURCES,
    "elevator": ("SERVO_OUTPUT_RAW", "ACTUATOR_OUTPUT_STATUS"),
    "power": ("SERVO_OUTPUT_RAW", "ACTUATOR_OUTPUT_STATUS", "NAMED_VALUE_FLOAT"),
    "vz": ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "VFR_HUD"),
}
"""Sources of a channel in order of preference at equal rates (a message not listed
comes after those that are)."""

CHANNEL_NAMES: dict[Channel, str] = {
    **{Channel(i): n for i, n in enumerate(OBS_NAMES)},
    Channel.ELEVATOR: "elevator",
    Channel.POWER: "power",
    Channel.DENSITY: "density",
}

SHORT_PERIOD_MIN_HZ = 10.0
"""Below this rate a channel the short period shows in cannot carry it (decision 0038):
small fixed-wing aircraft have short-period frequencies of 1-3 Hz (6-20 rad/s); sampling
must exceed twice that (Nyquist) to see the mode at all, and the filters, which step the
motion from frame to frame, need some 3-5 samples per cycle to follow it."""
SLOW_MIN_HZ = 2.0
"""Airspeed, a_x and power follow the phugoid (periods of 10-30 s) and the throttle:
a few samples a second carry them."""
MIN_RATE_HZ: dict[str, float] = {
    "V": SLOW_MIN_HZ,
    "alpha": SHORT_PERIOD_MIN_HZ,
    "theta": SHORT_PERIOD_MIN_HZ,
    "q": SHORT_PERIOD_MIN_HZ,
    "qdot": SHORT_PERIOD_MIN_HZ,
    "a_x": SLOW_MIN_HZ,
    "a_z": SHORT_PERIOD_MIN_HZ,
    "elevator": SHORT_PERIOD_MIN_HZ,
    "power": SLOW_MIN_HZ,
}
"""The rate below which a channel's rate is warned about [Hz] (none for the others)."""

RATE_WINDOW_S = 5.0
"""Rates for the choice and the status line are over this much receive time [s]."""
MIN_SAMPLES = 5
"""A source's rate is known once this many of its samples arrived."""
SWITCH_RATIO = 1.5
"""A source replaces the one taken when it arrives this many times as fast."""


@dataclass
class _Meter:
    """One (channel, message)'s arrivals."""

    first: float
    last: float
    count: int = 0
    recent: deque[float] = field(default_factory=deque)

    def add(self, t: float) -> None:
        self.count += 1
        self.last = max(self.last, t)
        self.recent.append(t)
        while self.recent and self.recent[0] < t - RATE_WINDOW_S:
            self.recent.popleft()

    def rate(self, now: float) -> float:
        """Arrivals per second over the last RATE_WINDOW_S before now [Hz]."""
        n = sum(1 for t in self.recent if t > now - RATE_WINDOW_S)
        span = min(RATE_WINDOW_S, now - self.first)
        return n / span if n >= 2 and span > 0 else 0.0

    def mean_rate(self) -> float:
        """Arrivals per second over the whole session [Hz]."""
        span = self.last - self.first
        return (self.count - 1) / span if self.count > 1 and span > 0 else 0.0


def _rank(key: str, message: str) -> int:
    order = PRIORITY.get(key, ())
    return order.index(message) if message in order else len(order)


@dataclass
class _Channel:
    meters: dict[str, _Meter] = field(default_factory=dict)
    source: str | None = None
    taken: int = 0
    """Samples taken, from any source."""
    switches: int = 0

    def offer(self, key: str, message: str, t: float) -> tuple[bool, str | None]:
        """Whether a sample of `message` at receive time t is taken; and the source it
        replaced, if it made the channel change source."""
        meter = self.meters.get(message)
        if meter is None:
            meter = self.meters[message] = _Meter(t, t)
        meter.add(t)
        if self.source is None:
            self.source = message
        elif message != self.source and self._better(key, message, t):
            old, self.source = self.source, message
            settled = self.taken >= MIN_SAMPLES
            self.taken += 1
            if not settled:
                return True, None  # still choosing: not a switch
            self.switches += 1
            return True, old
        if message == self.source:
            self.taken += 1
            return True, None
        return False, None

    def _better(self, key: str, message: str, t: float) -> bool:
        assert self.source is not None
        current = self.meters[self.source]
        challenger = self.meters[message]
        ranked_higher = _rank(key, message) < _rank(key, self.source)
        if self.taken < MIN_SAMPLES:
            return ranked_higher  # the stream's first samples: a better source came up
        if challenger.count < MIN_SAMPLES:
            return False
        ratio = challenger.rate(t) / max(current.rate(t), 1e-9)
        return ratio > SWITCH_RATIO


@dataclass
class ChannelSources:
    """One vehicle's choice of source per channel and its rates."""

    system_id: int
    channels: dict[str, _Channel] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    """What changed (a channel's first source, each switch), for the link to print."""
    dropped: int = 0
    """Channel values not taken because another source feeds the channel."""
    t_last: float = -math.inf

    def choose(self, sample: Sample) -> Sample | None:
        """The sample with only the values of channels that take it as their source
        (None if none is left)."""
        t = sample.t_recv_s
        self.t_last = max(self.t_last, t)
        values = tuple(
            (ch, v)
            for ch, v in sample.values
            if self._take(CHANNEL_NAMES[Channel(ch)], sample.message, t)
        )
        aux = tuple((k, v) for k, v in sample.aux if self._take(k, sample.message, t))
        self.dropped += len(sample.values) - len(values) + len(sample.aux) - len(aux)
        if not values and not aux:
            return None
        return sample._replace(values=values, aux=aux)

    def _take(self, key: str, message: str, t: float) -> bool:
        channel = self.channels.get(key)
        if channel is None:
            channel = self.channels[key] = _Channel()
        taken, old = channel.offer(key, message, t)
        if taken and channel.taken == MIN_SAMPLES:
            self.notes.append(f"{key} from {channel.source}")
        if old is not None:
            rate = channel.meters[message].rate(t)
            self.notes.append(
                f"{key} now from {message} ({rate:.1f} Hz), not {old} "
                f"({channel.meters[old].rate(t):.1f} Hz)"
            )
        return taken

    def source(self, key: str) -> str | None:
        channel = self.channels.get(key)
        return None if channel is None else channel.source

    def rate(self, key: str, now: float | None = None) -> float:
        """The current source's recent rate [Hz] (0 if none)."""
        channel = self.channels.get(key)
        if channel is None or channel.source is None:
            return 0.0
        return channel.meters[channel.source].rate(self.t_last if now is None else now)

    def report(self) -> dict[str, dict[str, Any]]:
        """Per channel: its source, the source's mean rate over the session [Hz], the
        other sources heard and their rates, switches, and a warning where the rate is
        below MIN_RATE_HZ."""
        out: dict[str, dict[str, Any]] = {}
        for key in sorted(self.channels, key=_order):
            channel = self.channels[key]
            if channel.source is None:
                continue
            rate = channel.meters[channel.source].mean_rate()
            entry: dict[str, Any] = {"message": channel.source, "rate_hz": round(rate, 2)}
            others = {
                m: round(meter.mean_rate(), 2)
                for m, meter in channel.meters.items()
                if m != channel.source
            }
            if others:
                entry["others_hz"] = others
            if channel.switches:
                entry["switches"] = channel.switches
            low = low_rate(key, rate)
            if low:
                entry["warning"] = low
            out[key] = entry
        return out


def _order(key: str) -> tuple[int, str]:
    names = (*OBS_NAMES, "elevator", "power", "density")
    return (names.index(key), key) if key in names else (len(names), key)


def low_rate(key: str, rate_hz: float) -> str:
    """A warning if a channel's rate is too low to identify what it carries ("" if not)."""
    floor = MIN_RATE_HZ.get(key)
    if floor is None or rate_hz >= floor:
        return ""
    what = "the short period" if floor >= SHORT_PERIOD_MIN_HZ else "its motion"
    return f"{rate_hz:.1f} Hz is below {floor:g} Hz: too slow to identify {what} from"


def rates_line(report: dict[str, dict[str, Any]]) -> str:
    """One line: each channel's rate and source, "!" after a rate too low."""
    parts = []
    for key, entry in report.items():
        if key not in MIN_RATE_HZ:
            continue
        mark = "!" if "warning" in entry else ""
        parts.append(f"{key} {entry['rate_hz']:.1f}{mark} Hz {entry['message']}")
    return ", ".join(parts)
