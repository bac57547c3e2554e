"""The validation set flown as a mission: JSBSim aircraft of the wide validation set
flown by a simple autopilot through what a small UAV's autopilot flies, written with no
vane in the autopilots' formats, with JSBSim's reference coefficients beside each.

    ./run bench jsbsim_missions [--seeds 1] [--jobs 2] [--out out/missions]

What each flight is (docs/decisions/0053): about 8 minutes of straight legs joined by
coordinated turns of 20-35 deg of bank (the mission's PLAN), elevator 3-2-1-1
multisteps and doublets on some legs (on top of the autopilot's elevator) and none on
others, a climb and a descent on throttle (throttle stepped, the elevator holding the
airspeed), flown "windy" (a steady wind of 5-8 m/s from a seeded direction and light
MIL-F-8785C Dryden turbulence) and "calm". The autopilot (Autopilot): bank hold on the
aileron, a yaw damper with turn coordination on the rudder (sideslip and yaw rate), an
altitude hold on the elevator through a pitch loop, an airspeed hold on the throttle.
Its loop runs at the logging rate (50 Hz); JSBSim integrates at 200 Hz.

Per flight (NAME = model_air_sSEED), in --out:
- NAME_asked.tlog: ArduPlane's MAVLink stream as a station that asks for the estimator's
  messages at [link] rate_hz records it; NAME_default.tlog: at the rate MAVProxy asks of
  every stream on connecting (4 Hz);
- NAME.bin (ArduPilot DataFlash at ArduPlane's logging rates) and NAME.ulg (PX4 ULog at
  the logger's default rates);
- each with its truth side file (NAME.truth.toml, NAME_asked.truth.toml, ...): the
  airframe file and JSBSim's reference coefficients, which `replay FILE` finds by itself;
- NAME.clean.npz: the noise-free signals the structure's best fit is fitted to (CLEAN_KEYS:
  the inputs as flown, JSBSim's thrust, what sensors at the CG would read, the gusts);
- NAME.toml: the airframe file (geometry, mass, inertia, the spec sheet's propulsion; no
  filter tuning, no vane) with [truth]; NAME.json: the references with their fit
  residuals, JSBSim's alpha-dot terms, how the flight went, how long it took to fly.

Every file carries bank, roll and yaw rate, climb rate, the EKF's wind (the steady wind:
an EKF does not follow turbulence), the throttle (not the thrust) and the elevator as
servo PWM with the SERVOn parameters. No vane: AOA_SSA and AOA carry what ArduPlane's
AHRS computes, the velocity over the ground less the wind estimate in body axes (blind
to the gusts); PX4 logs no angle of attack. Sensor noise: the project's default sigmas
on the seven channels (bank as pitch, roll and yaw rate as pitch rate, the lateral
acceleration as the others), 0.1 m/s on the GPS velocity.

Reference coefficients: as the validation set's (jsbsim_flights.reference), JSBSim's own
aerodynamic coefficients at every logged sample fitted by least squares on the
structure's regressors (1, alpha, q c / (2 V), elevator), with the air-relative alpha,
airspeed and pitch rate JSBSim's aerodynamics see (aerodynamic()): the structure's best
linear account of JSBSim's aerodynamics over what this mission flew. The aircraft are
the set's, not pa28, c172x and J3Cub (held for independent checks).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from jsbsim_flights import (  # benchmarks/: the script's dir is on sys.path
    MODEL_OUTPUT,
    NOISE,
    RATE_HZ,
    ROOT,
    STEPS_PER_SAMPLE,
    STRUCTURE,
    Aircraft,
    _sample,
    _trim,
    alpha_dot_terms,
    reference,
)
from validation_flights import member

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import Airframe, FlightAirframe, LinkConfig, Propulsion, load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.model import atmosphere
from gcs_estimator.units import FOOT
from sim.formats import HOME_ALT_M, FlightRecord, write_truth
from sim.formats.ardupilot import ArduPlaneVehicle, parse_rates
from sim.formats.dataflash import write_bin
from sim.formats.ulog import write_ulg

VERSION = 6
"""Bump when the flights or the files change: the cache is keyed on it."""
OUT = ROOT / "out" / "missions"
GRAVITY = 9.80665
DURATION_S = 480.0
AIRS = ("windy", "calm")
MODELS = ("c182", "t6texan2", "DHC6", "T37", "737", "A4")
"""Six classes of the validation set: light single, turboprop trainer, turboprop twin,
jet trainer, jet transport, jet attack. Not the glider (no throttle to climb on), not the
c172p, whose elevator works in the propeller's slipstream (JSBSim's Cmde on the induced
dynamic pressure: with the throttle moving, the structure's best linear fit puts Cmq
near 0 with a Cm residual ten times the c182's)."""
PREROLL_S, WIND_RISE_S = 40.0, 10.0
"""Flown before the record starts; the steady wind rises over the first seconds."""
GPS_VELOCITY_SIGMA = 0.1
"""GPS velocity noise, 1 sigma [m/s]."""


