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
from typing import Any, NamedTuple

from gcs_estimator.ingest.telemetry.decode import Sample, with_values
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
    Channel.PHI: "phi",
    Channel.ROLL_RATE: "p",
    Channel.YAW_RATE: "r",
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


RECENT = 512
"""Arrival times a meter keeps (RATE_WINDOW_S at up to 100 Hz)."""
CHECK_EVERY_S = 1.0
"""A settled channel weighs each challenger's rate at most this often [s]."""


@dataclass
class _Meter:
    """One message's arrivals (every sample of a message carries all its channels)."""

    first: float
    last: float
    count: int = 0
    recent: deque[float] = field(default_factory=lambda: deque(maxlen=RECENT))

    def add(self, t: float) -> None:
        self.count += 1
        if t > self.last:
            self.last = t
        self.recent.append(t)

    def extend(self, times: list[float]) -> None:
        """add() of each of these times in turn."""
        self.count += len(times)
        newest = max(times)
        if newest > self.last:
            self.last = newest
        self.recent.extend(times)

    def rate(self, now: float) -> float:
        """Arrivals per second over the last RATE_WINDOW_S before now [Hz]."""
        since = now - RATE_WINDOW_S
        n = sum(1 for t in self.recent if t > since)
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
    source: str
    heard: set[str] = field(default_factory=set)
    """Every message heard carrying this channel."""
    taken: int = 0
    """Samples taken, from any source."""
    switches: int = 0
    next_check: dict[str, float] = field(default_factory=dict)
    """Per challenger: when its rate is weighed next [s of receive time]."""


class _Kept(NamedTuple):
    """Which values of a sample of one shape pass (ChannelSources._partly)."""

    values: tuple[bool, ...]
    aux: tuple[bool, ...]
    until: float
    """The receive time from which a dropped channel weighs this message again [s]."""


NAMES: tuple[str, ...] = tuple(CHANNEL_NAMES[Channel(i)] for i in range(len(CHANNEL_NAMES)))
"""Channel names by channel number."""


