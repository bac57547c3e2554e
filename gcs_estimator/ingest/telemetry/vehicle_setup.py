"""What the station learns of and asks from each vehicle beyond its frames: which
autopilot it is, its servo parameters (params.py), which message each channel comes from
and at what rate (channel_sources.py), and the requests that get it there: the rates of
the messages the estimator reads (MAV_CMD_SET_MESSAGE_INTERVAL, which ArduPilot 4.0+ and
PX4 honour; ArduPilot's REQUEST_DATA_STREAM, which sets the SRn_ rates of the port it
arrives on, where the vehicle does not accept the former) and the parameters it needs
(PARAM_REQUEST_READ)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

from gcs_estimator.config import AircraftConfig, ConfigError, LinkConfig
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.channel_sources import MIN_RATE_HZ, ChannelSources, low_rate
from gcs_estimator.ingest.telemetry.decode import ParamValue, Ranges, Sample
from gcs_estimator.ingest.telemetry.mavlink import Codec
from gcs_estimator.ingest.telemetry.params import ServoMap, VehicleParams
from gcs_estimator.model.channels import Channel

ARDUPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
PX4 = mavlink.MAV_AUTOPILOT_PX4
AUX_RATE_HZ = 10.0
"""Rate asked for the auxiliary signals' messages (vertical speed, wind) [Hz]."""
EXTRA_MESSAGES: dict[int, tuple[str, ...]] = {
    ARDUPILOT: ("RAW_IMU",),
    PX4: ("ACTUATOR_OUTPUT_STATUS",),
}
"""Channel messages asked for beyond config.STREAMED_MESSAGES, per autopilot: ArduPilot's
first IMU is RAW_IMU (scaled: milli-g, mrad/s); PX4's outputs may come as
ACTUATOR_OUTPUT_STATUS."""
AUX_MESSAGES: dict[int, tuple[str, ...]] = {
    ARDUPILOT: ("GLOBAL_POSITION_INT", "WIND"),
    PX4: ("LOCAL_POSITION_NED",),
}
"""Messages of the auxiliary signals, asked for at AUX_RATE_HZ."""
STREAMS: tuple[tuple[int, float | None], ...] = (
    (mavlink.MAV_DATA_STREAM_RAW_SENSORS, None),  # RAW_IMU, SCALED_IMU2/3, SCALED_PRESSURE
    (mavlink.MAV_DATA_STREAM_EXTRA1, None),  # ATTITUDE
    (mavlink.MAV_DATA_STREAM_EXTRA2, None),  # VFR_HUD
    (mavlink.MAV_DATA_STREAM_RC_CHANNELS, None),  # SERVO_OUTPUT_RAW
    (mavlink.MAV_DATA_STREAM_EXTRA3, AUX_RATE_HZ),  # AOA_SSA, WIND
    (mavlink.MAV_DATA_STREAM_POSITION, AUX_RATE_HZ),  # GLOBAL_POSITION_INT
)
"""ArduPilot's stream groups holding what the estimator reads, with their rate (None:
[link] rate_hz)."""
STREAM_FALLBACK_AFTER = 2
"""Rate requests sent without an acceptance before REQUEST_DATA_STREAM is sent too."""
STREAM_TRIES = 3
PARAM_REQUEST_EVERY_S = 5.0
"""Parameters not yet heard are asked for again this often [s] ..."""
PARAM_ROUNDS = 6
"""... this many times at most."""
AHRS_ALPHA_SIGMA_DEG = 3.0
"""ArduPlane's AOA_SSA is its AHRS's estimate (velocity minus the estimated wind, in
body axes), not a vane: a wind estimate 1 m/s off at 15-25 m/s puts it 2-4 deg off, and
it lags the wind estimate. Its noise is taken as at least this (decision 0038)."""


