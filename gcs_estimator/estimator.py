"""Online estimation of one aircraft: EKF and IEKF side by side over synchronised frames.

A frame is (vehicle time [s], inputs [de rad, throttle or thrust N], observations [7],
NaN where a channel is missing). Each filter predicts from the previous frame's time with
the previous inputs held, then updates with the frame's observations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from gcs_estimator.config import AircraftConfig
from gcs_estimator.filters import hybrid
from gcs_estimator.filters.hybrid import Belief
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model, build_model
from gcs_estimator.model.equations import FloatArray

Backend = Literal["fast", "reference"]
FilterKind = Literal["EKF", "IEKF"]

GUST_SENSITIVITY_EVERY = 25
"""Steps between refreshes of the channels' sensitivity to the gust level."""

GUST_VAR_FLOOR = -0.1
"""Lowest running gust variance [m^2/s^2]: in calm air the estimate wanders around zero;
the floor keeps it from drifting so far below that real turbulence takes long to show."""


@dataclass(frozen=True)
class StepOutput:
    """What one filter step reports."""

    x: FloatArray
    sigma: FloatArray
    nis: float
    n_used: int
    iterations: int
    innovation: FloatArray
    """y - h(x-) per channel, NaN where the channel was not used [7]."""
    innovation_sigma: FloatArray
    """sqrt(diag(S)) per channel, NaN where not used [7]."""
    gust_sigma: float = 0.0
    """Vertical gust intensity the step's process noise assumed [m/s]."""