@dataclass(frozen=True)
class Spec:
    """What a spec sheet says of the aircraft's propulsion (and its top speed)."""

    engines: int
    power_w: float = 0.0
    """Each engine's rated power (0: a jet)."""
    diameter_m: float = 0.0
    """Propeller diameter (0: a jet)."""
    static_thrust_n: float = 0.0
    """Each jet engine's rated static thrust (0: a propeller)."""
    top_speed_mps: float = 0.0
    note: str = ""
    engine: str = "electric"
    """What turns the propeller ([propulsion] engine): these are piston and turboprop."""


HP, LBF, KT = 745.7, 4.44822, 0.514444
SPECS = {
    "c182": Spec(
        1, 230 * HP, 81 * 0.0254, top_speed_mps=145 * KT, note="IO-540, 81 in", engine="piston"
    ),
    "A4": Spec(1, static_thrust_n=11200 * LBF, top_speed_mps=585 * KT, note="J52"),
    "t6texan2": Spec(
        1,
        1100 * HP,
        97 * 0.0254,
        top_speed_mps=316 * KT,
        note="PT6A-68, 97 in four-blade",
        engine="turboprop",
    ),
    "DHC6": Spec(
        2, 680 * HP, 94 * 0.0254, top_speed_mps=182 * KT, note="PT6A-27, 94 in", engine="turboprop"
    ),
    "T37": Spec(2, static_thrust_n=1025 * LBF, top_speed_mps=360 * KT, note="J69-T25"),
    "737": Spec(2, static_thrust_n=20000 * LBF, top_speed_mps=470 * KT, note="CFM56"),
}
"""Spec-sheet figures (the JSBSim models' engine and propeller files agree with them; the
t6texan2 model flies its engine as a thrust, not a propeller)."""


# ------------------------------------------------------------------------------ the plan


@dataclass(frozen=True)
class Phase:
    """One piece of the mission: "straight" (level, `value` seconds), "turn" (`value`
    degrees of heading change at `bank_deg`, as long as it takes), "climb" and "descent"
    (`value` seconds on a throttle step, the elevator holding the airspeed)."""

    kind: str
    value: float
    bank_deg: float = 0.0
    excite: tuple[tuple[str, float], ...] = ()
    """Elevator inputs on a straight leg: ("3211" or "doublet", seconds into the leg)."""


PLAN = (
    Phase("straight", 30.0, excite=(("3211", 6.0), ("doublet", 18.0))),
    Phase("turn", 90.0, 30.0),
    Phase("straight", 30.0),
    Phase("climb", 40.0),
    Phase("straight", 25.0),
    Phase("turn", 90.0, 25.0),
    Phase("straight", 30.0, excite=(("doublet", 8.0),)),
    Phase("descent", 40.0),
    Phase("straight", 25.0),
    Phase("turn", 120.0, 35.0),
    Phase("straight", 30.0, excite=(("3211", 8.0),)),
    Phase("turn", -90.0, 20.0),
    Phase("straight", 30.0),
    Phase("turn", 90.0, 30.0),
    Phase("straight", 60.0, excite=(("3211", 6.0), ("doublet", 18.0))),
)
"""About 8 minutes for a light single (a turn's length is the aircraft's: a jet's take
longer and the flight ends at DURATION_S, in the last leg)."""
UNIT_3211_S, UNIT_DOUBLET_S = 0.3, 0.6
MAX_CLIMB_M = 300.0
"""A climb or descent ends after its time or this height, whichever comes first (MIL-F-
8785C's light turbulence fades out above 8,000 ft)."""
CLIMB_THROTTLE = {"c182": 0.3, "t6texan2": 0.25, "DHC6": 0.15, "T37": 0.1, "737": 0.15, "A4": 0.1}
"""The throttle step of a climb and a descent (up to full throttle: the DHC6 and the T37
cruise near it)."""
ALTITUDE_GAIN = 0.15
"""Climb rate commanded per metre of altitude error [1/s]."""


def excitation(kind: str, s: float) -> float:
    """The elevator input's sign pattern, s seconds after it began (0 outside it)."""
    if kind == "3211":
        k = s / UNIT_3211_S
        for a, b, step in ((0, 3, 1.0), (3, 5, -1.0), (5, 6, 1.0), (6, 7, -1.0)):
            if a <= k < b:
                return step
        return 0.0
    k = s / UNIT_DOUBLET_S
    return 1.0 if 0 <= k < 1 else -1.0 if 1 <= k < 2 else 0.0


# ------------------------------------------------------------------------- the autopilot


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclass
class Trim:
    elevator_norm: float
    aileron_norm: float
    rudder_norm: float
    throttle: float
    per_norm: float
    """Elevator [rad] per normalised command."""
    m_de: float
    """Pitch acceleration per elevator [1/s^2] at trim."""
    speed: float
    theta: float