@dataclass
class VehicleSetup:
    """One vehicle's autopilot, parameters, channel sources and requests."""

    system_id: int
    link: LinkConfig
    travel_deg: float
    ranges: Ranges
    autopilot_kind: int | None = None
    params: VehicleParams = field(default_factory=lambda: VehicleParams(ARDUPILOT))
    servo_map: ServoMap | None = None
    sources: ChannelSources = field(init=False)
    notes: list[str] = field(default_factory=list)
    invalid_values: int = 0
    raw_imu_refused: int = 0
    """RAW_IMU samples of a vehicle that is not ArduPilot: true raw sensor counts."""
    rate_rounds: int = 0
    stream_requests: int = 0
    param_rounds: int = 0
    last_param_request: float = -math.inf
    asked: list[str] = field(default_factory=list)
    """What was asked of the vehicle, once each ("SET_MESSAGE_INTERVAL RAW_IMU 50 Hz")."""

    def __post_init__(self) -> None:
        self.sources = ChannelSources(self.system_id)

    # ------------------------------------------------------------------ heard

    def autopilot(self, kind: int) -> None:
        if self.autopilot_kind is None:
            self.autopilot_kind = kind
            self.params.autopilot_kind = kind
            self._update_map()

    def param(self, p: ParamValue) -> None:
        self.params.add(p)
        self._update_map()

    def _update_map(self) -> None:
        new = self.params.servo_map(self.travel_deg)
        if new != self.servo_map and new is not None:
            self.notes.append(
                f"system id {self.system_id}: servo outputs from the vehicle's own "
                f"parameters, not [link]'s: {new.describe()}"
            )
        self.servo_map = new

    def prepare(self, sample: Sample) -> Sample | None:
        """The sample as its vehicle's parameters read it, with only the channels it is
        the chosen source of (None: nothing left)."""
        if sample.message == "RAW_IMU" and self.autopilot_kind not in (None, ARDUPILOT):
            self.raw_imu_refused += 1
            if self.raw_imu_refused == 1:
                self.notes.append(
                    f"system id {self.system_id}: RAW_IMU of an autopilot other than "
                    "ArduPilot holds raw sensor counts, not scaled units: not used"
                )
            return None
        if sample.outputs and self.servo_map is not None:
            sample = sample._replace(
                values=self._in_range(self.servo_map.values(self.link, sample.outputs))
            )
        chosen = self.sources.choose(sample)
        if self.sources.notes:
            self.notes += [f"system id {self.system_id}: {n}" for n in self.sources.notes]
            self.sources.notes.clear()
        if chosen is None or not chosen.values:
            return None  # auxiliary values only: measured, not for the synchroniser
        return chosen

    def prepare_common(self, samples: list[Sample]) -> list[Sample | None]:
        """prepare over samples one after the other, for as many from the first as need
        neither the vehicle's servo map nor the RAW_IMU rule and whose channels take
        ChannelSources' remembered paths (choose_common): what prepare gives each (no
        note can come of them); prepare takes the rest from the first not taken."""
        refuse_raw = self.autopilot_kind not in (None, ARDUPILOT)
        mapped = self.servo_map is not None
        if refuse_raw or mapped:
            n = 0
            for sample in samples:
                if (refuse_raw and sample.message == "RAW_IMU") or (mapped and sample.outputs):
                    break
                n += 1
            samples = samples[:n]
        chosen = self.sources.choose_common(samples)
        return [None if c is None or not c.values else c for c in chosen]

    def _in_range(self, vals: list[tuple[Channel, float]]) -> tuple[tuple[Channel, float], ...]:
        """The values the vehicle's servo map gives that are finite and in range (others
        counted, as decode counts its own)."""
        out = []
        for ch, v in vals:
            lo, hi = self.ranges[ch]
            if math.isfinite(v) and lo <= v <= hi:
                out.append((ch, v))
            else:
                self.invalid_values += 1
        return tuple(out)

    # ------------------------------------------------------------------ asked

    def requests(
        self, codec: Codec, acked: set[int], fleet_asked: bool, now: float
    ) -> Iterator[bytes]:
        """What to send the vehicle now, beyond the fleet's heartbeat and rate requests
        (fleet_asked: the fleet sent its rate requests just now)."""
        kind = self.autopilot_kind
        if kind is None:
            return
        if fleet_asked:
            self.rate_rounds += 1
            yield from self._rates(codec, kind)
            if kind == ARDUPILOT and self._streams_needed(acked):
                yield from self._streams(codec)
        yield from self._params(codec, now)

    def _rates(self, codec: Codec, kind: int) -> Iterator[bytes]:
        for name in EXTRA_MESSAGES.get(kind, ()):
            yield self._interval(codec, name, self.link.rate_hz)
        for name in AUX_MESSAGES.get(kind, ()):
            yield self._interval(codec, name, min(AUX_RATE_HZ, self.link.rate_hz))

    def _interval(self, codec: Codec, name: str, rate: float) -> bytes:
        self._said(f"SET_MESSAGE_INTERVAL {name} {rate:g} Hz")
        return codec.set_message_interval(self.system_id, name, rate)

    def _streams_needed(self, acked: set[int]) -> bool:
        if mavlink.MAV_RESULT_ACCEPTED in acked or self.stream_requests >= STREAM_TRIES:
            return False
        refused = bool(acked & {mavlink.MAV_RESULT_UNSUPPORTED, mavlink.MAV_RESULT_DENIED})
        return refused or self.rate_rounds > STREAM_FALLBACK_AFTER

    def _streams(self, codec: Codec) -> Iterator[bytes]:
        self.stream_requests += 1
        for stream, rate in STREAMS:
            hz = self.link.rate_hz if rate is None else min(rate, self.link.rate_hz)
            self._said(f"REQUEST_DATA_STREAM {stream} {hz:g} Hz")
            yield codec.request_data_stream(self.system_id, stream, hz)

    def _params(self, codec: Codec, now: float) -> Iterator[bytes]:
        wanted = self.params.wanted()
        if (
            not wanted
            or self.param_rounds >= PARAM_ROUNDS
            or now - self.last_param_request < PARAM_REQUEST_EVERY_S
        ):
            return
        self.param_rounds += 1
        self.last_param_request = now
        self._said(f"PARAM_REQUEST_READ ({len(wanted)} servo parameters)")
        for name in wanted:
            yield codec.param_request_read(self.system_id, name)

    def _said(self, what: str) -> None:
        if what not in self.asked:
            self.asked.append(what)

    # ------------------------------------------------------------------ told

    def rates_status(self) -> str:
        """Each channel's recent rate and source ("!": below channel_sources.MIN_RATE_HZ)."""
        parts = []
        for key in self.sources.report():
            if key not in MIN_RATE_HZ:
                continue
            rate = self.sources.rate(key)
            mark = "!" if low_rate(key, rate) else ""
            parts.append(f"{key} {rate:.0f}{mark} {self.sources.source(key)}")
        return " ".join(parts)

    def report(self) -> dict[str, object]:
        out: dict[str, object] = {"channels": self.sources.report()}
        out["servos"] = (
            f"vehicle parameters: {self.servo_map.describe()}"
            if self.servo_map is not None
            else "[link] servo numbers and PWM calibration"
        )
        if self.sources.source("alpha") == "AOA_SSA" and self.link.aoa_ssa == "ahrs":
            out["alpha_note"] = AHRS_NOTE
        if self.asked:
            out["asked"] = list(self.asked)
        return out