@dataclass
class FilterRunner:
    """One filter (EKF or IEKF) over the frames of one vehicle."""

    kind: FilterKind
    model: Model
    config: AircraftConfig
    backend: Backend = "fast"
    iterations: int = field(init=False)
    belief: Belief | None = field(default=None, init=False)
    t_last: float = field(default=math.nan, init=False)
    u_last: FloatArray = field(default_factory=lambda: np.zeros(2), init=False)
    t_start: float = field(default=math.nan, init=False)
    beta0: FloatArray = field(init=False)
    """Initial coefficient mean; a restart moves it."""
    sigma0: FloatArray = field(init=False)
    """Initial coefficient sigma; a restart may narrow it to a data-derived prior."""
    failed_updates: int = field(default=0, init=False)
    """Updates skipped because an innovation covariance was not positive definite."""
    divergences: int = field(default=0, init=False)
    """Times the belief went non-finite and the filter was restarted from scratch."""
    covariance_repairs: int = field(default=0, init=False)
    """Times P lost positive definiteness to rounding and was repaired (eigenvalue floor)."""

    def __post_init__(self) -> None:
        tuning = self.config.filter
        self.beta0 = np.array(tuning.initial_coefficients, float)
        self.sigma0 = np.array(tuning.initial_coefficient_sigma, float)
        self.iterations = 1 if self.kind == "EKF" else tuning.iterations
        self.R = np.diag(np.square(tuning.measurement_sigma))
        self.q_state = np.array(tuning.state_process_noise)
        self.q_coef_final = np.array(tuning.coefficient_process_noise)
        self.q_coef_initial = np.array(tuning.coefficient_process_noise_initial)
        self._q_settled: FloatArray | None = None
        self._q_coef_constant = bool(np.array_equal(self.q_coef_initial, self.q_coef_final))
        turbulence = tuning.turbulence
        self.q_gust_unit = np.array(turbulence.unit(float(self.model.k[eq.V0])))
        self._gust_num = 0.0
        self._gust_den = 0.0
        self._gust_sens: FloatArray | None = None
        self._gust_sens_age = 0
        self._gust_info = 0.0
        self._gust_gain = 0.0
        self._detect2 = turbulence.detection_sigma**2
        self.gust_var = turbulence.sigma_w_mps**2
        """Estimated vertical gust variance sigma_w^2 [m^2/s^2]. The running estimate may
        dip below zero in calm air (so that it averages to the truth); Q uses
        gust_var_used."""

    @property
    def gust_var_used(self) -> float:
        """Gust variance in the process noise: the running estimate where it stands at
        least detection_sigma of its standard errors above zero, else 0. An exponential
        average with gain g of one-step estimates of variance 1/I (I their Fisher
        information) has variance g / (2 - g) / I. A level not yet measured in this pass
        (the configured one, or the one a restart carries over) is used as it is."""
        level = self.gust_var
        if level <= 0.0:
            return 0.0
        info, g = self._gust_info, self._gust_gain
        if info <= 0.0 or level * level * info * (2.0 - g) >= self._detect2 * g:
            return level
        return 0.0

    @property
    def gust_sigma(self) -> float:
        """Vertical gust intensity the process noise currently assumes [m/s]."""
        return math.sqrt(self.gust_var_used)

    def initial_belief(self, y: FloatArray) -> Belief:
        """States from the first measurement where present, coefficients from the config."""
        tuning = self.config.filter
        state = np.array([self.model.k[eq.V0], 0.0, 0.0, 0.0])
        measured = np.isfinite(y[: eq.N_STATE])
        state[measured] = y[: eq.N_STATE][measured]
        x = np.concatenate([state, self.beta0])
        sigma = np.concatenate([np.array(tuning.initial_state_sigma), self.sigma0])
        return Belief(x, np.diag(sigma**2))

    def process_noise(self, t: float) -> FloatArray:
        """Q at time t: coefficient noise decays from its initial to its final density."""
        decay = math.exp(-(t - self.t_start) / self.config.filter.coefficient_noise_decay_s)
        if self._q_coef_constant or decay < 1e-12:
            # Settled: the same matrix every step, built once.
            if self._q_settled is None:
                self._q_settled = np.diag(np.concatenate([self.q_state, self.q_coef_final]))
            Q = self._q_settled
        else:
            q_coef = self.q_coef_final + (self.q_coef_initial - self.q_coef_final) * decay
            Q = np.diag(np.concatenate([self.q_state, q_coef]))
        gust = self.gust_var_used
        if gust > 0.0:
            Q = Q.copy()
            states = np.arange(eq.N_STATE)
            Q[states, states] += gust * self.q_gust_unit
        return Q

    def gust_var_of_pass(self) -> float:
        """Covariance-matching estimate of the gust variance over every step since the
        last reset, >= 0 (the current level if nothing was measured)."""
        if self._gust_den <= 0.0:
            return max(self.gust_var, 0.0)
        return max(self._gust_num / self._gust_den, 0.0)

    def adapt_turbulence(self, dt: float, u: FloatArray, out: StepOutput) -> None:
        """Move the gust variance towards the level at which the innovations are as
        large as the filter predicts (covariance matching, averaged over adapt_time_s by
        stochastic approximation).

        Each channel c gives a one-sample estimate of the correction,
        (e_c^2 - S_c) / G_c, where G_c = dt * sum_j H_cj^2 unit_j is the change of S_c
        per unit gust variance over one step. Channels are weighted by G_c^2 / (2 S_c^2),
        their Fisher information. The pitch acceleration carries the most: it moves 165
        rad/s^2 per radian of alpha on the NOC UAV, so alpha noise far below the vane's
        resolution already shows there. Innovations beyond 5 sigma count as 5 sigma, so
        that a glitch or the zero-start transient does not set the level.
        """
        turbulence = self.config.filter.turbulence
        if not turbulence.adaptive or not dt > 0.0 or self.belief is None:
            return
        from gcs_estimator.filters import fast

        # The channel sensitivities change with the flight state slowly; refreshed every
        # GUST_SENSITIVITY_EVERY steps (they only weigh the channels).
        if self._gust_sens is None or self._gust_sens_age >= GUST_SENSITIVITY_EVERY:
            _, H = fast.model_h(self.model, self.belief.x, u)
            self._gust_sens = H[:, : eq.N_STATE] ** 2 @ self.q_gust_unit
            self._gust_sens_age = 0
        self._gust_sens_age += 1
        num, den = fast.gust_match(out.innovation, out.innovation_sigma, dt * self._gust_sens)
        if den > 0.0:
            # Each step estimates the level as the level its process noise used plus its
            # correction: averaged over the pass (for the next restart) and running.
            estimate = self.gust_var_used + num / den
            self._gust_num += den * estimate
            self._gust_den += den
            gain = min(1.0, dt / turbulence.adapt_time_s)
            self._gust_gain = gain
            if self._gust_info > 0.0:
                self._gust_info += gain * (den - self._gust_info)
            else:
                self._gust_info = den
            self.gust_var = max(self.gust_var + gain * (estimate - self.gust_var), GUST_VAR_FLOOR)

    def reset(self, beta0: FloatArray | None = None, sigma0: FloatArray | None = None) -> None:
        """Forget the belief; start again from N(beta0, sigma0^2) (default: configured)."""
        tuning = self.config.filter
        self.beta0 = np.array(tuning.initial_coefficients if beta0 is None else beta0, float)
        self.sigma0 = np.array(
            tuning.initial_coefficient_sigma if sigma0 is None else sigma0, float
        )
        self.belief = None
        self.t_last = math.nan
        self.t_start = math.nan
        self.gust_var = tuning.turbulence.sigma_w_mps**2
        self._gust_num = 0.0
        self._gust_den = 0.0
        self._gust_sens = None
        self._gust_info = 0.0

    def rebase(self, t: float, y: FloatArray) -> None:
        """New time base (the vehicle clock reset): keep what is known of the coefficients,
        take the states afresh from the measurements with their initial uncertainty."""
        if self.belief is None:
            return
        fresh = self.initial_belief(y)
        x = self.belief.x.copy()
        P = self.belief.P.copy()
        n4 = eq.N_STATE
        x[:n4] = fresh.x[:n4]
        P[:n4, :] = 0.0
        P[:, :n4] = 0.0
        P[:n4, :n4] = fresh.P[:n4, :n4]
        self.belief = Belief(x, P)
        self.t_last = t
        self.u_last = np.full(2, np.nan)

    def step(self, t: float, u: FloatArray, y: FloatArray) -> StepOutput:
        """Predict to time t [s] and update with observations y (NaN = missing)."""
        tuning = self.config.filter
        if self.belief is None:
            self.belief = self.initial_belief(y)
            self.t_last = t
            self.t_start = t
            self.u_last = np.array(u, float)
        if not np.all(np.isfinite(self.u_last)):
            self.u_last = np.array(u, float)
        dt = t - self.t_last
        Q = self.process_noise(self.t_last)
        if self.backend == "fast":
            from gcs_estimator.filters import fast

            x, P, e, s_diag, nis, n_used, iters = fast.step(
                self.belief.x,
                self.belief.P,
                self.u_last,
                dt,
                np.asarray(u, float),
                np.asarray(y, float),
                Q,
                self.R,
                self.iterations,
                tuning.iteration_tolerance,
                tuning.relinearise_sigma,
                tuning.max_step_s,
                tuning.innovation_gate,
                self.model,
            )
            if n_used < 0:
                self.failed_updates += 1
                n_used = 0
            self.belief = Belief(x, P)
        else:
            u_prev = self.u_last
            model = self.model
            prior = hybrid.propagate(
                lambda x: model.f(x, u_prev), self.belief, Q, dt, tuning.max_step_s
            )
            u_now = np.asarray(u, float)
            e = np.full(eq.N_OBS, np.nan)
            s_diag = np.full(eq.N_OBS, np.nan)
            try:
                post, info = hybrid.iekf_update(
                    lambda x: model.h(x, u_now),
                    prior,
                    np.asarray(y, float),
                    self.R,
                    iterations=self.iterations,
                    tolerance=tuning.iteration_tolerance,
                    gate=tuning.innovation_gate,
                    relinearise=tuning.relinearise_sigma,
                )
            except np.linalg.LinAlgError:
                self.failed_updates += 1
                self.belief = prior
                nis, n_used, iters = math.nan, 0, 0
            else:
                self.belief = post
                e[info.used] = info.innovation
                s_diag[info.used] = np.sqrt(np.diag(info.S))
                nis, n_used, iters = info.nis, int(info.used.sum()), info.iterations
        variances = np.diag(self.belief.P)
        healthy = variances.min() > 0.0 and math.isfinite(
            float(self.belief.x.sum()) + float(self.belief.P.sum())
        )  # one cheap test on the hot path; NaN fails every comparison
        if not healthy and variances.min() <= 0.0 and np.isfinite(self.belief.P).all():
            self.covariance_repairs += 1
            self.belief = Belief(self.belief.x, repair_covariance(self.belief.P))
        if not healthy and not (
            np.isfinite(self.belief.x).all() and np.isfinite(self.belief.P).all()
        ):
            # Diverged (e.g. garbage input that passed every check): start again from the
            # configured prior at this frame rather than stop estimating.
            self.divergences += 1
            self.reset()
            self.belief = self.initial_belief(np.asarray(y, float))
            self.t_start = t
        self.t_last = t
        self.u_last = np.array(u, float)
        out = StepOutput(
            x=self.belief.x,  # a fresh array every step: the filter never mutates it
            sigma=np.sqrt(variances if healthy else np.diag(self.belief.P)),
            nis=float(nis),
            n_used=int(n_used),
            iterations=int(iters),
            innovation=e,
            innovation_sigma=s_diag,
            gust_sigma=self.gust_sigma,
        )
        self.adapt_turbulence(dt, np.asarray(u, float), out)
        return out


