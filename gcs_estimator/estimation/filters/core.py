"""One filter step over values: the contract the numpy reference and the compiled kernel
both keep.

    step(state, t, u, y, tuning, model) -> (state', info)

predicts the belief N(x, P) from state.t to vehicle time t [s] and updates it with the
observations y [7] (NaN = missing). Everything a filter carries from one frame to the next
is in FilterState; nothing is hidden on an object, so a restart is a new initial state.
Which backend runs is chosen once (`stepper`); both have the same failure semantics:

- an innovation covariance that is not positive definite skips the update: the state is
  the prediction, innovations and NIS are NaN, `failed` is set;
- a covariance that lost positive definiteness to rounding is repaired (eigenvalue floor)
  and `repaired` is set;
- a belief that went non-finite starts again from the configured prior at this frame, and
  `diverged` is set.

Process noise (Q, continuous-time spectral density, diagonal):

    Q = diag(q) + sigma_w^2 diag(gust_unit)

where sigma_w^2 is the vertical gust variance estimated online by covariance matching
(GustState), applied only once detected; gust_unit drives the gust states where the
layout has them (filter.turbulence.model = "states"), else the flight states.

Source: Meng, Liu and Veres (2010), sections III-IV; docs/model.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal, NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_OBS, Channel
from gcs_estimator.model.equations import ModelArrays
from gcs_estimator.model.turbulence import gust_state_densities

FilterKind = Literal["EKF", "IEKF"]
FILTER_KINDS: tuple[FilterKind, ...] = ("EKF", "IEKF")
Backend = Literal["fast", "reference"]

GUST_SENSITIVITY_EVERY = 25
"""Steps between refreshes of the channels' sensitivity to the gust level (they only
weigh the channels, and change with the flight state slowly)."""

GUST_VAR_FLOOR = -0.1
"""Lowest running gust variance [m^2/s^2]: in calm air the estimate wanders around zero;
the floor keeps it from drifting so far below that real turbulence takes long to show."""

STATE_MARGIN = 2.0
"""A belief's flight states may reach this multiple of the largest a signal can be before
it counts as run away (Tuning.state_max)."""

GUST_STATE_FLOOR = 1e-3
"""Gust intensity [m/s] the gust states always carry (process noise and initial spread),
so that their variance never reaches zero in calm air: a belief with a zero variance
would count as unhealthy and be repaired at every pass."""

GUST_CLIP = 25.0
"""Squared innovations count at most this many times their variance (5 sigma) in the
covariance matching, so that a glitch or the zero-start transient does not set the level."""

GUST_ADAPT_TIME_S = 2.0
"""Averaging time of the running gust level [s] (GustState): a few seconds of data judge
it, so that it follows turbulence that comes and goes."""

GUST_STILL_BAND_RAD = math.radians(0.2)
"""Elevator moves within this band [rad] leave the inputs still (adapt_gust; decision
0015)."""

GUST_MAX_WAIT_S = 10.0
"""When the inputs have not been still for this long [s] (a flight with the elevator always
moving), every step informs the gust level (adapt_gust)."""

MAX_STEP_S = 0.02
"""Longest Runge-Kutta step of the prediction [s]: 50 Hz, the rate of the paper's data;
longer intervals (the HFB-320's 10 Hz) are split."""

MAX_GAP_S = 2.0
"""Longest prediction [s]: after a longer gap between frames the flight states start
afresh from the next measurement (the coefficients are kept), so that a far-future time
never makes the filters integrate for hours."""

FLIGHT_PRIOR_SIGMA: tuple[float, ...] = (1.0, 0.02, 0.02, 0.02)
"""Prior 1 sigma of the flight states [V m/s, alpha rad, theta rad, q rad/s] about their
first measurement (or trim speed and zeros where it has none)."""

BIAS_SIGMA: tuple[float, ...] = (
    1.0,
    math.radians(2.0),
    math.radians(2.0),
    0.01,
    0.1,
    0.5,
    0.5,
    0.5,
)
"""Prior 1 sigma of an estimated sensor bias, per channel [SI]; the biases are constant
(no process noise)."""


class GustState(NamedTuple):
    """Online estimate of the vertical gust variance sigma_w^2 [m^2/s^2].

    Covariance matching: each step estimates the level at which its innovations e_c are as
    large as predicted, from (e_c^2 - S_c) / G_c per channel, G_c = dt sum_j H_cj^2 unit_j
    the change of S_c per unit gust variance, weighted by G_c^2 / (2 S_c^2) (their Fisher
    information). The running estimate is an exponential average with gain
    g = dt / GUST_ADAPT_TIME_S, each step's share scaled by its information over the
    running information (g itself where every frame carries the same channels); the pass
    sums give the average over the whole pass. Which steps inform it: adapt_gust.
    """

    var: float
    """Running estimate; may dip below zero in calm air so that it averages to the truth."""
    info: float
    """Running Fisher information I of one step's estimate (0: nothing measured yet)."""
    gain: float
    """The averaging gain g of the last step."""
    pass_num: float
    pass_den: float
    """Information-weighted sums of the step estimates since the pass started."""
    sens: FloatArray
    """Per-channel G_c / dt [N_OBS], refreshed every GUST_SENSITIVITY_EVERY steps."""
    sens_age: int
    input_ref: float
    """Elevator [rad] at its last move beyond the still band (NaN: none seen yet)."""
    t_moved: float
    """Vehicle time of that move [s] (-inf: none in this pass)."""
    t_still: float
    """Vehicle time the inputs were last still [s] (NaN: no step yet)."""

    @staticmethod
    def start(var: float) -> GustState:
        return GustState(
            var,
            0.0,
            0.0,
            0.0,
            0.0,
            np.zeros(N_OBS),
            GUST_SENSITIVITY_EVERY,
            math.nan,
            -math.inf,
            math.nan,
        )

    def applied(self, detection2: float) -> float:
        """The level in the process noise: the running estimate where it stands at least
        detection_sigma of its standard errors above zero, else 0. The exponential average
        of one-step estimates of variance 1/I has variance g / (2 - g) / I. A level not yet
        measured in this pass (configured, or carried over by a restart) is used as is."""
        return gust_applied(self.var, self.info, self.gain, detection2)

    def pass_average(self) -> float:
        """The pass's information-weighted average level, >= 0 (the running level if
        nothing was measured)."""
        return pass_average(self.var, self.pass_num, self.pass_den)

    def pass_z(self) -> float:
        """The pass's average level in its standard errors, 1/sqrt(sum of the steps'
        information): how far the whole pass says the air was turbulent (NaN: nothing
        measured). Where the running level, judged over GUST_ADAPT_TIME_S, stays below its
        detection threshold, a whole pass can still find turbulence: weak gusts, or ones of
        a long scale length."""
        if self.pass_den <= 0.0:
            return math.nan
        return self.pass_num / math.sqrt(self.pass_den)


def pass_average(var: float, pass_num: float, pass_den: float) -> float:
    """See GustState.pass_average (a function of scalars, so that the kernel shares it)."""
    if pass_den <= 0.0:
        return max(var, 0.0)
    return max(pass_num / pass_den, 0.0)


def gust_applied(var: float, info: float, gain: float, detection2: float) -> float:
    """See GustState.applied (a function of scalars, so that the kernel shares it)."""
    if var > 0.0 and (info <= 0.0 or var * var * info * (2.0 - gain) >= detection2 * gain):
        return var
    return 0.0


class FilterState(NamedTuple):
    """Everything one filter carries from one frame to the next."""

    x: FloatArray
    """Augmented state estimate [n] (layout: model.state)."""
    P: FloatArray
    """Its covariance [n x n]."""
    t: float
    """Vehicle time of the belief [s]."""
    u: FloatArray
    """Inputs held since t [elevator rad, throttle or thrust N]."""
    gust: GustState


class Tuning(NamedTuple):
    """One filter's settings, as the step takes them (built once from the config)."""

    R: FloatArray
    """Measurement noise covariance [N_OBS x N_OBS]."""
    q: FloatArray
    """Process-noise spectral density per state [n], before turbulence (gust_unit)."""
    gust_unit: FloatArray
    """Process-noise spectral density per unit sigma_w^2 [n] (zero but on the gust states,
    or on the flight states where turbulence is white process noise)."""
    iterations: int
    """Measurement-update iterations: 1 is the EKF, more the IEKF."""
    relinearise: float
    """Keep the IEKF's iterations only when they move some coefficient by at least this many
    EKF-posterior sigmas (0: always iterate). See hybrid.iekf_update."""
    max_step_s: float
    """Longest Runge-Kutta step of the prediction [s] (MAX_STEP_S)."""
    adaptive: bool
    """Estimate the gust level online."""
    detection2: float
    """Squared detection threshold of the gust level, in its standard errors."""
    prior_sigma: FloatArray
    """Prior sigma of the whole augmented state [n]: the coefficients' as configured, the
    flight states' FLIGHT_PRIOR_SIGMA about their first measurement. The prior mean of the
    coefficients is zero (the paper's start; the restarts start from the data)."""
    gust_var0: float
    """Configured initial gust variance [m^2/s^2]."""
    linear_inputs: bool
    """Inputs linear between samples (first-order hold), else held at the earlier sample."""
    state_max: FloatArray
    """Largest magnitude of each flight state [V, alpha, theta, q] a belief may hold
    (twice what an aircraft's signals reach, config.PLAUSIBLE_MAX); beyond it, or at an
    airspeed not above zero, the belief has run away (see plausible)."""
    settle_s: float
    """Time after the elevator's last move before a step informs the gust level [s]."""
    r_gust: FloatArray
    """Per observation channel, the measurement variance a unit gust variance adds, times
    the frame interval [s] (measurement_noise): the vertical wind in the climb rate where
    turbulence is white process noise (decision 0060); zero elsewhere."""


class StepInfo(NamedTuple):
    """What one step reports."""

    sigma: FloatArray
    """sqrt(diag(P)) after the step [n]."""
    nis: float
    """e^T S^-1 e over the channels used; NaN when the update failed."""
    n_used: int
    iterations: int
    innovation: FloatArray
    """y - h(x-) per channel, NaN where not used [N_OBS]."""
    innovation_sigma: FloatArray
    """sqrt(diag(S)) per channel, NaN where not used [N_OBS]."""
    gust_sigma: float
    """Vertical gust intensity the step's process noise assumed [m/s]."""
    gust_pass_sigma: float
    """The intensity averaged over the pass so far, after the step [m/s]
    (GustState.pass_average): what the whole pass says of the air, where the running
    level may not pass its detection test."""
    failed: bool = False
    repaired: bool = False
    diverged: bool = False


def tuning_of(config: AircraftConfig, model: Model, kind: FilterKind) -> Tuning:
    """The step's settings for one filter kind from the config."""
    ft = config.filter
    n = model.n
    flight, coef = model.flight, model.coefficients
    q = np.zeros(n)
    q[flight] = ft.process_noise.states
    q[coef] = ft.process_noise.coefficients
    unit = np.zeros(n)
    turb = ft.turbulence
    v0 = float(model.k[eq.V0])
    if model.has_gust_states:
        # The pitch gust's state, where there is one, takes no noise of its own.
        unit[model.gusts.start : model.gusts.start + 2] = gust_state_densities(
            v0, turb.sigma_u_ratio, turb.length_u_m, turb.length_w_m
        )
        q[model.gusts] = GUST_STATE_FLOOR**2 * unit[model.gusts]
    else:
        unit[flight] = turb.unit(v0)
    prior_sigma = np.zeros(n)
    prior_sigma[flight] = FLIGHT_PRIOR_SIGMA
    prior_sigma[coef] = ft.initial_sigma.coefficients
    prior_sigma[model.biases] = np.array(BIAS_SIGMA)[list(config.sensors.bias_channels)]
    r_gust = np.zeros(N_OBS)
    if not model.has_gust_states:
        r_gust[Channel.HDOT] = climb_rate_gust(turb.length_w_m, v0)
    return Tuning(
        R=np.diag(np.square(ft.measurement_sigma)),
        q=q,
        gust_unit=unit,
        iterations=1 if kind == "EKF" else ft.iterations,
        relinearise=ft.relinearise_sigma,
        max_step_s=MAX_STEP_S,
        adaptive=ft.turbulence.adaptive,
        detection2=ft.turbulence.detection_sigma**2,
        prior_sigma=prior_sigma,
        gust_var0=ft.turbulence.sigma_w_mps**2,
        linear_inputs=config.data.input_hold == "linear",
        state_max=STATE_MARGIN
        * np.array([config.data.plausible(q) for q in ("airspeed", "alpha", "theta", "q")]),
        settle_s=turb.settle_s,
        r_gust=r_gust,
    )


def climb_rate_gust(length_w_m: float, airspeed_mps: float) -> float:
    """The climb rate's measurement variance per unit gust variance, times the frame
    interval [s], where turbulence is white process noise (decision 0060).

    The climb rate is the motion over the ground; the filter's alpha, driven by the white
    gust noise, is the air's. Their difference is the vertical wind w_g, which goes into
    the climb rate's innovation whole: variance sigma_w^2, correlated over about
    T = L_w / V. The coefficients feel its slow part (alpha's level), whose spectral
    density at zero frequency is that of white noise of density 2 sigma_w^2 T: frames
    dt apart carry as much about a level as independent ones of variance
    2 sigma_w^2 T / dt each. So that is what it adds to the climb rate's R."""
    return 2.0 * length_w_m / airspeed_mps


def measurement_noise(tuning: Tuning, applied: float, dt: float) -> FloatArray:
    """The step's measurement noise covariance: R, plus the gust level applied times
    r_gust / dt on the diagonal (the vertical wind in the climb rate)."""
    if not (applied > 0.0 and dt > 0.0):
        return tuning.R
    R = tuning.R.copy()
    for c in range(R.shape[0]):
        R[c, c] += applied * tuning.r_gust[c] / dt
    return R


def initial_state(
    model: Model,
    tuning: Tuning,
    t: float,
    u: FloatArray,
    y: FloatArray,
    coefficients: FloatArray | None = None,
    coefficient_sigma: FloatArray | None = None,
    gust_var: float | None = None,
    guess: FloatArray | None = None,
) -> FilterState:
    """The belief at the first frame of a pass: flight states from the measurement where
    present (else `guess`, the flight states last believed, where given; else trim speed
    and zeros), coefficients N(coefficients, sigma^2) (default: the configured prior),
    the gust level given (default: configured)."""
    x = np.zeros(model.n)
    sigma = tuning.prior_sigma.copy()
    flight = model.flight
    state = np.array([model.k[eq.V0], 0.0, 0.0, 0.0])
    if guess is not None:
        state = np.where(np.isfinite(guess), guess, state)
    measured = np.isfinite(y[flight])
    state[measured] = y[flight][measured]
    if not measured[1]:  # no vane: alpha from the climb rate (decision 0049)
        phi = eq.bank(np.asarray(u, float))[0]
        climb = float(y[Channel.HDOT]) if y.shape[0] > Channel.HDOT else math.nan
        alpha = eq.alpha_from_climb(state[0], state[2], climb, phi)
        if math.isfinite(alpha):
            state[1] = alpha
        elif guess is None:
            state[1] = 0.0
    x[flight] = state
    if coefficients is not None:
        x[model.coefficients] = coefficients
    if coefficient_sigma is not None:
        sigma[model.coefficients] = coefficient_sigma
    level = tuning.gust_var0 if gust_var is None else gust_var
    gusts = model.gusts
    if model.has_gust_states:
        # Gust states start at zero with their stationary spread at this level: a
        # first-order process of density q and time constant L/V has variance q L/(2 V).
        lengths = np.array([model.k[eq.GUST_LU], model.k[eq.GUST_LW]])
        ug_wg = slice(gusts.start, gusts.start + 2)
        stationary = tuning.gust_unit[ug_wg] * lengths / (2.0 * model.k[eq.V0])
        sigma[ug_wg] = np.sqrt(max(level, GUST_STATE_FLOOR**2) * stationary)
        if eq.has_pitch_gust(model.arrays):
            # p_g = q_g - c w_g starts at zero with w_g's spread scaled by c: q_g = 0
            # within the pitch gust's own spread.
            sigma[gusts.start + 2] = eq.pitch_gust_scale(model.k) * sigma[gusts.start + 1]
    P = np.diag(sigma**2)
    if eq.has_pitch_gust(model.arrays) and not model.has_gust_states:
        # p_g = q_g - c V alpha: q_g = 0 within c sigma_w, independent of the flight
        # states, so p_g is tied to the beliefs of V and alpha.
        p, v, a = gusts.start, flight.start, flight.start + 1
        c = eq.pitch_gust_scale(model.k)
        x[p] = -c * x[v] * x[a]
        P[p, v] = P[v, p] = -c * x[a] * P[v, v]
        P[p, a] = P[a, p] = -c * x[v] * P[a, a]
        P[p, p] = (
            (c * x[a]) ** 2 * P[v, v]
            + (c * x[v]) ** 2 * P[a, a]
            + c**2 * max(level, GUST_STATE_FLOOR**2)
        )
    return FilterState(
        x=x,
        P=P,
        t=t,
        u=np.array(u, float),
        gust=GustState.start(level),
    )


def rebase(
    state: FilterState, model: Model, tuning: Tuning, t: float, y: FloatArray
) -> FilterState:
    """A new time base (the vehicle clock reset): keep what is known of the coefficients,
    take the flight states (and a pitch gust's state tied to alpha) afresh from the
    measurement with their initial uncertainty.
    The flight states the frame does not measure start from those last believed (the
    frame's alpha from its climb rate where it has one): nearer than trim and zeros, with
    the same initial uncertainty. The gust estimate's clocks keep their age."""
    fresh = initial_state(model, tuning, t, state.u, y, guess=state.x[model.flight])
    # The flight states, and a pitch gust's state tied to alpha (white gust noise).
    afresh = list(range(model.flight.start, model.flight.stop))
    if eq.has_pitch_gust(model.arrays) and not model.has_gust_states:
        afresh.append(model.gusts.start)
    x = state.x.copy()
    P = state.P.copy()
    x[afresh] = fresh.x[afresh]
    P[afresh, :] = 0.0
    P[:, afresh] = 0.0
    P[np.ix_(afresh, afresh)] = fresh.P[np.ix_(afresh, afresh)]
    shift = t - state.t
    g = state.gust
    return state._replace(
        x=x,
        P=P,
        t=t,
        u=np.full(state.u.shape, np.nan),
        gust=g._replace(t_moved=g.t_moved + shift, t_still=g.t_still + shift),
    )


# The functions below are written once, for both backends: plain Python on numpy arrays
# and named tuples, which filters.fast also compiles.


def plausible(x: FloatArray, state_max: FloatArray) -> bool:
    """Whether the flight states x[0:4] are where an aircraft can be: an airspeed above
    zero (the equations divide by it) and every state within state_max. A belief beyond
    is treated as diverged (the contract starts it again from the prior) even while it is
    still finite: the next steps would take it to infinity, through absurd estimates."""
    if not x[0] > 0.0:
        return False
    for i in range(state_max.shape[0]):  # noqa: SIM110 (numba compiles no generators)
        if not abs(x[i]) <= state_max[i]:
            return False
    return True


MOTION_INPUTS = 3
"""Inputs from this one on (bank angle, roll and yaw rate) are samples of the lateral
motion, which moves between them: they go linearly from one to the next whatever the
hold of the commands (elevator, throttle, density: [data] input_hold)."""


def input_path(u_prev: FloatArray, u: FloatArray, linear: bool) -> tuple[FloatArray, FloatArray]:
    """The inputs at the start and the end of a prediction interval: from the earlier
    sample to this one (first-order hold), or the earlier sample held (zero-order hold).
    An input missing at either end is held at the sample that has it."""
    start = u_prev.copy()
    for i in range(u.shape[0]):
        if not math.isfinite(start[i]):
            start[i] = u[i]
    end = start.copy()
    for i in range(u.shape[0]):
        if (linear or i >= MOTION_INPUTS) and math.isfinite(u[i]):
            end[i] = u[i]
    return start, end


def process_noise(state: FilterState, tuning: Tuning) -> tuple[FloatArray, float]:
    """Diagonal of Q, and the gust variance in it."""
    q = tuning.q.copy()
    g = state.gust
    gust = gust_applied(g.var, g.info, g.gain, tuning.detection2)
    if gust > 0.0:
        q = q + gust * tuning.gust_unit
    return q, gust


def gust_match(e: FloatArray, s: FloatArray, G: FloatArray) -> tuple[float, float]:
    """Weighted covariance-matching sums of one step (GustState):
    num = sum w (min(e^2, 25 S) - S), den = sum w G, w = G / (2 S^2), over the channels
    whose innovation e and its sigma s are present."""
    num = 0.0
    den = 0.0
    for c in range(e.shape[0]):
        S = s[c] * s[c]
        if not (math.isfinite(e[c]) and S > 0.0):  # also catches NaN sigma
            continue
        w = G[c] / (2.0 * S * S)
        num += w * (min(e[c] * e[c], GUST_CLIP * S) - S)
        den += w * G[c]
    return num, den


def adapt_gust(
    g: GustState,
    tuning: Tuning,
    model: ModelArrays,
    t: float,
    dt: float,
    x: FloatArray,
    u: FloatArray,
    e: FloatArray,
    s: FloatArray,
    applied: float,
) -> GustState:
    """One step of the gust estimate (GustState) from the step's innovations e and their
    sigmas s at the posterior x, at vehicle time t, refreshing the channel sensitivities
    when due. Each step estimates the level as the one its process noise used (applied)
    plus a correction: averaged over the pass (for the next restart) and running.

    While no level is applied, a step informs the estimate only once the inputs are
    still: settle_s after the elevator last moved beyond GUST_STILL_BAND_RAD; or, when
    they have not been still for GUST_MAX_WAIT_S (a flight with the inputs always moving),
    every step.
    A model that misses part of the aircraft's response leaves innovations in its
    manoeuvres and hardly after them; turbulence leaves them everywhere. So the level
    cannot be switched on by the model's own error, and once turbulence is detected every
    step informs it."""
    if not tuning.adaptive or not dt > 0.0:
        return g
    sens = g.sens
    age = g.sens_age
    if age >= GUST_SENSITIVITY_EVERY:
        _, H = eq.observe(x, u, model)
        sens = (H * H) @ tuning.gust_unit
        age = 0
    age += 1
    ref = g.input_ref
    moved = g.t_moved
    if not math.isfinite(ref):
        ref = u[0]
    elif math.isfinite(u[0]) and abs(u[0] - ref) > GUST_STILL_BAND_RAD:
        ref = u[0]
        moved = t
    still = t - moved >= tuning.settle_s
    last_still = t if still or not math.isfinite(g.t_still) else g.t_still
    informs = applied > 0.0 or t - last_still >= GUST_MAX_WAIT_S or still
    num, den = gust_match(e, s, dt * sens)
    if not (informs and den > 0.0):
        return GustState(
            g.var, g.info, g.gain, g.pass_num, g.pass_den, sens, age, ref, moved, last_still
        )
    estimate = applied + num / den
    gain = min(1.0, dt / GUST_ADAPT_TIME_S)
    info = g.info + gain * (den - g.info) if g.info > 0.0 else den
    # Each step moves the running level by its share of the running information: on
    # frames that all carry the same channels this is the gain itself; a frame of a
    # link or log that carries only a channel the gusts hardly move (den small, its
    # one-step estimate num / den wild) moves it little (decision 0079).
    step = min(1.0, gain * den / info)
    var = max(g.var + step * (estimate - g.var), GUST_VAR_FLOOR)
    return GustState(
        var,
        info,
        gain,
        g.pass_num + den * estimate,
        g.pass_den + den,
        sens,
        age,
        ref,
        moved,
        last_still,
    )


def repair_covariance(P: FloatArray, rel_floor: float = 1e-12) -> FloatArray:
    """Nearest symmetric matrix with eigenvalues >= rel_floor * largest eigenvalue.

    Rounding in an update with a very wide prior (a zero start with sigma 100) can leave
    P with a negative variance; the step repairs it and says so rather than stop.
    """
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    w = np.maximum(w, rel_floor * max(float(w.max()), 1e-300))
    out: FloatArray = (V * w) @ V.T
    return 0.5 * (out + out.T)


KernelStep = Callable[
    [FilterState, float, FloatArray, FloatArray, Tuning, Model],
    tuple[FilterState, StepInfo, bool],
]
"""A backend: (state, t, u, y, tuning, model) -> (state', info, healthy), where healthy
says every variance is positive and the belief finite."""

StepFn = Callable[
    [FilterState, float, FloatArray, FloatArray, Tuning, Model], tuple[FilterState, StepInfo]
]


def guarded(kernel: KernelStep) -> StepFn:
    """The step contract around a backend: repair or restart an unhealthy belief."""

    def step(
        state: FilterState, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model
    ) -> tuple[FilterState, StepInfo]:
        new, info, healthy = kernel(state, t, u, y, tuning, model)
        if healthy:
            return new, info
        return recover(new, info, t, u, y, tuning, model)

    return step


def recover(
    state: FilterState,
    info: StepInfo,
    t: float,
    u: FloatArray,
    y: FloatArray,
    tuning: Tuning,
    model: Model,
) -> tuple[FilterState, StepInfo]:
    finite = np.isfinite(state.x).all() and np.isfinite(state.P).all()
    if finite and plausible(state.x, tuning.state_max):
        P = repair_covariance(state.P)
        return state._replace(P=P), info._replace(sigma=np.sqrt(np.diag(P)), repaired=True)
    # Diverged (non-finite, or run away from where an aircraft can be: a long gap while
    # the coefficients are unknown, garbage input that passed every check): start again
    # from the configured prior at this frame rather than stop estimating.
    fresh = initial_state(model, tuning, t, u, y)
    nothing = np.full(N_OBS, np.nan)  # the step's update was thrown away with its belief
    return fresh, info._replace(
        sigma=np.sqrt(np.diag(fresh.P)),
        nis=math.nan,
        n_used=0,
        innovation=nothing,
        innovation_sigma=nothing.copy(),
        diverged=True,
    )


def output_row(x: FloatArray, info: StepInfo) -> FloatArray:
    """A step's outputs as one row (filters.fast.output_width's layout): x, sigma, NIS,
    channels used, gust sigma, its pass average, innovations, their sigmas, iterations,
    failed, repaired, diverged."""
    return np.concatenate(
        (
            x,
            info.sigma,
            (info.nis, info.n_used, info.gust_sigma, info.gust_pass_sigma),
            info.innovation,
            info.innovation_sigma,
            (info.iterations, info.failed, info.repaired, info.diverged),
        ),
        dtype=np.float64,
    )


def info_of_row(row: FloatArray, n: int) -> StepInfo:
    """output_row's StepInfo, its arrays views of the row."""
    o = 2 * n
    k = o + 4 + 2 * N_OBS
    nis, used, gust, gust_pass = row[o : o + 4].tolist()
    iterations, failed, repaired, diverged = row[k : k + 4].tolist()
    return StepInfo(
        row[n:o],
        nis,
        int(used),
        int(iterations),
        row[o + 4 : o + 4 + N_OBS],
        row[o + 4 + N_OBS : k],
        gust,
        gust_pass,
        bool(failed),
        bool(repaired),
        bool(diverged),
    )


def flags_of_row(row: FloatArray, n: int) -> IntArray:
    """output_row's failed, repaired and diverged flags, as 0 or 1 each."""
    k = 2 * n + 5 + 2 * N_OBS
    flags: IntArray = (row[k : k + 3] != 0.0).astype(np.int64)
    return flags