@dataclass
class Autopilot:
    """Bank hold on the aileron, yaw damper and turn coordination on the rudder,
    altitude hold on the elevator (through a pitch loop), airspeed hold on the throttle;
    on a climb or descent the throttle is stepped and the elevator holds the airspeed."""

    trim: Trim
    engines: int
    throttle_step: float
    heading: float = 0.0
    altitude: float = 0.0
    phase: int = 0
    phase_start: float = 0.0
    phase_altitude: float = 0.0
    theta_i: float = 0.0
    gamma_i: float = 0.0
    throttle_i: float = 0.0
    beta_i: float = 0.0
    log: dict[str, list[float]] = field(default_factory=dict)

    def start(self, g: Callable[[str], float]) -> None:
        self.heading = g("attitude/psi-rad")
        self.altitude = self.phase_altitude = g("position/h-sl-ft") * FOOT
        self.theta_i = self.trim.theta
        self.throttle_i = self.trim.throttle

    def step(self, fdm: Any, t: float) -> tuple[float, float]:
        """Set the controls for the next sample interval; returns (bank commanded [rad],
        elevator excitation [rad])."""
        g: Callable[[str], float] = fdm.__getitem__
        phase = self._advance(g, t)
        psi = g("attitude/psi-rad")
        V = g("velocities/vt-fps") * FOOT
        bank = math.radians(phase.bank_deg if phase.kind == "turn" else 30.0)
        phi_cmd = float(np.clip(1.5 * _wrap(self.heading - psi), -bank, bank))
        self._lateral(fdm, g, phi_cmd, V)
        exc = self._excitation(phase, t)
        self._longitudinal(fdm, g, phase, V, exc)
        return phi_cmd, exc

    def _advance(self, g: Callable[[str], float], t: float) -> Phase:
        phase = PLAN[min(self.phase, len(PLAN) - 1)]
        h = g("position/h-sl-ft") * FOOT
        if phase.kind == "turn":
            done = abs(_wrap(self.heading - g("attitude/psi-rad"))) < math.radians(2.0)
            done = done and abs(g("attitude/phi-rad")) < math.radians(5.0)
        else:
            done = t - self.phase_start >= phase.value
            if phase.kind in ("climb", "descent"):
                done = done or abs(h - self.phase_altitude) >= MAX_CLIMB_M
        if done and self.phase < len(PLAN) - 1:
            self.phase += 1
            self.phase_start, self.phase_altitude = t, h
            new = PLAN[self.phase]
            if new.kind == "turn":
                self.heading = _wrap(self.heading + math.radians(new.value))
            if new.kind in ("climb", "descent"):
                self.gamma_i = g("velocities/h-dot-fps") / g("velocities/vt-fps")
            if phase.kind in ("climb", "descent"):
                # Level off smoothly: the target where the climb rate, decaying at the
                # altitude loop's rate, runs out.
                hdot = g("velocities/h-dot-fps") * FOOT
                self.altitude = h + hdot / ALTITUDE_GAIN
            return new
        return phase

    def _excitation(self, phase: Phase, t: float) -> float:
        s = t - self.phase_start
        amplitude = math.radians(self.amplitude_deg)
        return sum(amplitude * excitation(kind, s - at) for kind, at in phase.excite)

    amplitude_deg: float = 1.0

    def _lateral(self, fdm: Any, g: Callable[[str], float], phi_cmd: float, V: float) -> None:
        phi, p, r = g("attitude/phi-rad"), g("velocities/p-rad_sec"), g("velocities/r-rad_sec")
        theta, beta = g("attitude/theta-rad"), g("aero/beta-rad")
        aileron = self.trim.aileron_norm + 2.0 * (phi_cmd - phi) - 0.5 * p
        fdm["fcs/aileron-cmd-norm"] = float(np.clip(aileron, -0.6, 0.6))
        self.beta_i += beta / RATE_HZ
        r_turn = GRAVITY * math.sin(phi) * math.cos(theta) / V
        rudder = self.trim.rudder_norm - 4.0 * beta - 2.0 * self.beta_i + 2.0 * (r - r_turn)
        fdm["fcs/rudder-cmd-norm"] = float(np.clip(rudder, -1.0, 1.0))

    def _longitudinal(
        self, fdm: Any, g: Callable[[str], float], phase: Phase, V: float, exc: float
    ) -> None:
        dt = 1.0 / RATE_HZ
        gamma = g("velocities/h-dot-fps") * FOOT / V
        speed_error = V - self.trim.speed
        climbing = phase.kind in ("climb", "descent")
        if climbing:
            self.gamma_i += 0.2 * speed_error / self.trim.speed * dt
            gamma_cmd = self.gamma_i + 1.5 * speed_error / self.trim.speed
            step = self.throttle_step if phase.kind == "climb" else -self.throttle_step
            throttle = self.trim.throttle + step
        else:
            h = g("position/h-sl-ft") * FOOT
            climb_cmd = float(np.clip(ALTITUDE_GAIN * (self.altitude - h), -0.15 * V, 0.15 * V))
            gamma_cmd = climb_cmd / V
            self.throttle_i -= 0.01 * speed_error * dt
            throttle = self.throttle_i - 0.05 * speed_error
        self.theta_i += 0.3 * (gamma_cmd - gamma) * dt
        theta_cmd = self.theta_i + gamma_cmd + 1.0 * (gamma_cmd - gamma)
        phi, theta = g("attitude/phi-rad"), g("attitude/theta-rad")
        q_turn = GRAVITY / V * math.tan(phi) * math.sin(phi) * math.cos(theta)
        q = g("velocities/q-rad_sec") - q_turn
        w, zeta = 2.0, 0.7
        de = (w * w * (theta - theta_cmd) + 2 * zeta * w * q) / abs(self.trim.m_de) + exc
        norm = self.trim.elevator_norm + de / self.trim.per_norm
        fdm["fcs/elevator-cmd-norm"] = float(np.clip(norm, -1.0, 1.0))
        for k in range(self.engines):
            fdm[f"fcs/throttle-cmd-norm[{k}]"] = float(np.clip(throttle, 0.0, 1.0))