def repair_covariance(P: FloatArray, rel_floor: float = 1e-12) -> FloatArray:
    """Nearest symmetric matrix with eigenvalues >= rel_floor * largest eigenvalue.

    Rounding in an update with a very wide prior (a zero start with sigma 100) can leave
    P with a negative variance; the estimator repairs it and counts it rather than stop.
    """
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    w = np.maximum(w, rel_floor * max(float(w.max()), 1e-300))
    out: FloatArray = (V * w) @ V.T
    return 0.5 * (out + out.T)


@dataclass
class History:
    """Time histories of one filter: arrays grow by blocks, read with .arrays()."""

    n: int
    t: list[float] = field(default_factory=list)
    x: list[FloatArray] = field(default_factory=list)
    sigma: list[FloatArray] = field(default_factory=list)
    nis: list[float] = field(default_factory=list)
    n_used: list[int] = field(default_factory=list)
    innovation: list[FloatArray] = field(default_factory=list)
    innovation_sigma: list[FloatArray] = field(default_factory=list)
    gust_sigma: list[float] = field(default_factory=list)
    u: list[FloatArray] = field(default_factory=list)
    """The frame's inputs [2]."""
    y: list[FloatArray] = field(default_factory=list)
    """The frame's observations [7], NaN where missing."""

    def append(self, t: float, out: StepOutput, u: FloatArray, y: FloatArray) -> None:
        self.t.append(t)
        self.u.append(u)
        self.y.append(y)
        self.x.append(out.x)
        self.sigma.append(out.sigma)
        self.nis.append(out.nis)
        self.n_used.append(out.n_used)
        self.innovation.append(out.innovation)
        self.innovation_sigma.append(out.innovation_sigma)
        self.gust_sigma.append(out.gust_sigma)

    def replace_last(self, out: StepOutput) -> None:
        """The frame's output changed (a restart re-ran up to it): same frame, new output."""
        t, u, y = self.t[-1], self.u[-1], self.y[-1]
        for seq in (
            self.t,
            self.u,
            self.y,
            self.x,
            self.sigma,
            self.nis,
            self.n_used,
            self.innovation,
            self.innovation_sigma,
            self.gust_sigma,
        ):
            seq.pop()
        self.append(t, out, u, y)

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class Track:
    """Frozen arrays of one filter's run: t [N], x [N x n], sigma [N x n], nis [N], ..."""

    t: FloatArray
    x: FloatArray
    sigma: FloatArray
    nis: FloatArray
    n_used: FloatArray
    innovation: FloatArray
    innovation_sigma: FloatArray
    gust_sigma: FloatArray
    """Gust intensity the process noise assumed per frame [N], m/s."""
    u: FloatArray
    """Inputs per frame [N x 2]."""
    y: FloatArray
    """Observations per frame [N x 7], NaN where missing."""

    @staticmethod
    def of(h: History) -> Track:
        n = h.n
        return Track(
            t=np.array(h.t, float),
            x=np.array(h.x, float).reshape(-1, n),
            sigma=np.array(h.sigma, float).reshape(-1, n),
            nis=np.array(h.nis, float),
            n_used=np.array(h.n_used, float),
            innovation=np.array(h.innovation, float).reshape(-1, eq.N_OBS),
            innovation_sigma=np.array(h.innovation_sigma, float).reshape(-1, eq.N_OBS),
            gust_sigma=np.array(h.gust_sigma, float),
            u=np.array(h.u, float).reshape(-1, 2),
            y=np.array(h.y, float).reshape(-1, eq.N_OBS),
        )


