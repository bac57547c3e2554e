"""What the simulator flies: the [simulation] table of an airframe file.

The estimator does not read this table (gcs_estimator.config leaves it to the simulator);
the simulator checks it here, with the same schema walker, when it flies. Its keys are
listed by `gcs-sim --keys` (docs/simulation.md), apart from the airframe's. The
manoeuvre, the sensors' errors and the turbulence are what the filters do not know: the
tests and benchmarks grade the filters on flights made of them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from gcs_estimator.config import NOC_SENSOR_SIGMA, SIMULATOR_TABLE, AircraftConfig, per_channel
from gcs_estimator.model import turbulence as gusts
from gcs_estimator.schema import Invalid, Where, build, reference, setting, table


@dataclass(frozen=True)
class Manoeuvre:
    """Elevator excitation around trim: 3-2-1-1 multisteps and pulses (docs/model.md)."""

    duration_s: float = setting(60.0, gt=0, unit="s")
    multistep_starts_s: tuple[float, ...] = setting((2.0, 6.0), ge=0, unit="s")
    multistep_unit_s: float = setting(0.2, gt=0, unit="s")
    multistep_amplitude_deg: float = setting(3.0, unit="deg")
    pulse_starts_s: tuple[float, ...] = setting((12.0, 30.0), ge=0, unit="s")
    pulse_durations_s: tuple[float, ...] = setting((2.0, 2.0), ge=0, unit="s")
    pulse_amplitudes_deg: tuple[float, ...] = setting((-3.0, 3.0), unit="deg")

    def check(self) -> None:
        n = len(self.pulse_starts_s)
        for key in ("pulse_durations_s", "pulse_amplitudes_deg"):
            if len(getattr(self, key)) != n:
                raise Invalid(key, f"must have {n} values, one per pulse_starts_s")


@dataclass(frozen=True)
class Turns:
    """Coordinated turns (docs/model.md, "Turns"): the bank rolls in over roll_s, holds,
    and rolls out over roll_s; the yaw rate is r = g sin(phi)/V (the body's share of the
    turn rate g tan(phi)/V), the roll rate p = phi-dot. None: wings level throughout."""

    starts_s: tuple[float, ...] = setting((), ge=0, unit="s")
    durations_s: tuple[float, ...] = setting((), gt=0, unit="s", doc="roll-in to roll-out")
    banks_deg: tuple[float, ...] = setting((), unit="deg", doc="right wing down positive")
    roll_s: float = setting(3.0, gt=0, unit="s", doc="roll-in and roll-out time")

    def check(self) -> None:
        n = len(self.starts_s)
        for key in ("durations_s", "banks_deg"):
            if len(getattr(self, key)) != n:
                raise Invalid(key, f"must have {n} values, one per starts_s")


@dataclass(frozen=True)
class ThrottleSteps:
    """Throttle (or thrust) steps from trim: a climb on more, a descent on less."""

    starts_s: tuple[float, ...] = setting((), ge=0, unit="s")
    durations_s: tuple[float, ...] = setting((), gt=0, unit="s")
    amounts: tuple[float, ...] = setting((), doc="added to the trim throttle (0..1) or thrust [N]")

    def check(self) -> None:
        n = len(self.starts_s)
        for key in ("durations_s", "amounts"):
            if len(getattr(self, key)) != n:
                raise Invalid(key, f"must have {n} values, one per starts_s")


@dataclass(frozen=True)
class Wind:
    """A steady horizontal wind: along the flight path it adds to the airspeed by the
    cosine of the heading against it (turns sweep it round)."""

    speed_mps: float = setting(0.0, ge=0, unit="m/s")
    from_deg: float = setting(0.0, unit="deg", doc="direction it blows from, the heading 0")


@dataclass(frozen=True)
class Turbulence:
    """Dryden longitudinal gusts of the simulator; a preset sets the intensities."""

    preset: str = setting(
        "none", choices=("none", "light", "moderate", "custom"), doc="defaults of the sigmas below"
    )
    sigma_w_mps: float | None = setting(None, ge=0, unit="m/s", doc="unset: the preset's")
    sigma_u_mps: float | None = setting(None, ge=0, unit="m/s", doc="unset: 1.5 sigma_w")
    length_u_m: float = setting(200.0, gt=0, unit="m")
    length_w_m: float = setting(50.0, gt=0, unit="m")

    def __post_init__(self) -> None:
        w = self.sigma_w_mps
        if w is None:
            w = gusts.SIGMA_W_PRESETS.get(self.preset, 0.0)
            object.__setattr__(self, "sigma_w_mps", w)
        if self.sigma_u_mps is None:
            object.__setattr__(self, "sigma_u_mps", gusts.SIGMA_U_RATIO * w)

    @property
    def sigma_w(self) -> float:
        return self.sigma_w_mps or 0.0

    @property
    def sigma_u(self) -> float:
        return self.sigma_u_mps or 0.0


@dataclass(frozen=True)
class Sensors:
    """Measurement errors of the simulated aircraft per channel, SI units (or KEY_deg)."""

    noise_sigma: tuple[float, ...] = per_channel(NOC_SENSOR_SIGMA, ge=0, doc="white noise 1 sigma")
    bias: tuple[float, ...] = per_channel(0.0)
    quantum: tuple[float, ...] = per_channel(0.0, ge=0, doc="quantisation step; 0: none")


@dataclass(frozen=True)
class Simulation:
    """Truth simulator settings."""

    sample_rate_hz: float = setting(50.0, gt=0, unit="Hz")
    integration_step_s: float = setting(0.002, gt=0, unit="s")
    seed: int = setting(1)
    actuator_time_constant_s: float = setting(
        0.0, ge=0, unit="s", doc="first-order servo lag; 0: each command holds until the next"
    )
    vane: bool = setting(True, doc="false: no angle-of-attack vane (alpha not sent)")
    climb_rate: bool = setting(
        False, doc="a climb-rate sensor (h_dot, GPS vertical speed): the missions' (decision 0049)"
    )
    manoeuvre: Manoeuvre = table(Manoeuvre)
    sensors: Sensors = table(Sensors)
    turbulence: Turbulence = table(Turbulence)
    turns: Turns = table(Turns)
    throttle: ThrottleSteps = table(ThrottleSteps)
    wind: Wind = table(Wind)

    @property
    def banked(self) -> bool:
        """Whether the flight has turns (its inputs carry phi, p, r)."""
        return len(self.turns.starts_s) > 0


MISSION_DURATION_S = 480.0


def mission(turbulence: str = "light", duration_s: float = MISSION_DURATION_S) -> list[str]:
    """A mission as an autopilot flies it (`gcs-sim --scenario mission`), as [simulation]
    overrides: straight legs of 40 s joined by coordinated turns of 20-35 deg bank, a
    3-2-1-1 on every other leg and none on the others, a climb and a descent on throttle,
    a steady 6 m/s wind, and `turbulence` ("none" for calm). Scaled to duration_s
    (default about 8 min; the tests fly a short one). Times fall on tenths of a second, on
    the sample grid: an input switching between samples is one the data misplace."""
    scale = duration_s / MISSION_DURATION_S
    legs = [40.0 + 80.0 * i for i in range(6)]  # leg starts; turns 20 s after each
    turn_starts = [round((leg + 25.0) * scale, 1) for leg in legs]
    turn_lengths = [round(max(15.0 * scale, 7.0), 1)] * len(legs)
    banks = [25.0, -30.0, 20.0, 35.0, -25.0, 30.0]
    # The first leg opens with two 3-2-1-1s before the filters' restarts (5 and 10 s by
    # default), as the wings-level manoeuvre does; later ones on every other leg.
    multisteps = [2.0, 6.0] + [round((leg + 5.0) * scale, 1) for leg in legs[1::2]]
    pulses = [round(t * scale, 1) for t in (170.0, 330.0)]
    climb = [round(t * scale, 1) for t in (210.0, 290.0)]
    steps = round(max(25.0 * scale, 5.0), 1)
    return [
        f"simulation.manoeuvre.duration_s={duration_s}",
        f"simulation.manoeuvre.multistep_starts_s={sorted(multisteps)}",
        f"simulation.manoeuvre.pulse_starts_s={pulses}",
        f"simulation.manoeuvre.pulse_durations_s={[2.0, 2.0]}",
        f"simulation.manoeuvre.pulse_amplitudes_deg={[-3.0, 3.0]}",
        f"simulation.turns.starts_s={turn_starts}",
        f"simulation.turns.durations_s={turn_lengths}",
        f"simulation.turns.banks_deg={banks}",
        f"simulation.throttle.starts_s={climb}",
        f"simulation.throttle.durations_s={[steps, steps]}",
        f"simulation.throttle.amounts={[0.05, -0.05]}",
        "simulation.wind.speed_mps=6.0",
        "simulation.wind.from_deg=30.0",
        "simulation.climb_rate=true",
        f'simulation.turbulence.preset="{turbulence}"',
    ]


def scenario_of(config: AircraftConfig) -> Simulation:
    """The [simulation] table of the config's file (with its command-line overrides),
    checked: errors name the file, the table and the key, as the airframe's do."""
    data = config.raw.get(SIMULATOR_TABLE, {})
    where = Where(config.source)
    if not isinstance(data, Mapping):
        raise where.error(SIMULATOR_TABLE, f"must be a table, got {data!r}")
    return build(Simulation, data, where.sub(SIMULATOR_TABLE))


def scenario_reference() -> str:
    """Every key of the [simulation] table (Markdown), as `gcs-sim --keys` prints it."""
    head = (
        "# Simulator keys\n\n"
        "Generated by `gcs-sim --keys` from the schema in sim/scenario.py. The [simulation] "
        "table of an airframe file says what the simulator flies (`gcs-sim`, "
        "`gcs-estimator demo`, the tests and benchmarks); the estimator does not read it. "
        "The airframe's own keys: configuration.md.\n\n"
    )
    from sim.formats import OUTPUTS_REFERENCE

    return head + reference(Simulation, {}, SIMULATOR_TABLE) + OUTPUTS_REFERENCE
