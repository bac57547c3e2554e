"""Truth simulator: trims the aircraft, flies the manoeuvre, and makes sensor data.

It integrates the same equations the filter uses (gcs_estimator.model.equations) with the
true coefficients, plus what the filter does not model: Dryden turbulence, sensor noise,
constant biases and quantisation. Everything random comes from one seeded generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.linalg import solve_continuous_lyapunov

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.ingest.telemetry import pwm
from gcs_estimator.model import compiled  # noqa: F401  (makes the equations compilable)
from gcs_estimator.model.aircraft import Model, Trim, build_model, steady_residual, trim
from gcs_estimator.model.channels import LEGACY_OBS, N_FLIGHT, N_OBS
from gcs_estimator.model.equations import GRAV, ModelArrays, air_relative, fly_step, observe_in_gust
from sim.scenario import Manoeuvre, Simulation, Turbulence, scenario_of


@dataclass(frozen=True)
class Flight:
    """A simulated flight sampled at the sensor rate.

    t_s [N] vehicle time [s]; inputs [N x 2] elevator [rad] and throttle [0..1] (or
    thrust [N]), with turns [N x 6]: then the air density [kg/m^3], bank angle phi [rad],
    roll and yaw rate p, r [rad/s] (model.channels); measurements [N x 7] V [m/s],
    alpha [rad], theta [rad], q [rad/s], qdot [rad/s^2], a_x, a_z [m/s^2]; states [N x 4]
    the true air-relative V, alpha, theta, q; truth [p] the true coefficients.
    """

    t_s: FloatArray
    inputs: FloatArray
    measurements: FloatArray
    states: FloatArray
    truth: FloatArray
    trim: Trim
    clean: FloatArray
    """Noise-free observations [N x 7] (for tests of the measurement model)."""


def elevator_offset_rad(manoeuvre: Manoeuvre, t_s: float) -> float:
    """Elevator deflection from trim at time t [rad]: 3-2-1-1 multisteps, then pulses.

    A 3-2-1-1 multistep is +A for 3 units, -A for 2, +A for 1, -A for 1.
    """
    a = math.radians(manoeuvre.multistep_amplitude_deg)
    unit = manoeuvre.multistep_unit_s
    for start in manoeuvre.multistep_starts_s:
        tau = (t_s - start) / unit
        # The small offset puts a sample that falls on a switching time after the switch.
        tau += 1e-9
        if 0.0 <= tau < 3.0:
            return a
        if 3.0 <= tau < 5.0:
            return -a
        if 5.0 <= tau < 6.0:
            return a
        if 6.0 <= tau < 7.0:
            return -a
    for start, length, amp in zip(
        manoeuvre.pulse_starts_s,
        manoeuvre.pulse_durations_s,
        manoeuvre.pulse_amplitudes_deg,
        strict=True,
    ):
        if start <= t_s + 1e-9 < start + length:
            return math.radians(amp)
    return 0.0


class _GustModel:
    """Dryden gusts u_g (first order) and w_g (second order), unit-variance shaped, and
    with a wing span b > 0 the pitch gust q_g = (s / V) / (1 + (4 b / (pi V)) s) w_g.

    Shaping filters from MIL-F-8785C with frozen airspeed V; the output gain is set from
    the stationary covariance so that the gust standard deviations are exactly sigma.
    The pitch gust is flown as the filters model it (equations.pitch_gust_rows): its
    state p = q_g - c w_g, c = pi / (4 b), follows p' = -c V q_g.
    """

    def __init__(
        self, turb: Turbulence, airspeed: float, rng: np.random.Generator, span_m: float = 0.0
    ) -> None:
        self.c = math.pi / (4.0 * span_m) if span_m > 0.0 else 0.0
        self.airspeed = airspeed
        Tu = turb.length_u_m / airspeed
        Tw = turb.length_w_m / airspeed
        self.A = np.array([[-1.0 / Tu, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0 / Tw**2, -2.0 / Tw]])
        B = np.eye(3)[:, [0, 2]]
        self.B = B
        Pss = solve_continuous_lyapunov(self.A, -B @ B.T)
        cu = np.array([1.0, 0.0, 0.0])
        cw = np.array([0.0, 1.0, math.sqrt(3.0) * Tw])
        self.C = np.vstack(
            [
                turb.sigma_u * cu / math.sqrt(cu @ Pss @ cu),
                turb.sigma_w * cw / math.sqrt(cw @ Pss @ cw),
            ]
        )
        self.active = turb.sigma_u > 0.0 or turb.sigma_w > 0.0
        self.z = rng.multivariate_normal(np.zeros(3), Pss) if self.active else np.zeros(3)
        self.rng = rng
        self.p = -self.c * float(self.C[1] @ self.z)  # q_g = 0 at the start

    def step(self, dt: float) -> None:
        if self.active:
            qg = self.p + self.c * float(self.C[1] @ self.z)
            noise = self.rng.standard_normal(2) * math.sqrt(dt)
            self.z = self.z + self.A @ self.z * dt + self.B @ noise
            self.p -= self.c * self.airspeed * qg * dt

    def gust(self) -> FloatArray:
        """[u_g, w_g] in m/s, then q_g [rad/s] where the span gives a pitch gust."""
        g = self.C @ self.z
        if self.c > 0.0:
            return np.array([g[0], g[1], self.p + self.c * g[1]])
        return np.asarray(g)


MULTISTEP_UNITS = ((0.0, 3.0), (3.0, 5.0), (5.0, 6.0), (6.0, 7.0))
"""The 3-2-1-1 multistep's steps, in units from its start (+A, -A, +A, -A)."""