# --------------------------------------------------------------------------- the flight


@dataclass(frozen=True)
class Flight:
    """One mission flown: every logged sample's values (jsbsim_flights._sample's and
    the lateral ones) and what the autopilot commanded."""

    aircraft: Aircraft
    air: str
    seed: int
    values: dict[str, FloatArray]
    spec: Spec
    seconds: float
    """Wall-clock time the flight took to fly [s]."""


def wind(air: str, seed: int) -> tuple[float, float]:
    """The steady wind (north, east) [m/s] the air moves with: 5-8 m/s from a seeded
    direction ("windy"), none ("calm")."""
    if air == "calm":
        return 0.0, 0.0
    rng = np.random.default_rng(1000 + seed)
    speed, towards = rng.uniform(5.0, 8.0), rng.uniform(0.0, 2 * math.pi)
    return speed * math.cos(towards), speed * math.sin(towards)


def fly(model: str, air: str, seed: int, duration_s: float = DURATION_S) -> Flight:
    """One mission, JSBSim's banner and notes on stderr (as jsbsim_flights.fly)."""
    start = time.perf_counter()
    with contextlib.redirect_stdout(sys.stderr):
        ac = member(model).aircraft
        values = _fly(ac, air, seed, duration_s)
    return Flight(ac, air, seed, values, SPECS[model], time.perf_counter() - start)


def _setup(ac: Aircraft, air: str, seed: int) -> tuple[Any, Trim]:
    import jsbsim

    fdm = jsbsim.FGFDMExec(None)
    fdm.set_debug_level(0)
    MODEL_OUTPUT.mkdir(parents=True, exist_ok=True)
    fdm.set_output_path(str(MODEL_OUTPUT))
    fdm.load_model(ac.model)
    fdm.set_dt(1.0 / (RATE_HZ * STEPS_PER_SAMPLE))
    wn, we = wind(air, seed)
    # Trimmed in still air heading downwind; the wind rises during the pre-roll (JSBSim
    # 1.3's initial conditions with a wind give an airspeed off by twice the wind).
    fdm["ic/psi-true-deg"] = math.degrees(math.atan2(we, wn)) % 360.0
    _trim(fdm, ac)
    trim = _calibrate(fdm, ac)
    if air != "calm":  # MIL-F-8785C Dryden, light (W20 = 15 kt)
        fdm["atmosphere/turb-type"] = 3
        fdm["atmosphere/turbulence/milspec/windspeed_at_20ft_ft_sec"] = 15 * 1.6878
        fdm["atmosphere/turbulence/milspec/severity"] = 1
        fdm["atmosphere/randomseed"] = seed
    return fdm, trim


def _calibrate(fdm: Any, ac: Aircraft) -> Trim:
    """The trim's controls, the elevator's deflection per normalised command and its
    pitch acceleration per radian (from a small step held 0.1 s), then trimmed again."""
    fdm.run()
    elevator = fdm["fcs/elevator-cmd-norm"]
    de0, qdot0 = fdm["fcs/elevator-pos-rad"], fdm["accelerations/qdot-rad_sec2"]
    fdm["fcs/elevator-cmd-norm"] = elevator + 0.05
    for _ in range(int(0.1 * RATE_HZ * STEPS_PER_SAMPLE)):
        fdm.run()
    moved = fdm["fcs/elevator-pos-rad"] - de0
    m_de = (fdm["accelerations/qdot-rad_sec2"] - qdot0) / moved
    for _ in range(STEPS_PER_SAMPLE * 20):
        fdm.run()
    per_norm = (fdm["fcs/elevator-pos-rad"] - de0) / 0.05
    fdm["fcs/elevator-cmd-norm"] = elevator
    _trim(fdm, ac)
    fdm.run()
    return Trim(
        elevator_norm=fdm["fcs/elevator-cmd-norm"],
        aileron_norm=fdm["fcs/aileron-cmd-norm"],
        rudder_norm=fdm["fcs/rudder-cmd-norm"],
        throttle=fdm["fcs/throttle-cmd-norm[0]"],
        per_norm=per_norm,
        m_de=m_de,
        speed=fdm["velocities/vt-fps"] * FOOT,
        theta=fdm["attitude/theta-rad"],
    )


LATERAL = {
    "psi": "attitude/psi-rad",
    "p": "velocities/p-rad_sec",
    "r": "velocities/r-rad_sec",
    "beta": "aero/beta-rad",
    "v_north": "velocities/v-north-fps",
    "v_east": "velocities/v-east-fps",
    "v_down": "velocities/v-down-fps",
    "u": "velocities/u-fps",
    "v": "velocities/v-fps",
    "w": "velocities/w-fps",
}