AHRS_NOTE = (
    "alpha from AOA_SSA: in ArduPilot the AHRS's estimate (velocity minus estimated wind), "
    f"not a vane; weighed with a sigma of at least {AHRS_ALPHA_SIGMA_DEG:g} deg "
    '([link] aoa_ssa = "ahrs"; "vane" where a vane fills it)'
)


def link_config(config: AircraftConfig) -> AircraftConfig:
    """The configuration a MAVLink link or its recording is estimated with: refused (a
    ConfigError naming the key) where it cannot read a link's power input
    (config.link_problem), its alpha weighed as [link] aoa_ssa says (weigh_alpha)."""
    problem = config.link_problem()
    if problem:
        raise ConfigError(problem)
    return weigh_alpha(config)


def weigh_alpha(config: AircraftConfig) -> AircraftConfig:
    """The configuration a MAVLink session estimates with: where [link] aoa_ssa says
    AOA_SSA is an AHRS estimate, alpha's measurement sigma at least AHRS_ALPHA_SIGMA_DEG
    (a config, not a per-frame choice: the same in every process a session may use)."""
    if config.link.aoa_ssa != "ahrs":
        return config
    sigma = list(config.filter.measurement_sigma)
    floor = math.radians(AHRS_ALPHA_SIGMA_DEG)
    if sigma[Channel.ALPHA] >= floor:
        return config
    sigma[Channel.ALPHA] = floor
    return replace(config, filter=replace(config.filter, measurement_sigma=tuple(sigma)))