@dataclass
class Estimator:
    """EKF and IEKF side by side for one vehicle; the place that owns the filter loop."""

    config: AircraftConfig
    backend: Backend = "fast"
    keep_history: bool = True
    model: Model = field(init=False)
    filters: dict[FilterKind, FilterRunner] = field(init=False)
    histories: dict[FilterKind, History] = field(init=False)
    frames: int = field(default=0, init=False)
    restarts_done: int = field(default=0, init=False)
    warm_start: FloatArray | None = field(default=None, init=False)
    """Equation-error coefficients of the first restart, when that is the warm start."""
    _buffer: list[tuple[float, FloatArray, FloatArray]] = field(default_factory=list, init=False)
    _t0: float = field(default=math.nan, init=False)

    def __post_init__(self) -> None:
        self.model = build_model(self.config)
        self.filters = {
            kind: FilterRunner(kind, self.model, self.config, self.backend)
            for kind in ("EKF", "IEKF")
        }
        self.histories = {kind: History(self.model.n) for kind in self.filters}

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    @property
    def restarts_pending(self) -> bool:
        return self.restarts_done < len(self.config.filter.restart_times_s)

    def step(self, t: float, u: FloatArray, y: FloatArray) -> dict[FilterKind, StepOutput]:
        """Advance both filters to vehicle time t [s] with inputs u and observations y.

        At each configured restart time both filters re-run the buffered frames from the
        start; the outputs returned are then those of the re-run's last frame.
        """
        if self.frames == 0:
            self._t0 = t
        u = np.array(u, float)
        y = np.array(y, float)
        if self.restarts_pending:
            self._buffer.append((t, u, y))
        outs = self._advance(t, u, y)
        self.frames += 1
        if (
            self.restarts_pending
            and t - self._t0 >= self.config.filter.restart_times_s[self.restarts_done]
        ):
            outs = self._restart()
        return outs

    def rebase(self, t: float, y: FloatArray) -> None:
        """The vehicle clock restarted: continue the coefficient estimates on a new time
        base. Restarts still pending are dropped (their frames span two time bases)."""
        for runner in self.filters.values():
            runner.rebase(t, y)
        if self.restarts_pending:
            self.restarts_done = len(self.config.filter.restart_times_s)
            self._buffer = []

    def _advance(self, t: float, u: FloatArray, y: FloatArray) -> dict[FilterKind, StepOutput]:
        outs: dict[FilterKind, StepOutput] = {}
        for kind, runner in self.filters.items():
            out = runner.step(t, u, y)
            outs[kind] = out
            if self.keep_history:
                self.histories[kind].append(t, out, u, y)
        return outs

    def _restart(self) -> dict[FilterKind, StepOutput]:
        """Re-run the buffered frames from a new linearisation point (see FilterTuning)."""
        tuning = self.config.filter
        if self.restarts_done == 0 and tuning.warm_start == "equation-error":
            from gcs_estimator.warmstart import equation_error

            t_b = np.array([f[0] for f in self._buffer])
            u_b = np.array([f[1] for f in self._buffer])
            y_b = np.array([f[2] for f in self._buffer])
            ws = equation_error(
                self.model,
                t_b,
                u_b,
                y_b,
                np.array(tuning.initial_coefficients),
                np.array(tuning.initial_coefficient_sigma),
            )
            self.warm_start = ws.beta
            starts = {kind: (ws.beta, ws.sigma) for kind in self.filters}
        else:
            starts = {
                kind: (
                    runner.belief.x[eq.N_STATE :].copy(),
                    np.sqrt(np.diag(runner.belief.P))[eq.N_STATE :],
                )
                for kind, runner in self.filters.items()
                if runner.belief is not None
            }
        p0 = np.array(tuning.initial_coefficient_sigma)
        for kind, runner in self.filters.items():
            # The first re-run starts at the turbulence level the zero-start pass ended
            # with (its running estimate). That pass tends to overstate it, which makes
            # the first re-run cautious. Its average over the whole pass can instead
            # come out near calm (its early innovations are smaller than the unknown
            # coefficients make it predict), and a re-run that takes its first steps as
            # calm air in turbulence can lock onto wrong coefficients (light turbulence,
            # seed 24: CLa -194 %). Later re-runs start at the average of the pass
            # before, which started near the solution: its running estimate would still
            # carry some of that cautious start into the final pass in calm air.
            gust_var = None
            if tuning.turbulence.adaptive:
                gust_var = (
                    max(runner.gust_var, 0.0)
                    if self.restarts_done == 0
                    else runner.gust_var_of_pass()
                )
            if kind in starts:
                beta, sigma = starts[kind]
                # A data-derived prior, widened so that reusing the early data in it
                # weighs little next to the data themselves; never wider than P0.
                runner.reset(beta, np.minimum(p0, tuning.restart_sigma_inflation * sigma))
            else:
                runner.reset()
            if gust_var is not None:
                runner.gust_var = gust_var
        # The history keeps what was known live at each time: the re-run replaces only
        # the output of the current frame.
        outs: dict[FilterKind, StepOutput] = {}
        for t, u, y in self._buffer:
            outs = {kind: runner.step(t, u, y) for kind, runner in self.filters.items()}
        if self.keep_history:
            for kind, out in outs.items():
                self.histories[kind].replace_last(out)
        self.restarts_done += 1
        if not self.restarts_pending:
            self._buffer = []
        return outs

    def run(self, t_s: FloatArray, inputs: FloatArray, measurements: FloatArray) -> None:
        """Process a whole recording: frames in time order."""
        for i in range(len(t_s)):
            self.step(float(t_s[i]), inputs[i], measurements[i])

    def tracks(self) -> dict[FilterKind, Track]:
        return {kind: Track.of(h) for kind, h in self.histories.items()}

    def current(self) -> dict[FilterKind, tuple[FloatArray, FloatArray]]:
        """Current coefficient estimates and sigmas per filter (empty before data)."""
        out: dict[FilterKind, tuple[FloatArray, FloatArray]] = {}
        for kind, runner in self.filters.items():
            if runner.belief is not None:
                b = runner.belief
                out[kind] = (
                    b.x[eq.N_STATE :].copy(),
                    np.sqrt(np.diag(b.P))[eq.N_STATE :],
                )
        return out