def _sample_mission(fdm: Any, t: float, out: dict[str, list[float]], ap: Autopilot) -> None:
    g: Callable[[str], float] = fdm.__getitem__
    _sample(fdm, t, out)
    values = {
        k: g(prop) * (FOOT if k.startswith(("v", "u", "w")) else 1.0) for k, prop in LATERAL.items()
    }
    mass = g("inertia/mass-slugs")
    values |= {
        "a_y": (g("forces/fby-aero-lbs") + g("forces/fby-prop-lbs")) / mass * FOOT,
        "lat": g("position/lat-geod-rad"),
        "lon": g("position/long-gc-rad"),
        "h": g("position/h-sl-ft") * FOOT,
        "pressure": g("atmosphere/P-psf") * 47.880258,
        "throttle": g("fcs/throttle-cmd-norm[0]"),
        "ixx": g("inertia/ixx-slugs_ft2") * 1.35581795,
        "izz": g("inertia/izz-slugs_ft2") * 1.35581795,
        "ixz": g("inertia/ixz-slugs_ft2") * 1.35581795,
        "phase": float(ap.phase),
    }
    for k, v in values.items():
        out.setdefault(k, []).append(float(v))


def _preroll(fdm: Any, ap: Autopilot, wind_ne: tuple[float, float]) -> None:
    """PREROLL_S of flight before the record starts, the autopilot holding the first
    leg: the steady wind rises over its first WIND_RISE_S, and the autopilot settles."""
    n = int(PREROLL_S * RATE_HZ)
    for k in range(n):
        share = min(1.0, k / (WIND_RISE_S * RATE_HZ))
        fdm["atmosphere/wind-north-fps"] = share * wind_ne[0] / FOOT
        fdm["atmosphere/wind-east-fps"] = share * wind_ne[1] / FOOT
        ap.step(fdm, 0.0)
        for _ in range(STEPS_PER_SAMPLE):
            fdm.run()


def _fly(ac: Aircraft, air: str, seed: int, duration_s: float) -> dict[str, FloatArray]:
    fdm, trim = _setup(ac, air, seed)
    engines = int(fdm.get_propulsion().get_num_engines())
    step = CLIMB_THROTTLE.get(ac.model, 0.2)
    ap = Autopilot(trim, engines, throttle_step=step, amplitude_deg=ac.amplitude_deg)
    ap.start(fdm.__getitem__)
    _preroll(fdm, ap, wind(air, seed))
    out: dict[str, list[float]] = {}
    n = int(duration_s * RATE_HZ)
    for k in range(n + 1):
        t = k / RATE_HZ
        phi_cmd, exc = ap.step(fdm, t)
        _sample_mission(fdm, t, out, ap)
        out.setdefault("phi_cmd", []).append(phi_cmd)
        out.setdefault("excitation", []).append(exc)
        if k < n:
            for _ in range(STEPS_PER_SAMPLE):
                fdm.run()
    out["elevator_per_norm"] = [abs(trim.per_norm)]
    return {k: np.array(v) for k, v in out.items()}


# ---------------------------------------------------------------------------- the files


def _air_relative_alpha(v: dict[str, FloatArray]) -> FloatArray:
    """ArduPlane's AHRS angle of attack: the velocity over the ground less the EKF's wind
    (the steady wind: it does not follow the gusts), in body axes."""
    wn, we = v["wind_n"], v["wind_e"]
    psi, theta, phi = v["psi"], v["theta"], v["phi"]
    x1 = np.cos(psi) * wn + np.sin(psi) * we
    y1 = -np.sin(psi) * wn + np.cos(psi) * we
    u_w = np.cos(theta) * x1
    w_w = np.sin(theta) * x1
    w_w = -np.sin(phi) * y1 + np.cos(phi) * w_w
    return np.arctan2(v["w"] - w_w, v["u"] - u_w)


def elevator_travel(flight: Flight) -> float:
    """The elevator's deflection at full output [rad], the PWM's scale (500 us): the
    model's deflection per normalised command at trim, or more where it flew further."""
    v = flight.values
    return float(max(v["elevator_per_norm"][0], 1.05 * np.abs(v["de"]).max()))


def link(flight: Flight) -> LinkConfig:
    """Elevator on output 2, throttle on 3 (ArduPlane's defaults), 500 us for the
    elevator's travel, a higher PWM trailing edge down (reversed, as the NOC UAV's)."""
    return LinkConfig(elevator_us_per_rad=500.0 / elevator_travel(flight))


