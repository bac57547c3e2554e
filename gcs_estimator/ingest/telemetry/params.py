"""A vehicle's own parameters and what they say about its servo outputs.

Which output drives the elevator and which the throttle, their PWM range, trim and
direction are the vehicle's parameters: heard as PARAM_VALUE (answers to the station's
PARAM_REQUEST_READ, or a ground station's fetch recorded in a tlog). Where they are known
they replace the [link] table's servo numbers and PWM calibration.

ArduPilot (Plane 3.8 and later): SERVOn_FUNCTION 19 is the elevator, 70 the throttle;
SERVOn_MIN/MAX/TRIM [us], SERVOn_REVERSED. A surface output is trim + out * (max - trim)
for out >= 0, trim + out * (trim - min) below, out negated where reversed, and a positive
elevator output pitches the nose up (trailing edge up: a negative deflection in the
model's convention, docs/model.md). The throttle is min + out * (max - min).

PX4 (control allocation, 1.13 and later): PWM_MAIN_FUNCn 201..208 is servo 1..8, 101 the
first motor; CA_SV_CSk_TYPE 3 makes servo k+1 the elevator; PWM_MAIN_MINn/MAXn [us],
PWM_MAIN_REV a bit mask of reversed outputs; a positive surface command moves the
trailing edge up, as ArduPilot's. PX4 sends integer parameters bytewise in the float.

The surface's travel at full output is the airframe file's ([airframe] elevator_travel_deg):
no log says it.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

from gcs_estimator.config import LinkConfig
from gcs_estimator.ingest.telemetry import pwm
from gcs_estimator.ingest.telemetry.decode import ParamValue
from gcs_estimator.ingest.telemetry.mavlink import MAV_AUTOPILOT_PX4
from gcs_estimator.model.channels import Channel

ARDUPILOT_ELEVATOR = 19
ARDUPILOT_THROTTLE = 70
ARDUPILOT_OUTPUTS = 16
PX4_SERVO_1 = 201
PX4_MOTOR_1 = 101
PX4_ELEVATOR_TYPE = 3
PX4_OUTPUTS = 8
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_UINT32 = 5


def param_number(p: ParamValue, autopilot_kind: int) -> float:
    """A parameter's value: PX4 puts an integer's bytes into the float (bytewise)."""
    if autopilot_kind == MAV_AUTOPILOT_PX4 and p.param_type in (
        MAV_PARAM_TYPE_INT32,
        MAV_PARAM_TYPE_UINT32,
    ):
        fmt = "<i" if p.param_type == MAV_PARAM_TYPE_INT32 else "<I"
        return float(struct.unpack(fmt, struct.pack("<f", p.value))[0])
    return p.value


@dataclass(frozen=True)
class Output:
    """One servo output: its number (1-based) and calibration [us]."""

    number: int
    low: float
    high: float
    trim: float
    reversed: bool

    def surface(self, us: float) -> float:
        """The normalised surface command (-1..1, ArduPilot's and PX4's sign)."""
        side = (self.high - self.trim) if us >= self.trim else (self.trim - self.low)
        out = (us - self.trim) / side if side > 0 else math.nan
        return -out if self.reversed else out

    def throttle(self, us: float) -> float:
        """The throttle (0..1)."""
        span = self.high - self.low
        out = (us - self.low) / span if span > 0 else math.nan
        return 1.0 - out if self.reversed else out


@dataclass(frozen=True)
class ServoMap:
    """Elevator and throttle from a servo message's outputs, per the vehicle's
    parameters (None: that output is not known from them: the [link] table's)."""

    elevator: Output | None
    throttle: Output | None
    travel_rad: float
    """The elevator's deflection at full output [rad]; 0: not given (the [link] PWM
    calibration is then used on the vehicle's elevator output)."""

    def values(self, link: LinkConfig, outputs: tuple[float, ...]) -> list[tuple[Channel, float]]:
        vals: list[tuple[Channel, float]] = []
        el = self.elevator
        if el is not None and el.number <= len(outputs):
            us = float(outputs[el.number - 1])
            if self.travel_rad > 0:
                vals.append((Channel.ELEVATOR, -el.surface(us) * self.travel_rad))
            else:
                vals.append((Channel.ELEVATOR, pwm.elevator_rad(link, us)))
        elif link.elevator_servo <= len(outputs):
            us = float(outputs[link.elevator_servo - 1])
            vals.append((Channel.ELEVATOR, pwm.elevator_rad(link, us)))
        th = self.throttle
        if th is not None and th.number <= len(outputs):
            vals.append((Channel.POWER, th.throttle(float(outputs[th.number - 1]))))
        elif 0 < link.throttle_servo <= len(outputs):
            vals.append(
                (Channel.POWER, pwm.throttle(link, float(outputs[link.throttle_servo - 1])))
            )
        return vals

    def describe(self) -> str:
        parts = []
        for what, o in (("elevator", self.elevator), ("throttle", self.throttle)):
            if o is None:
                continue
            rev = ", reversed" if o.reversed else ""
            parts.append(
                f"{what} on output {o.number} ({o.low:.0f}/{o.trim:.0f}/{o.high:.0f} us{rev})"
            )
        text = "; ".join(parts)
        if self.elevator is not None and self.travel_rad <= 0:
            text += (
                "; [airframe] elevator_travel_deg not given: the elevator's [link] PWM "
                "calibration is used on that output"
            )
        return text


@dataclass
class VehicleParams:
    """The parameters heard from one vehicle."""

    autopilot_kind: int
    raw: dict[str, ParamValue] = field(default_factory=dict)

    def add(self, p: ParamValue) -> None:
        self.raw[p.name] = p

    @property
    def values(self) -> dict[str, float]:
        """The values, read by the autopilot's convention (known once its HEARTBEAT is)."""
        return {n: param_number(p, self.autopilot_kind) for n, p in self.raw.items()}

    @property
    def px4(self) -> bool:
        return bool(self.autopilot_kind == MAV_AUTOPILOT_PX4)

    def wanted(self) -> list[str]:
        """The parameters the servo map needs that have not been heard."""
        return [n for n in self._needed() if n not in self.raw]

    def _needed(self) -> list[str]:
        if self.px4:
            names = [f"PWM_MAIN_FUNC{n}" for n in range(1, PX4_OUTPUTS + 1)]
            names += [f"CA_SV_CS{k}_TYPE" for k in range(PX4_OUTPUTS)]
            for n in self._px4_outputs():
                names += [f"PWM_MAIN_MIN{n}", f"PWM_MAIN_MAX{n}"]
            return [*names, "PWM_MAIN_REV"]
        names = [f"SERVO{n}_FUNCTION" for n in range(1, ARDUPILOT_OUTPUTS + 1)]
        for n in self._ardupilot_outputs():
            names += [f"SERVO{n}_{s}" for s in ("MIN", "MAX", "TRIM", "REVERSED")]
        return names

    def _function(self, prefix: str, suffix: str, value: int, count: int) -> int | None:
        values = self.values
        for n in range(1, count + 1):
            if values.get(f"{prefix}{n}{suffix}") == value:
                return n
        return None

    def _ardupilot_outputs(self) -> list[int]:
        found = (
            self._function("SERVO", "_FUNCTION", ARDUPILOT_ELEVATOR, ARDUPILOT_OUTPUTS),
            self._function("SERVO", "_FUNCTION", ARDUPILOT_THROTTLE, ARDUPILOT_OUTPUTS),
        )
        return [n for n in found if n is not None]

    def _px4_elevator(self) -> int | None:
        values = self.values
        for k in range(PX4_OUTPUTS):  # control surfaces count from 0
            if values.get(f"CA_SV_CS{k}_TYPE") == PX4_ELEVATOR_TYPE:
                return self._function("PWM_MAIN_FUNC", "", PX4_SERVO_1 + k, PX4_OUTPUTS)
        return None

    def _px4_outputs(self) -> list[int]:
        found = (
            self._px4_elevator(),
            self._function("PWM_MAIN_FUNC", "", PX4_MOTOR_1, PX4_OUTPUTS),
        )
        return [n for n in found if n is not None]

    def servo_map(self, travel_deg: float) -> ServoMap | None:
        """The outputs the parameters heard so far fully describe (None: neither)."""
        if self.px4:
            el = self._px4_output(self._px4_elevator())
            th = self._px4_output(self._function("PWM_MAIN_FUNC", "", PX4_MOTOR_1, PX4_OUTPUTS))
        else:
            el = self._ardupilot_output(
                self._function("SERVO", "_FUNCTION", ARDUPILOT_ELEVATOR, ARDUPILOT_OUTPUTS)
            )
            th = self._ardupilot_output(
                self._function("SERVO", "_FUNCTION", ARDUPILOT_THROTTLE, ARDUPILOT_OUTPUTS)
            )
        if el is None and th is None:
            return None
        return ServoMap(el, th, math.radians(travel_deg))

    def _ardupilot_output(self, n: int | None) -> Output | None:
        if n is None:
            return None
        got = [self.values.get(f"SERVO{n}_{s}") for s in ("MIN", "MAX", "TRIM", "REVERSED")]
        if any(v is None for v in got):
            return None
        low, high, trim, rev = (float(v) for v in got if v is not None)
        return Output(n, low, high, trim, rev != 0)

    def _px4_output(self, n: int | None) -> Output | None:
        if n is None:
            return None
        low = self.values.get(f"PWM_MAIN_MIN{n}")
        high = self.values.get(f"PWM_MAIN_MAX{n}")
        rev = self.values.get("PWM_MAIN_REV")
        if low is None or high is None or rev is None:
            return None
        return Output(n, low, high, (low + high) / 2, bool(int(rev) >> (n - 1) & 1))