def elevator_offsets_rad(manoeuvre: Manoeuvre, t_s: np.ndarray) -> FloatArray:
    """elevator_offset_rad at every time of t_s [s] (ascending), in one pass over each
    multistep's and pulse's own span of samples: linear in the flight's length."""
    t = np.asarray(t_s, float)
    if len(t) > 1 and np.any(np.diff(t) < 0):
        return np.array([elevator_offset_rad(manoeuvre, float(v)) for v in t])
    out = np.zeros_like(t)
    # Earlier entries win, as in elevator_offset_rad: assign in reverse order.
    pulses = zip(
        manoeuvre.pulse_starts_s,
        manoeuvre.pulse_durations_s,
        manoeuvre.pulse_amplitudes_deg,
        strict=True,
    )
    for start, length, amp in reversed(list(pulses)):
        lo, hi = np.searchsorted(t, [start - 1e-6, start + length + 1e-6])
        seg = t[lo:hi] + 1e-9
        inside = (start <= seg) & (seg < start + length)
        out[lo:hi][inside] = math.radians(amp)
    a = math.radians(manoeuvre.multistep_amplitude_deg)
    unit = manoeuvre.multistep_unit_s
    for start in reversed(manoeuvre.multistep_starts_s):
        lo, hi = np.searchsorted(t, [start - unit, start + 8.0 * unit])
        tau = (t[lo:hi] - start) / unit + 1e-9
        level = np.select(
            [(tau >= lo_) & (tau < hi_) for lo_, hi_ in MULTISTEP_UNITS],
            [a, -a, a, -a],
            np.nan,
        )
        hit = ~np.isnan(level)
        out[lo:hi][hit] = level[hit]
    return out


def perturbed(config: AircraftConfig, seed: int, spread: float) -> AircraftConfig:
    """The config with its true coefficients moved by spread/2 to spread of their value,
    each up or down at random (seeded by seed): an aircraft that is not the paper's, for
    showing that nothing is tuned to the paper's values. spread <= 0: unchanged."""
    if config.truth is None:
        raise ValueError(f"{config.source}: [truth] is needed to perturb it")
    if spread <= 0.0:
        return config
    rng = np.random.default_rng(10_000 + seed)
    n = len(config.truth)
    factors = 1.0 + spread * rng.choice([-1.0, 1.0], size=n) * rng.uniform(0.5, 1.0, size=n)
    return config.with_truth(tuple(float(v) for v in np.array(config.truth) * factors))