def flight_record(flight: Flight, lk: LinkConfig) -> FlightRecord:
    """The flight as the formats take it: what the sensors read (noise from the seed),
    the position and the air data as the vehicle reports them."""
    v = dict(flight.values)
    n = len(v["t"])
    v["wind_n"], v["wind_e"] = (np.full(n, w) for w in wind(flight.air, flight.seed))
    rng = np.random.default_rng(flight.seed)
    sigma = dict(zip(("V", "alpha", "theta", "q", "qdot", "a_x", "a_z"), NOISE, strict=True))
    sigma |= {"phi": NOISE[2], "p": NOISE[3], "r": NOISE[3], "a_y": NOISE[5]}
    sigma |= dict.fromkeys(("v_north", "v_east", "v_down"), GPS_VELOCITY_SIGMA)
    sensed = {k: v[k] + s * rng.standard_normal(n) for k, s in sigma.items()}
    sensed["alpha"] = _air_relative_alpha(v) + sigma["alpha"] * rng.standard_normal(n)
    rho = v["rho"]
    e_pwm = np.round(lk.elevator_pwm_center_us + v["de"] * lk.elevator_us_per_rad)
    throttle = np.clip(v["throttle"], 0.0, 1.0)
    lat0, lon0 = v["lat"][0], v["lon"][0]
    return FlightRecord(
        t_s=v["t"],
        elevator_rad=v["de"],
        elevator_pwm=e_pwm,
        elevator_out=-(e_pwm - lk.elevator_pwm_center_us) / 500.0,
        power=throttle,
        throttle_pwm=np.round(
            lk.throttle_pwm_min_us + throttle * (lk.throttle_pwm_max_us - lk.throttle_pwm_min_us)
        ),
        V=sensed["V"],
        alpha=sensed["alpha"],
        theta=sensed["theta"],
        q=sensed["q"],
        qdot=sensed["qdot"],
        a_x=sensed["a_x"],
        a_z=sensed["a_z"],
        north_m=(v["lat"] - lat0) * 6378137.0,
        height_m=v["h"] - HOME_ALT_M,
        v_north=sensed["v_north"],
        v_down=sensed["v_down"],
        pressure_pa=v["pressure"],
        temperature_c=v["pressure"] / (rho * atmosphere.R_AIR) - 273.15,
        density=rho,
        link=lk,
        throttle_model=True,
        phi=sensed["phi"],
        psi=v["psi"] % (2 * math.pi),
        p=sensed["p"],
        r=sensed["r"],
        a_y=sensed["a_y"],
        east_m=(v["lon"] - lon0) * 6378137.0 * math.cos(lat0),
        v_east=sensed["v_east"],
        wind_north=v["wind_n"],
        wind_east=v["wind_e"],
        name=f"the JSBSim {flight.aircraft.label}",
    )


def known(table: type, key: str) -> bool:
    """Whether the airframe file's table (a config dataclass) has this key: the lateral
    inertia and the spec sheet's propulsion are other work of issue 53, written as keys
    where the configuration reads them and as comments where it does not yet."""
    return key in {f.name for f in dataclasses.fields(table)}


def keyed(table: type, key: str, value: float) -> str:
    """`key = value`, commented out where the table has no such key yet."""
    return ("" if known(table, key) else "# ") + f"{key} = {value:.6g}"


def propulsion_lines(spec: Spec) -> list[str]:
    """[propulsion] from the spec sheet alone. A propeller: its diameter and the engine's
    power (several engines as one propeller of their discs' area with their power), as
    the spec-sheet keys where the configuration has them; else (and for a jet, which has
    no propeller) the exact propeller model's keys by the starter airframe file's rules:
    disc area from the diameter, prop_coefficient 1.0 (not fitted), the motor constant
    twice the top speed; a jet's disc the one whose full-throttle static thrust at sea
    level is the rated one."""
    k = 2.0 * spec.top_speed_mps
    head = [
        f"# The spec sheet: {spec.engines} x {spec.note}; top speed {spec.top_speed_mps:.4g} m/s.",
    ]
    if spec.diameter_m > 0:
        diameter = spec.diameter_m * math.sqrt(spec.engines)
        power = spec.power_w * spec.engines
        if spec.engines > 1:
            head.append("# As one propeller of the discs' area with the engines' power:")
        lines = [
            *head,
            "[propulsion]",
            'model = "propeller"',
            keyed(Propulsion, "prop_diameter_m", diameter),
            keyed(Propulsion, "max_power_w", power),
            f'engine = "{spec.engine}"',
        ]
        if known(Propulsion, "prop_diameter_m"):
            return lines
        area = math.pi * (diameter / 2) ** 2
    else:
        area = 2.0 * spec.engines * spec.static_thrust_n / (1.225 * k * k)
        head.append(f"# Rated static thrust {spec.static_thrust_n:.6g} N per engine.")
        lines = [*head, "[propulsion]", 'model = "propeller"']
    return [
        *lines,
        f"prop_area_m2 = {area:.6g}",
        "prop_coefficient = 1.0  # the starter file's value: not fitted",
        f"motor_constant_mps = {k:.6g}  # twice the top speed",
    ]