@dataclass
class ChannelSources:
    """One vehicle's choice of source per channel and its rates. Per sample its cost is a
    dictionary look-up per value while the sources stand (the replay's common case)."""

    system_id: int
    channels: dict[str, _Channel] = field(default_factory=dict)
    meters: dict[str, _Meter] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    """What changed (a channel's source once settled, each switch), for the link to print."""
    dropped: int = 0
    """Channel values not taken because another source feeds the channel."""
    t_last: float = -math.inf
    _settled: set[tuple[str, int]] = field(default_factory=set)
    """(message, its first channel) whose every channel has settled on it: such a sample
    passes whole with no per-value work (forgotten at any change of source)."""
    _partly: dict[tuple[str, tuple[int, ...], tuple[str, ...]], _Kept] = field(default_factory=dict)
    """(message, its channels, its auxiliary names) whose every channel has settled, some
    on another message (ATTITUDE, whose pitch rate comes from an IMU): which values pass,
    until a dropped channel next weighs this message as a challenger (forgotten at any
    change of source)."""

    def choose(self, sample: Sample) -> Sample | None:
        """The sample with only the values of channels that take it as their source
        (the sample itself where it is the source of all; None if of none)."""
        t = sample.t_recv_s
        message = sample.message
        meter = self.meters.get(message)
        if meter is None:
            meter = self.meters[message] = _Meter(t, t)
        meter.add(t)
        if t > self.t_last:
            self.t_last = t
        values = sample.values
        key = (message, values[0][0] if values else -1)
        if key in self._settled:
            return sample
        aux = sample.aux
        shape = (message, tuple([v[0] for v in values]), tuple([a[0] for a in aux]))
        known = self._partly.get(shape)
        if known is not None and t < known.until:
            kept = tuple([v for v, k in zip(values, known.values, strict=True) if k])
            kept_aux = tuple([a for a, k in zip(aux, known.aux, strict=True) if k])
        else:
            take = self._take
            kept = tuple(v for v in values if take(NAMES[v[0]], message, t))
            kept_aux = tuple(a for a in aux if take(a[0], message, t)) if aux else aux
            if len(kept) == len(values) and len(kept_aux) == len(aux):
                if self._all_settled(sample):
                    self._settled.add(key)
                return sample
            self._remember(shape, message)
        self.dropped += len(values) - len(kept) + len(aux) - len(kept_aux)
        if not kept and not kept_aux:
            return None
        return with_values(sample, kept, kept_aux)

    def choose_common(self, samples: list[Sample]) -> list[Sample | None]:
        """choose over samples one after the other, for as many from the first as take
        its remembered paths (every channel settled: _settled, or _partly before its
        `until`): those read no meter, so each message's meter takes its arrivals once
        for all (_Meter.extend). What choose gives each of them is returned; choose takes
        the rest from the first not taken (tests/telemetry/test_link_common.py compares
        the two)."""
        out: list[Sample | None] = []
        settled, partly = self._settled, self._partly
        arrivals: dict[str, list[float]] = {}
        dropped = 0
        for sample in samples:
            values = sample.values
            message = sample.message
            chosen: Sample | None = sample
            if (message, values[0][0] if values else -1) not in settled:
                aux = sample.aux
                shape = (message, tuple([v[0] for v in values]), tuple([a[0] for a in aux]))
                known = partly.get(shape)
                if known is None or message not in self.meters or sample.t_recv_s >= known.until:
                    break
                kept = tuple([v for v, k in zip(values, known.values, strict=True) if k])
                kept_aux = tuple([a for a, k in zip(aux, known.aux, strict=True) if k])
                dropped += len(values) - len(kept) + len(aux) - len(kept_aux)
                chosen = with_values(sample, kept, kept_aux) if kept or kept_aux else None
            got = arrivals.get(message)
            if got is None:
                got = arrivals[message] = []
            got.append(sample.t_recv_s)
            out.append(chosen)
        self.dropped += dropped
        for message, times in arrivals.items():
            self.meters[message].extend(times)
            newest = max(times)
            if newest > self.t_last:
                self.t_last = newest
        return out

    def _remember(self, shape: tuple[str, tuple[int, ...], tuple[str, ...]], message: str) -> None:
        """After _take judged a sample of this shape value by value: if every one of its
        channels has settled, what _take will say of each until a dropped channel next
        weighs this message (its next_check), so that the values need not be judged."""
        _, chans, aux = shape
        keys = [NAMES[ch] for ch in chans] + list(aux)
        channels = [self.channels[k] for k in keys]
        if any(c.taken < MIN_SAMPLES for c in channels):
            return
        keep = [c.source == message for c in channels]
        until = min(
            (c.next_check.get(message, -math.inf) for c in channels if c.source != message),
            default=math.inf,
        )
        self._partly[shape] = _Kept(tuple(keep[: len(chans)]), tuple(keep[len(chans) :]), until)

    def _all_settled(self, sample: Sample) -> bool:
        channels = self.channels
        return all(channels[NAMES[ch]].taken >= MIN_SAMPLES for ch, _ in sample.values) and all(
            channels[k].taken >= MIN_SAMPLES for k, _ in sample.aux
        )

    def _take(self, key: str, message: str, t: float) -> bool:
        channel = self.channels.get(key)
        if channel is None:
            channel = self.channels[key] = _Channel(message, {message})
            self._forget()
        if channel.source == message:
            channel.taken += 1
            if channel.taken == MIN_SAMPLES and len(channel.heard) > 1:
                others = ", ".join(sorted(channel.heard - {message}))
                self.notes.append(f"{key} from {message}, not {others}")
            return True
        if message not in channel.heard:
            channel.heard.add(message)
            if channel.taken >= MIN_SAMPLES:
                self.notes.append(f"{key}: {message} heard too; {channel.source} kept for now")
        if channel.taken < MIN_SAMPLES:  # still choosing: a better-ranked source came up
            if _rank(key, message) < _rank(key, channel.source):
                channel.source = message
                channel.taken += 1
                return True
            return False
        if t < channel.next_check.get(message, -math.inf):
            return False
        channel.next_check[message] = t + CHECK_EVERY_S
        return self._switch(key, channel, message, t)

    def _switch(self, key: str, channel: _Channel, message: str, t: float) -> bool:
        """Whether a challenger, measured, arrives SWITCH_RATIO times as fast as the source
        taken: then it is taken from now on (said, counted)."""
        challenger = self.meters[message]
        if challenger.count < MIN_SAMPLES:
            return False
        new, old = challenger.rate(t), self.meters[channel.source].rate(t)
        if new <= SWITCH_RATIO * old:
            return False
        self.notes.append(
            f"{key} now from {message} ({new:.1f} Hz), not {channel.source} ({old:.1f} Hz)"
        )
        channel.source = message
        channel.switches += 1
        channel.taken += 1
        self._forget()
        return True

    def _forget(self) -> None:
        """A channel's source changed (or a channel appeared): judge values afresh."""
        self._settled.clear()
        self._partly.clear()

    def source(self, key: str) -> str | None:
        channel = self.channels.get(key)
        return None if channel is None else channel.source

    def rate(self, key: str, now: float | None = None) -> float:
        """The current source's recent rate [Hz] (0 if none)."""
        channel = self.channels.get(key)
        if channel is None:
            return 0.0
        return self.meters[channel.source].rate(self.t_last if now is None else now)

    def report(self) -> dict[str, dict[str, Any]]:
        """Per channel: its source, the source's mean rate over the session [Hz], the
        other sources heard and their rates, switches, and a warning where the rate is
        below MIN_RATE_HZ."""
        out: dict[str, dict[str, Any]] = {}
        for key in sorted(self.channels, key=_order):
            channel = self.channels[key]
            rate = self.meters[channel.source].mean_rate()
            entry: dict[str, Any] = {"message": channel.source, "rate_hz": round(rate, 2)}
            others = {
                m: round(self.meters[m].mean_rate(), 2)
                for m in sorted(channel.heard)
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