def simulate(
    config: AircraftConfig,
    seed: int | None = None,
    truth: FloatArray | None = None,
    scenario: Simulation | None = None,
) -> Flight:
    """Fly the manoeuvre of `scenario` (default: the config file's [simulation] table,
    sim.scenario) with the true coefficients and sample the sensors.

    The state flown is the motion over the ground; the air-relative state (V + u_g,
    alpha + w_g/V) drives the aerodynamics and is what the air-data sensors see
    (equations.wind_slope).
    """
    if truth is None:
        if config.truth is None:
            raise ValueError(f"{config.source}: [truth] is needed to simulate this aircraft")
        truth = np.array(config.truth)
    sim = scenario_of(config) if scenario is None else scenario
    rng = np.random.default_rng(sim.seed if seed is None else seed)
    model = build_model(config, gust_states=False)
    trimmed = trim(model, truth)
    gusts = _GustModel(sim.turbulence, float(trimmed.state[0]), rng, config.airframe.wing_span_m)

    dt = sim.integration_step_s
    per_sample = max(1, round(1.0 / (sim.sample_rate_hz * dt)))
    dt = 1.0 / (sim.sample_rate_hz * per_sample)
    n_samples = int(math.floor(sim.manoeuvre.duration_s * sim.sample_rate_hz + 1e-9)) + 1

    de0, power0 = servo_commands(config, trimmed.inputs.reshape(1, 2))[0]
    x0 = model.augment(_steady_state(model, truth, trimmed.state, de0, power0), truth)
    sensors = sim.sensors
    noise_sigma = _per_channel(sensors.noise_sigma)
    bias = _per_channel(sensors.bias)
    quantum = _per_channel(sensors.quantum)

    n_steps = (n_samples - 1) * per_sample
    t_samples = np.arange(n_samples) / sim.sample_rate_hz
    # Inputs are piecewise constant; evaluating them mid-step makes a switch on a step
    # boundary act from that step on, and at a sample time from that sample on.
    t_mid = (np.arange(n_steps) + 0.5) * dt
    u_steps = np.column_stack(
        [de0 + elevator_offsets_rad(sim.manoeuvre, t_mid), np.full(n_steps, power0)]
    )
    u_samples = np.column_stack(
        [de0 + elevator_offsets_rad(sim.manoeuvre, t_samples), np.full(n_samples, power0)]
    )
    if sim.banked or sim.throttle.starts_s:
        turn = TurnFeed(model, truth, trimmed, sim, config.airframe.air_density_kgpm3)
        held = (np.arange(n_steps) // per_sample) / sim.sample_rate_hz
        u_steps = turn.inputs(u_steps, np.asarray(t_mid, np.float64), held)
        u_samples = turn.inputs(u_samples, t_samples)
    if sim.actuator_time_constant_s > 0.0:
        # The servo lags its command: the elevator moves between samples, flown as it
        # moves and reported (to PWM resolution) as it stands at each sample.
        position = servo_lag(u_steps[:, 0], de0, dt, sim.actuator_time_constant_s)
        u_steps[:, 0] = 0.5 * (position[:-1] + position[1:])
        u_samples[:, 0] = position[::per_sample]
        u_samples = servo_commands(config, u_samples)
    else:
        u_steps = servo_commands(config, u_steps)
        u_samples = servo_commands(config, u_samples)
    gust = np.empty((n_steps + 1, 3 if gusts.c > 0.0 else 2))
    for i in range(n_steps + 1):
        gust[i] = gusts.gust()
        gusts.step(dt)

    air_states, clean = integrate(x0, u_steps, u_samples, gust, dt, per_sample, model.arrays)
    # The seven channels' noise drawn first, as before the climb rate: a flight without
    # it is the same flight, seed for seed.
    noise = np.zeros(clean.shape)
    noise[:, :LEGACY_OBS] = rng.standard_normal((clean.shape[0], LEGACY_OBS))
    if sim.climb_rate:
        noise[:, LEGACY_OBS:] = rng.standard_normal((clean.shape[0], N_OBS - LEGACY_OBS))
    y = clean + bias + noise_sigma * noise
    q_nz = quantum > 0
    y[:, q_nz] = np.round(y[:, q_nz] / quantum[q_nz]) * quantum[q_nz]
    if not sim.vane:
        y[:, 1] = np.nan
    if not sim.climb_rate:
        y[:, LEGACY_OBS:] = np.nan
    t_out, u_out, y_out, x_out, clean_out = t_samples, u_samples, y, air_states, clean
    return Flight(
        t_s=t_out,
        inputs=u_out,
        measurements=y_out,
        states=x_out,
        truth=np.asarray(truth, float),
        trim=trimmed,
        clean=clean_out,
    )


class TurnFeed:
    """The inputs of a mission (sim.scenario Turns, ThrottleSteps): the bank profile and
    its roll and yaw rates as inputs, the throttle steps, and the elevator and throttle an
    autopilot adds to hold height in a turn (feedforward, from the level turn's trim at
    the turn's full bank, scaled with the load factor's increment 1/cos(phi) - 1)."""

    def __init__(
        self, model: Model, truth: FloatArray, trimmed: Trim, sim: Simulation, rho: float
    ) -> None:
        self.sim = sim
        self.rho = rho
        self.V = float(trimmed.state[0])
        self.g = float(model.k[GRAV])
        self.extra: dict[float, tuple[float, float]] = {}
        for bank in set(sim.turns.banks_deg):
            self.extra[bank] = self._turn_trim(model, truth, trimmed, math.radians(bank))

    def _turn_trim(
        self, model: Model, truth: FloatArray, trimmed: Trim, phi: float
    ) -> tuple[float, float]:
        """(elevator, throttle) added to trim for a level turn at bank phi."""
        from scipy.optimize import least_squares

        omega = self.g * math.tan(phi) / self.V
        q, r = omega * math.sin(phi), omega * math.cos(phi)
        de0, power0 = trimmed.inputs

        def residual(z: FloatArray) -> FloatArray:
            x = model.augment(np.array([self.V, z[0], z[0], q]), truth)
            u = np.array([de0 + z[1], power0 + z[2], self.rho, phi, 0.0, r])
            f, _ = model.f(x, u)
            return np.array([f[0], f[1] * self.V, f[3]])

        z0 = np.array([float(trimmed.state[1]), 0.0, 0.0])
        sol = least_squares(residual, z0, xtol=1e-14, ftol=1e-14, gtol=1e-14)
        return float(sol.x[1]), float(sol.x[2])

    def bank(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """phi, p [rad, rad/s] at times t, and the elevator and throttle added for it."""
        turns = self.sim.turns
        phi = np.zeros_like(t)
        p = np.zeros_like(t)
        de = np.zeros_like(t)
        dp = np.zeros_like(t)
        T = turns.roll_s
        for start, length, bank in zip(
            turns.starts_s, turns.durations_s, turns.banks_deg, strict=True
        ):
            B = math.radians(bank)
            tau = t - start
            roll_in = (tau >= 0.0) & (tau < T)
            hold = (tau >= T) & (tau < length - T)
            roll_out = (tau >= length - T) & (tau < length)
            phi[roll_in] = 0.5 * B * (1.0 - np.cos(math.pi * tau[roll_in] / T))
            p[roll_in] = 0.5 * B * math.pi / T * np.sin(math.pi * tau[roll_in] / T)
            phi[hold] = B
            back = tau[roll_out] - (length - T)
            phi[roll_out] = 0.5 * B * (1.0 + np.cos(math.pi * back / T))
            p[roll_out] = -0.5 * B * math.pi / T * np.sin(math.pi * back / T)
            inside = (tau >= 0.0) & (tau < length)
            share = (1.0 / np.cos(phi[inside]) - 1.0) / (1.0 / math.cos(B) - 1.0)
            de[inside] = self.extra[bank][0] * share
            dp[inside] = self.extra[bank][1] * share
        return phi, p, de, dp

    def throttle(self, t: FloatArray) -> FloatArray:
        out = np.zeros_like(t)
        steps = self.sim.throttle
        for start, length, amount in zip(
            steps.starts_s, steps.durations_s, steps.amounts, strict=True
        ):
            out[(t >= start - 1e-9) & (t < start + length - 1e-9)] = amount
        return out

    def inputs(
        self, u: FloatArray, t: FloatArray, t_commands: FloatArray | None = None
    ) -> FloatArray:
        """u [N x 2] with the turns' and steps' elevator and throttle added, and the
        density, phi, p, r columns; t_commands (default t): the times the elevator and
        throttle are commanded at. An autopilot's commands hold from one output to the
        next, while the bank moves between them: flown between samples, the commands are
        those of the sample before (decision 0077)."""
        phi, p, de, dp = self.bank(t)
        tc = t
        if t_commands is not None:
            tc = t_commands
            _, _, de, dp = self.bank(tc)
        r = self.g * np.sin(phi) / self.V
        out = np.column_stack([u[:, 0] + de, u[:, 1] + dp + self.throttle(tc)])
        if self.sim.banked:
            out = np.column_stack([out, np.full(len(t), self.rho), phi, p, r])
        return out


def _per_channel(values: tuple[float, ...]) -> FloatArray:
    """One value per observation channel, zero for channels a scenario made in code before
    the climb rate does not name."""
    out = np.zeros(N_OBS)
    out[: len(values)] = values
    return out


def servo_lag(command: FloatArray, start: float, dt: float, tau: float) -> FloatArray:
    """Positions of a first-order servo (time constant tau [s]) at the step boundaries,
    from `start`, under commands held over each step of dt [s] (exact per step)."""
    decay = math.exp(-dt / tau)
    position = np.empty(command.shape[0] + 1)
    position[0] = start
    for i, c in enumerate(command):
        position[i + 1] = c + (position[i] - c) * decay
    return position


def _steady_state(
    model: Model, truth: FloatArray, guess: FloatArray, de: float, power: float
) -> FloatArray:
    """Steady straight flight (q = 0) at the given servo commands: V, alpha and theta
    such that Vdot = alphadot = qdot = 0 (a climb or descent of a few hundredths of a
    degree, where the rounded commands do not hold level flight at V0)."""
    from scipy.optimize import least_squares

    def residual(z: FloatArray) -> FloatArray:
        return steady_residual(model, truth, z, np.array([de, power]))

    sol = least_squares(residual, guess[:3], xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return np.array([sol.x[0], sol.x[1], sol.x[2], 0.0])


def servo_commands(config: AircraftConfig, inputs: FloatArray) -> FloatArray:
    """The inputs as the servos receive them: whole microseconds of PWM (the link's
    mapping), which is also what SERVO_OUTPUT_RAW reports. Flying the unrounded values
    while reporting rounded ones would give the station a thrust 0.25 N off at trim
    (throttle 0.316), a bias the filters cannot know of."""
    link = config.link
    out = np.array(inputs, float)
    out[:, 0] = pwm.elevator_rad(link, np.round(pwm.elevator_pwm(link, out[:, 0])))
    if config.propulsion.model == "propeller":
        out[:, 1] = pwm.throttle(link, np.round(pwm.throttle_pwm(link, out[:, 1])))
    return out


@njit(cache=True)
def integrate(
    x0: FloatArray,
    u_steps: FloatArray,
    u_samples: FloatArray,
    gust: FloatArray,
    dt: float,
    per_sample: int,
    m: ModelArrays,
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    """Fly x0 (the motion over the ground) with classical Runge-Kutta through the air's
    motion (equations.fly_step), inputs u_steps [steps x 2] and gust [steps + 1 x 2 or 3]
    (u_g, w_g and, with a wing span, the pitch gust q_g) held
    over each step of dt [s]; every per_sample steps, sample the air-relative flight
    states and the noise-free observations with u_samples."""
    n_samples = u_samples.shape[0]
    states = np.empty((n_samples, N_FLIGHT))
    clean = np.empty((n_samples, N_OBS))
    x = x0.copy()
    step = 0
    for i in range(n_samples):
        xa = air_relative(x, gust[step])
        states[i] = xa[:N_FLIGHT]
        clean[i] = observe_in_gust(x, u_samples[i], gust[step], m)
        if i == n_samples - 1:
            break
        for _ in range(per_sample):
            x = fly_step(x, u_steps[step], u_steps[step], gust[step], dt, m)
            step += 1
    return states, clean