def airframe_toml(flight: Flight, lk: LinkConfig, ref: dict[str, tuple[float, float]]) -> str:
    """The airframe file a user would write: geometry, mass, inertia, the spec sheet's
    propulsion, the servo outputs; no vane, no filter tuning; JSBSim's references."""
    ac, v = flight.aircraft, flight.values
    adot = alpha_dot_terms(v)

    def mean(key: str) -> float:
        return float(np.mean(v[key]))

    return "\n".join(
        [
            f"# {ac.label} ({ac.kind}): JSBSim '{ac.model}' flown as a mission by "
            "benchmarks/jsbsim_missions.py.",
            "",
            "# The lateral inertia as JSBSim's inertia/ixx, izz, ixz give it (commented out",
            "# where the airframe file has no such keys yet).",
            "[airframe]",
            *(keyed(Airframe, f"inertia_{a}_kgm2", mean(f"i{a}")) for a in ("xx", "zz", "xz")),
            f'name = "{ac.label}"',
            f"mass_kg = {mean('mass'):.6g}",
            f"wing_area_m2 = {float(v['area'][0]):.6g}",
            f"mean_chord_m = {float(v['chord'][0]):.6g}",
            f"wing_span_m = {float(v['span'][0]):.6g}",
            f"inertia_yy_kgm2 = {mean('iyy'):.6g}",
            f"air_density_kgpm3 = {mean('rho'):.6g}  # the logs' pressure and temperature give it",
            f"trim_airspeed_mps = {float(v['V'][0]):.6g}",
            f"elevator_travel_deg = {math.degrees(elevator_travel(flight)):.6g}",
            f"thrust_inclination_rad = {float(np.median(v['incl'])):.6g}",
            f"thrust_moment_arm_m = {float(np.median(v['arm'])):.6g}",
            "",
            *propulsion_lines(flight.spec),
            "",
            "[coefficients]",
            *(f"{axis} = {regs}".replace("'", '"') for axis, regs in STRUCTURE.items()),
            "",
            "[link]",
            f"elevator_servo = {lk.elevator_servo}",
            f"elevator_us_per_rad = {lk.elevator_us_per_rad:.6g}",
            f"throttle_servo = {lk.throttle_servo}",
            "",
            "# JSBSim's own aerodynamics at every logged sample, fitted on the structure above",
            "# (fit residual RMS per axis in the comments). JSBSim's alpha-dot terms, which the",
            "# structure lacks and the fit takes in as they come: "
            + ", ".join(f"{n} = {x:.4g}" for n, x in adot.items())
            + ".",
            "[truth]",
            'label = "JSBSim"',
            *(f"{n} = {x:.6g}  # residual {r:.2g}" for n, (x, r) in ref.items()),
            "",
        ]
    )


def aerodynamic(v: dict[str, FloatArray]) -> dict[str, FloatArray]:
    """The flight's values with the pitch rate the aerodynamics see (JSBSim's
    q-aero: the body's less turbulence's pitch gust), as the references take it: with the
    body rate, a turbulent flight's fit takes the gust as noise on the q regressor (the
    T-37's Cmq comes out -10 windy against -50 calm; with the aerodynamic rate -50 both)."""
    return {**v, "q": v["q"] - v["gust_q"]}


def record_name(model: str, air: str, seed: int) -> str:
    return f"{model}_{air}_s{seed}"


class _Nowhere:
    """A port that sends nowhere: the stream is only recorded (the .tlog)."""

    def send(self, packet: bytes) -> None:
        pass

    def receive(self) -> list[bytes]:
        return []

    def close(self) -> None:
        pass


def write_tlog(fr: FlightRecord, path: Path, asked: bool) -> Path:
    """ArduPlane's stream as a station records it: the estimator's messages asked for at
    [link] rate_hz (asked), or every stream at what MAVProxy asks (4 Hz)."""
    inputs = np.column_stack([fr.elevator_rad, fr.power])
    measured = np.column_stack([fr.V, fr.alpha, fr.theta, fr.q, fr.qdot, fr.a_x, fr.a_z])
    rec = Recording(fr.t_s, inputs, measured, "throttle")
    vehicle = ArduPlaneVehicle(
        rec,
        fr.link,
        _Nowhere(),
        speed=0.0,
        tlog=path,
        asked_rates=parse_rates([], fr.link.rate_hz, asked),
        flight=fr,
    )
    vehicle.run()
    return path


def write_flight(flight: Flight, out: Path) -> dict[str, Any]:
    """Every file of one flight (module docstring); returns its summary (NAME.json)."""
    out.mkdir(parents=True, exist_ok=True)
    name = record_name(flight.aircraft.model, flight.air, flight.seed)
    lk = link(flight)
    v = flight.values
    ref = reference(aerodynamic(v), float(v["chord"][0]))
    airframe = out / f"{name}.toml"
    airframe.write_text(airframe_toml(flight, lk, ref), encoding="utf-8")
    config = load_config(airframe)
    truth = {1: tuple(ref[n][0] for n in config.coefficient_names)}
    fr = flight_record(flight, lk)
    flown = FlightAirframe(airframe.name, (), True)
    clean = out / f"{name}.clean.npz"
    np.savez_compressed(clean, allow_pickle=False, **clean_values(flight))
    files = [
        write_tlog(fr, out / f"{name}_asked.tlog", True),
        write_tlog(fr, out / f"{name}_default.tlog", False),
        write_bin(fr, out / f"{name}.bin"),
        write_ulg(fr, out / f"{name}.ulg"),
    ]
    for path in files:
        write_truth(path, truth, config.coefficient_names, flown)
    summary = {
        "name": name,
        "files": [p.name for p in (*files, clean)],
        "airframe": airframe.name,
        "reference": {n: {"value": x, "residual_rms": r} for n, (x, r) in ref.items()},
        "alpha_dot_terms": alpha_dot_terms(v),
        "flown": flown_summary(flight),
        "seconds_to_fly": flight.seconds,
    }
    (out / f"{name}.json").write_text(json.dumps(summary, indent=1), encoding="utf-8")
    return summary


CLEAN_KEYS = (
    *("t", "de", "thrust", "rho", "phi", "p", "r"),
    *("V", "alpha", "theta", "q", "qdot", "a_x", "a_z", "h_dot"),
    *("gust_u", "gust_w", "gust_q"),
)
"""NAME.clean.npz's arrays: time, the inputs (elevator as it moved, JSBSim's thrust [N],
density, bank, roll and yaw rate), the eight observations without noise at the CG (the
climb rate over the ground, up positive) and the gusts (jsbsim_flights._sample)."""


def clean_values(flight: Flight) -> dict[str, FloatArray]:
    """The flight's noise-free signals (CLEAN_KEYS) for the structure's best fit."""
    v = {**flight.values, "h_dot": -flight.values["v_down"]}
    return {k: np.asarray(v[k], float) for k in CLEAN_KEYS}


def flown_summary(flight: Flight) -> dict[str, float]:
    """How the mission went: duration, bank in the turns, sideslip, alpha's range, the
    climb and descent, the wind."""
    v = flight.values
    kinds = np.array([PLAN[int(k)].kind for k in v["phase"]])
    turning = kinds == "turn"
    turn_beta = v["beta"][turning]
    wn, we = wind(flight.air, flight.seed)
    return {
        "duration_s": float(v["t"][-1]),
        "turns": float(np.sum(np.diff(turning.astype(int)) == 1)),
        "largest_bank_deg": float(np.degrees(np.abs(v["phi"]).max())),
        "sideslip_rms_deg": float(np.degrees(np.sqrt(np.mean(v["beta"] ** 2)))),
        "sideslip_max_deg": float(np.degrees(np.abs(v["beta"]).max())),
        "turn_seconds": float(turning.sum() / RATE_HZ),
        # 0 where the flight is too short to reach a turn.
        "turn_sideslip_rms_deg": float(
            np.degrees(np.sqrt(np.sum(turn_beta**2) / max(len(turn_beta), 1)))
        ),
        "turn_sideslip_max_deg": float(np.degrees(np.max(np.abs(turn_beta), initial=0.0))),
        "alpha_min_deg": float(np.degrees(v["alpha"].min())),
        "alpha_max_deg": float(np.degrees(v["alpha"].max())),
        "altitude_range_m": float(v["h"].max() - v["h"].min()),
        "throttle_min": float(v["throttle"].min()),
        "throttle_max": float(v["throttle"].max()),
        "wind_mps": float(math.hypot(wn, we)),
    }


# --------------------------------------------------------------------------- the set


def _key(model: str, air: str, seed: int) -> str:
    text = repr((VERSION, model, air, seed, PLAN, DURATION_S, NOISE, SPECS[model]))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def fly_unit(args: tuple[str, str, int, str]) -> dict[str, Any]:
    """One flight flown and written, skipped where out/ holds it for this key."""
    model, air, seed, out_dir = args
    out = Path(out_dir)
    index = out / f"{record_name(model, air, seed)}.json"
    key = _key(model, air, seed)
    if index.exists():
        summary: dict[str, Any] = json.loads(index.read_text(encoding="utf-8"))
        if summary.get("key") == key and all((out / f).exists() for f in summary["files"]):
            return summary
    start = time.perf_counter()
    flight = fly(model, air, seed)
    summary = write_flight(flight, out)
    summary["seconds_to_write"] = time.perf_counter() - start - flight.seconds
    summary["key"] = key
    index.write_text(json.dumps(summary, indent=1), encoding="utf-8")
    return summary


def generate(
    seeds: Sequence[int] = (1,),
    jobs: int = 2,
    out: Path = OUT,
    models: Sequence[str] = MODELS,
) -> list[dict[str, Any]]:
    """Every model x air x seed, flown where out/ lacks it, in `jobs` processes."""
    out.mkdir(parents=True, exist_ok=True)
    units = [(m, air, s, str(out)) for m in models for air in AIRS for s in seeds]
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            return list(pool.map(fly_unit, units))
    return [fly_unit(u) for u in units]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--seeds", type=int, default=1, help="wind, turbulence and noise seeds 1..N")
    ap.add_argument("--jobs", type=int, default=2, help="processes flying the set")
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    args = ap.parse_args(argv)
    start = time.perf_counter()
    done = generate(tuple(range(1, args.seeds + 1)), args.jobs, Path(args.out), args.models)
    for s in done:
        f = s["flown"]
        print(
            f"{s['name']}: {f['duration_s']:.0f} s, {f['turns']:.0f} turns, bank up to "
            f"{f['largest_bank_deg']:.1f} deg, sideslip in turns rms "
            f"{f['turn_sideslip_rms_deg']:.2f} deg (at most {f['turn_sideslip_max_deg']:.1f}), "
            f"altitudes over {f['altitude_range_m']:.0f} m; flown in {s['seconds_to_fly']:.1f} s, "
            f"written in {s['seconds_to_write']:.1f} s"
        )
    print(f"{len(done)} flights in {time.perf_counter() - start:.1f} s ({args.jobs} jobs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
