"""Data compatibility check: flight path reconstruction before estimation (decision 0056).

The kinematic equations, integrated from the measured body rates and specific forces,
must reproduce the measured attitudes, airspeed, angle of attack, climb rate and (where
the record has it) GPS velocity. What they cannot reproduce without a constant bias, a
scale factor or a time shift of a channel is a fault of that channel (Jategaonkar, Flight
Vehicle System Identification, ch. 10; Morelli and Klein, Aircraft System Identification,
ch. 10). Two stages, each a Gauss-Newton fit:

    attitude  theta' = q cos(phi) - r sin(phi)        (theta' = q without roll)
              phi'   = p + (q sin(phi) + r cos(phi)) tan(theta)
              q_m = (1 + k_q) q + b_q,  p_m = (1 + k_p) p + b_p,  r_m = r + b_r
              theta_m(t) = theta(t - tau_theta),  phi_m(t) = phi(t - tau_phi)
    velocity  V_air' = R(phi, theta, psi) [a_x - b_ax, 0, a_z - b_az] + [0, 0, g]
              (NED, steady wind, no side force: the record has no a_y)
              V_m(t)     = (1 + k_V) |V_air(t - tau_V)|
              alpha_m(t) = (1 + k_alpha) alpha(t - tau_alpha) + b_alpha   (vane offset kept)
              vz_m(t)    = V_air,D(t - tau_vz)      GPS: V_air(t - tau_gps) + wind

The record is cut into SEGMENT_S pieces, each with its own initial attitude and velocity
(and, with GPS, its own horizontal wind): an integration over an hour drifts with the
sensors' noise, and the wind changes. Each finding's sigma is the fit's covariance with the
residuals' own level and their correlation in time (a residual correlated over k samples
carries about 1/k of the information white noise would): a finding beyond SIGNIFICANT
sigma is more than the sensors' noise explains, a warning, and the one corrected.

check(recording, sensors) is pure: the findings and the corrected recording. The
reconstructed angle of attack and wind go into Recording.aux ("alpha_fpr", "wind_n_fpr",
"wind_e_fpr") where the record has GPS velocity and a heading.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.config import AircraftConfig, SensorPlacement
from gcs_estimator.differences import channel_differences, mad_sigma
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.model.channels import Channel

G = 9.80665
SEGMENT_S = 20.0
"""Length of the pieces with their own initial conditions [s]."""
EDGE_S = 0.5
"""Samples this close after a piece's start are left out (a shifted model crosses it)."""
SIGNIFICANT = 3.0
"""A finding this many sigma from zero is beyond the noise: a warning, and corrected."""
ITERATIONS = 8
CONVERGED = 1e-6
"""A full step that lowers the cost by less than this share of it ends the iterations."""
LOCAL_FIRST = 2
"""Gauss-Newton iterations that move each piece's own parameters only: from a start far
from them, the first full step took the scale factors to -76 % and -114 % on a long
quiet record, and never came back."""
MIN_SAMPLES = 50
MAX_LAG = 500
"""Residual correlation is summed over at most this many lags."""
MODES = ("correct", "report", "off")
EXCITED = 3.0
"""A piece enters a stage where its output moves by this many times its model's noise."""
PINNED = 1e-12
"""The prior sigma of a parameter held at zero."""

V, ALPHA, THETA, Q, QDOT, AX, AZ = range(7)

UNITS = {"bias": "", "scale": "", "shift": "s"}
BIAS_UNITS = {
    "q": "rad/s",
    "p": "rad/s",
    "r": "rad/s",
    "a_x": "m/s^2",
    "a_z": "m/s^2",
    "alpha": "rad",
}
NEGLIGIBLE = {
    ("", "scale"): 0.005,
    ("", "shift"): 0.005,
    ("q", "bias"): 2e-4,
    ("p", "bias"): 2e-4,
    ("r", "bias"): 2e-4,
    ("a_x", "bias"): 0.01,
    ("a_z", "bias"): 0.01,
    ("alpha", "bias"): 1e-3,
}
"""Sizes below which a finding changes nothing an estimate would show (0.5 %, 5 ms,
0.01 deg/s, 0.01 m/s^2, 0.06 deg): never a warning, never corrected."""


@dataclass(frozen=True)
class Finding:
    """One channel's bias, scale factor (a fraction: 0.01 reads 1 % high) or time shift
    (the channel lags the rates and accelerations by this much) with its sigma."""

    channel: str
    kind: str
    value: float
    sigma: float
    unit: str

    @property
    def z(self) -> float:
        return self.value / self.sigma if self.sigma > 0 else math.inf

    @property
    def significant(self) -> bool:
        """Beyond SIGNIFICANT sigma and beyond what no estimate would notice (NEGLIGIBLE:
        a noise-free simulated record resolves the integration's own error, a 2 ms shift
        at 200 sigma)."""
        floor = NEGLIGIBLE.get((self.channel, self.kind), NEGLIGIBLE.get(("", self.kind), 0.0))
        return abs(self.z) > SIGNIFICANT and abs(self.value) > floor

    def line(self) -> str:
        word = "WARNING" if self.significant else "ok"
        unit = f" {self.unit}" if self.unit else ""
        return (
            f"{word}: {self.channel} {self.kind} {self.value:+.4g} +- {self.sigma:.2g}{unit} "
            f"({self.z:+.1f} sigma)"
        )


@dataclass(frozen=True)
class Compatibility:
    """What the check found and the recording with the significant findings removed."""

    findings: tuple[Finding, ...]
    recording: Recording
    corrected: bool
    residual_rms: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        """The text report: one line a finding, warnings first."""
        did = "corrected" if self.corrected else "reported only"
        order = sorted(self.findings, key=lambda f: (not f.significant, f.channel))
        warn = sum(f.significant for f in self.findings)
        out = [
            f"data compatibility (flight path reconstruction): {len(self.findings)} "
            f"finding(s), {warn} beyond {SIGNIFICANT:g} sigma and the noise"
            + (f" ({did})" if warn else "")
        ]
        out += [f"data compatibility: {f.line()}" for f in order]
        out += [f"data compatibility: {n}" for n in self.notes]
        return out

    def as_dict(self) -> dict[str, Any]:
        return {
            "corrected": self.corrected,
            "significant_sigma": SIGNIFICANT,
            "findings": [
                {
                    "channel": f.channel,
                    "kind": f.kind,
                    "value": f.value,
                    "sigma": f.sigma,
                    "unit": f.unit,
                    "z": f.z,
                    "significant": f.significant,
                }
                for f in self.findings
            ],
            "residual_rms": self.residual_rms,
            "notes": list(self.notes),
        }


# ------------------------------------------------------------------ the fit machinery


@dataclass
class _Output:
    """One measured channel and its model at the record's times: value [N], its
    derivatives by each piece's own parameters [N x L] and by the global ones [N x G],
    and which global parameter is its time shift (None: not shifted)."""

    name: str
    measured: FloatArray
    value: FloatArray
    d_local: FloatArray
    d_global: FloatArray
    shift: int | None


class Model(Protocol):
    """A stage's outputs at the global and local parameters; derivatives=False: their
    values only (the derivative arrays left unset), for the line search and replicas."""

    def __call__(
        self, g: FloatArray, loc: FloatArray, derivatives: bool = True
    ) -> list[_Output]: ...


Replicas = Callable[[np.random.Generator], Model]
"""The model with its integrated inputs' noise drawn anew."""
REPLICAS = 20
"""Draws of the inputs' noise for its share of each finding's sigma."""


@dataclass
class _Fit:
    globals_: FloatArray
    locals_: FloatArray
    cov: FloatArray
    rms: dict[str, float]
    outputs: list[_Output]


def _shifted(t: FloatArray, x: FloatArray, tau: float) -> FloatArray:
    """x(t - tau), columns alike (held beyond the ends)."""
    if tau == 0.0:
        return x
    if x.ndim == 1:
        return np.interp(t - tau, t, x)
    return np.column_stack([np.interp(t - tau, t, c) for c in x.T])


def _residual(
    out: _Output, t: FloatArray, g: FloatArray, keep: np.ndarray
) -> tuple[FloatArray, np.ndarray]:
    """Residual of one output at its shift (0 where unusable), and where it is usable."""
    tau = 0.0 if out.shift is None else float(g[out.shift])
    value = _shifted(t, out.value, tau)
    use = keep & np.isfinite(out.measured) & np.isfinite(value)
    return np.where(use, out.measured - value, 0.0), use


def _rows(
    out: _Output, t: FloatArray, g: FloatArray, keep: np.ndarray
) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Residual, local and global derivatives of one output at its shift; usable rows."""
    tau = 0.0 if out.shift is None else float(g[out.shift])
    dl = _shifted(t, out.d_local, tau)
    dg = _shifted(t, out.d_global, tau)
    if out.shift is not None:
        dg = dg.copy()
        dg[:, out.shift] = -_shifted(t, np.gradient(out.value, t), tau)
    r, use = _residual(out, t, g, keep)
    return r, dl, dg, use


def _normal(
    segs: IntArray, n_seg: int, rows: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Each piece's block of the weighted normal equations: A_ll, A_lg, b_l."""
    n_l = rows[0][1].shape[1]
    n_g = rows[0][2].shape[1]
    all_ = np.zeros((n_seg, n_l, n_l))
    alg = np.zeros((n_seg, n_l, n_g))
    bl = np.zeros((n_seg, n_l))
    for r, dl, dg, w in rows:
        wdl = dl * w[:, None]
        for i in range(n_l):
            for j in range(n_l):
                all_[:, i, j] += np.bincount(segs, wdl[:, i] * dl[:, j], n_seg)
            for j in range(n_g):
                alg[:, i, j] += np.bincount(segs, wdl[:, i] * dg[:, j], n_seg)
            bl[:, i] += np.bincount(segs, wdl[:, i] * r, n_seg)
    return all_, alg, bl


def _solve(
    all_: FloatArray,
    alg: FloatArray,
    bl: FloatArray,
    rows: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]],
    segs: IntArray,
    prior: tuple[FloatArray, FloatArray, np.ndarray],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Steps of the global and the local parameters, and the globals' covariance. Each
    piece's own parameters are projected out of the rows before the globals' normal
    equations are formed (A_gg - A_lg' A_ll^-1 A_lg formed as a difference lost every
    digit on a long quiet record, where a scale factor is all but a piece's level)."""
    pg, g, pinned = prior
    proj = np.linalg.solve(all_, alg)
    base = np.linalg.solve(all_, bl[:, :, None])[:, :, 0]
    n = len(g)
    s = np.diag(np.where(pinned, 1.0, pg))
    rhs = -np.where(pinned, 0.0, pg * g)
    for r, dl, dg, w in rows:
        red = dg - np.einsum("nl,nlg->ng", dl, proj[segs])
        red[:, pinned] = 0.0
        rr = r - np.einsum("nl,nl->n", dl, base[segs])
        s += red.T @ (red * w[:, None])
        rhs += red.T @ (w * rr)
    cov = np.linalg.inv(s)
    step = cov @ rhs
    local = base - np.einsum("slg,g->sl", proj, step)
    return step, local, cov[:n, :n]


def _reduced(
    all_: FloatArray, alg: FloatArray, segs: IntArray, dl: FloatArray, dg: FloatArray
) -> FloatArray:
    """Derivatives by the globals with each piece's own parameters projected out."""
    proj = np.linalg.solve(all_, alg)  # A_ll^-1 A_lg per piece
    out: FloatArray = dg - np.einsum("nl,nlg->ng", dl, proj[segs])
    return out


def _input_noise(
    cov: FloatArray,
    reduced: list[FloatArray],
    rows: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]],
    replicas: list[list[FloatArray]],
) -> FloatArray:
    """The globals' covariance from the noise of the integrated inputs: the model's
    outputs with the inputs' noise drawn anew (replicas: each output's change), through
    the fit's gain S^-1 J~' W."""
    m = np.zeros_like(cov)
    for changes in replicas:
        u = sum(
            (
                red.T @ (w * d)
                for red, (_r, _dl, _dg, w), d in zip(reduced, rows, changes, strict=True)
            ),
            np.zeros(cov.shape[0]),
        )
        m += np.outer(u, u)
    return cov @ (m / max(len(replicas), 1)) @ cov


def _replicated(
    replicas: Replicas,
    cov: FloatArray,
    blocks: tuple[FloatArray, FloatArray],
    rows: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]],
    names: list[str],
    where: tuple[FloatArray, IntArray, np.ndarray, FloatArray, FloatArray],
) -> FloatArray:
    """The inputs' noise's share of the globals' covariance (_input_noise), from REPLICAS
    draws (seeded: the check is a pure function of the record)."""
    t, segs, keep, g, loc = where
    reduced = [_reduced(blocks[0], blocks[1], segs, dl, dg) for _r, dl, dg, _w in rows]
    rng = np.random.default_rng(0)
    changes = []
    for _ in range(REPLICAS):
        outs = {o.name: o for o in replicas(rng)(g, loc, False)}
        changes.append([rows[i][0] - _rows(outs[n], t, g, keep)[0] for i, n in enumerate(names)])
    return _input_noise(cov, reduced, rows, changes)


def _cost(
    model: Model,
    where: tuple[FloatArray, np.ndarray],
    x: tuple[FloatArray, FloatArray],
    weights: tuple[dict[str, float], FloatArray, FloatArray],
) -> float:
    """The weighted squared residuals and the priors' terms at the parameters x."""
    sigma, pg, pl = weights
    total = float(np.sum(np.where(pg > 1e20, 0.0, pg * x[0] ** 2)) + np.sum(pl * x[1] ** 2))
    for out in model(x[0], x[1], False):
        r, use = _residual(out, where[0], x[0], where[1])
        if use.sum() >= MIN_SAMPLES:
            total += float(np.sum(r * r)) / sigma[out.name] ** 2
    return total


def _line_search(
    model: Model,
    where: tuple[FloatArray, np.ndarray],
    x: tuple[FloatArray, FloatArray],
    step: tuple[FloatArray, FloatArray],
    weights: tuple[dict[str, float], FloatArray, FloatArray],
) -> tuple[tuple[FloatArray, FloatArray], bool]:
    """The Gauss-Newton step, halved until it lowers the cost (a long, quiet record
    starts far enough from its fit for the full step to overshoot); and whether the fit
    has converged (the full step lowered the cost by less than CONVERGED of it)."""
    now = _cost(model, where, x, weights)
    scale = 1.0
    for _ in range(12):
        trial = (x[0] + scale * step[0], x[1] + scale * step[1])
        cost = _cost(model, where, trial, weights)
        if cost <= now:
            return trial, scale == 1.0 and now - cost < CONVERGED * max(now, 1e-300)
        scale *= 0.5
    return x, True


def _fit(
    model: Model,
    t: FloatArray,
    segs: IntArray,
    masks: tuple[np.ndarray, np.ndarray],
    prior: tuple[FloatArray, FloatArray],
    start: tuple[FloatArray, FloatArray],
    sigma0: dict[str, float],
    replicas: Replicas | None = None,
) -> _Fit:
    """Gauss-Newton over the global and each piece's parameters, each output weighted by
    its residual level (first its nominal noise sigma0), weak zero-mean priors (prior
    sigmas of the globals and locals) keeping what the data cannot decide at zero.
    masks: which samples are used at all, and which of them inform the globals."""
    keep, informs = masks
    g, loc = start[0].copy(), start[1].copy()
    n_seg = int(segs.max()) + 1
    pg, pl = 1.0 / prior[0] ** 2, 1.0 / prior[1] ** 2
    pinned = prior[0] == PINNED
    sigma = dict(sigma0)
    cov = np.zeros((len(g), len(g)))
    outs: list[_Output] = []
    done = False
    for it in range(ITERATIONS + 1):
        outs = model(g, loc)
        rows, names = [], []
        for out in outs:
            r, dl, dg, use = _rows(out, t, g, keep)
            if use.sum() < MIN_SAMPLES:
                continue
            if it:
                sigma[out.name] = max(float(np.sqrt(np.mean(r[use] ** 2))), 1e-9)
            w = np.where(use, 1.0 / sigma[out.name] ** 2, 0.0)
            rows.append((r, dl, np.where(informs[:, None], dg, 0.0), w))
            names.append(out.name)
        if not rows:
            break
        all_, alg, bl = _normal(segs, n_seg, rows)
        all_ += np.eye(len(pl)) * pl
        bl -= loc * pl
        held = pinned | (it < LOCAL_FIRST)
        dg, dl, cov = _solve(all_, alg, bl, rows, segs, (pg, g, held))
        if it == ITERATIONS or done:
            if replicas is not None:
                where = (t, segs, keep, g, loc)
                cov = cov + _replicated(replicas, cov, (all_, alg), rows, names, where)
            break
        (g, loc), done = _line_search(model, (t, keep), (g, loc), (dg, dl), (sigma, pg, pl))
        done = done and it >= LOCAL_FIRST
    return _Fit(g, loc, cov, {k: sigma[k] for k in sigma if k in {o.name for o in outs}}, outs)


# ---------------------------------------------------------------------- helpers


def _cumint(t: FloatArray, x: FloatArray, segs: IntArray) -> FloatArray:
    """The integral of x (trapezoid) from each piece's start [N] or [N x k]."""
    dt = np.diff(t)
    mid = 0.5 * (x[1:] + x[:-1])
    step = mid * (dt if x.ndim == 1 else dt[:, None])
    step = np.where(
        (segs[1:] != segs[:-1]) if x.ndim == 1 else (segs[1:] != segs[:-1])[:, None], 0.0, step
    )
    c = np.concatenate([np.zeros((1, *x.shape[1:])), np.cumsum(step, axis=0)])
    first = np.concatenate([[0], np.nonzero(segs[1:] != segs[:-1])[0] + 1])
    out: FloatArray = c - c[first][segs]
    return out


def _filled(t: FloatArray, x: FloatArray | None) -> FloatArray | None:
    """x with its missing samples interpolated (None where it has too few)."""
    if x is None:
        return None
    ok = np.isfinite(x)
    if ok.sum() < MIN_SAMPLES:
        return None
    return x if ok.all() else np.interp(t, t[ok], x[ok])


def segments(t: FloatArray, length_s: float = SEGMENT_S) -> IntArray:
    """Each sample's piece: SEGMENT_S long, a new one after any gap of over a second; a
    last piece shorter than half the length joins the one before."""
    gap = np.concatenate([[False], np.diff(t) > 1.0])
    block = np.cumsum(gap)
    out = np.zeros(len(t), dtype=np.int64)
    n = 0
    for b in range(int(block[-1]) + 1):
        idx = np.nonzero(block == b)[0]
        span = t[idx[-1]] - t[idx[0]]
        pieces = max(1, int(round(span / length_s)))
        k = np.minimum(
            ((t[idx] - t[idx[0]]) / max(span, 1e-9) * pieces).astype(np.int64), pieces - 1
        )
        out[idx] = n + k
        n += pieces
    return out


def _keep(t: FloatArray, segs: IntArray) -> np.ndarray:
    first = np.concatenate([[0], np.nonzero(segs[1:] != segs[:-1])[0] + 1])
    start = t[first][segs]
    out: np.ndarray = t - start >= EDGE_S
    return out


class _Params:
    """Names of the global parameters of a stage: (channel, kind) each, with a prior
    sigma; their indices by name."""

    def __init__(self) -> None:
        self.names: list[tuple[str, str]] = []
        self.prior: list[float] = []

    def add(self, channel: str, kind: str, prior: float) -> int:
        self.names.append((channel, kind))
        self.prior.append(prior)
        return len(self.names) - 1

    def pin_scales(self) -> None:
        """Scale factors held at zero: the record's motion too small to tell them."""
        self.prior = [
            PINNED if kind == "scale" else p
            for (_c, kind), p in zip(self.names, self.prior, strict=True)
        ]

    def findings(self, fit: _Fit) -> list[Finding]:
        sig = np.sqrt(np.maximum(np.diag(fit.cov), 0.0))
        return [
            Finding(
                ch,
                kind,
                float(fit.globals_[i]),
                float(sig[i]),
                BIAS_UNITS.get(ch, "") if kind == "bias" else UNITS[kind],
            )
            for i, (ch, kind) in enumerate(self.names)
            if self.prior[i] != PINNED
        ]


@dataclass
class _Signals:
    """The record's channels the reconstruction uses, gaps filled (None: not there)."""

    t: FloatArray
    segs: IntArray
    keep: np.ndarray
    q: FloatArray
    p: FloatArray | None
    r: FloatArray | None
    phi: FloatArray | None
    psi: FloatArray | None
    measured: dict[str, FloatArray]
    """The outputs as measured, NaN where missing: theta, phi, airspeed, alpha, vz, vn..."""
    noise: dict[str, float] = field(default_factory=dict)
    """The integrated inputs' white noise (1 sigma) on the grid t (noise_sigma)."""

    def noisy(self, rng: np.random.Generator) -> _Signals:
        """The rates with their noise drawn anew (added: the change is what counts)."""

        def draw(x: FloatArray | None, name: str) -> FloatArray | None:
            return (
                None if x is None else x + self.noise.get(name, 0.0) * rng.standard_normal(len(x))
            )

        q = draw(self.q, "q")
        assert q is not None
        return replace(self, q=q, p=draw(self.p, "p"), r=draw(self.r, "r"))


def own_noise(t: FloatArray, x: FloatArray) -> tuple[float, float]:
    """A channel's white noise (1 sigma) and median spacing [s] from its own samples (x
    at times t, NaN where a frame lacks it): the median absolute deviation of their
    fourth divided differences (differences.py, at any spacing; a manoeuvre's
    few sharp changes left out; decision 0078). (0, 0) where it has too few samples."""
    d, t_own = channel_differences(t, x)
    if not d.size:
        return 0.0, 0.0
    return mad_sigma(d), float(np.median(np.diff(t_own)))


def noise_sigma(t: FloatArray, x: FloatArray) -> float:
    """A channel's white noise (1 sigma) as the reconstruction's grid t carries it: its
    own (own_noise) times sqrt(own median spacing / the grid's), the grid noise whose
    integral over a second (the attitude and velocity the check integrates) spreads as
    the channel's own does. A channel sampled at a fifth of the frames and filled between
    its samples (_filled) has no noise between them: read from the filled signal, its
    noise was taken a fraction of its size."""
    own, own_dt = own_noise(t, x)
    grid_dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    return own * math.sqrt(own_dt / grid_dt) if grid_dt > 0.0 else own


ROLL_EXCITED_RAD = 0.1
"""Below this rms roll angle the yaw rate's bias cannot be told from the pitch rate's."""


def _attitude_theta(s: _Signals, phi_hat: FloatArray | None) -> tuple[_Params, Model]:
    """theta from q (and r, phi): its model and parameters."""
    par = _Params()
    ib, ik, it = (
        par.add("q", "bias", 0.1),
        par.add("q", "scale", 0.5),
        par.add("theta", "shift", 0.5),
    )
    phi = np.zeros_like(s.t) if phi_hat is None else phi_hat
    cphi, sphi = np.cos(phi), np.sin(phi)
    r = np.zeros_like(s.t) if s.r is None else s.r
    roll = s.r is not None and float(np.sqrt(np.mean(phi**2))) > ROLL_EXCITED_RAD
    ir = par.add("r", "bias", 0.1) if roll else None
    b_cos = _cumint(s.t, cphi, s.segs)
    b_sin = _cumint(s.t, sphi, s.segs)
    ones = np.ones((len(s.t), 1))

    def model(g: FloatArray, loc: FloatArray, derivatives: bool = True) -> list[_Output]:
        q = (s.q - g[ib]) / (1.0 + g[ik])
        rr = r - (g[ir] if ir is not None else 0.0)
        value = loc[s.segs, 0] + _cumint(s.t, q * cphi - rr * sphi, s.segs)
        dg = np.zeros((len(s.t), len(par.names)))
        if not derivatives:
            return [_Output("theta", s.measured["theta"], value, ones, dg, it)]
        dg[:, ib] = -b_cos / (1.0 + g[ik])
        dg[:, ik] = -_cumint(s.t, q * cphi, s.segs) / (1.0 + g[ik])
        if ir is not None:
            dg[:, ir] = b_sin
        return [_Output("theta", s.measured["theta"], value, ones, dg, it)]

    return par, model


def _attitude_phi(s: _Signals, q: FloatArray, r: FloatArray) -> tuple[_Params, Model]:
    """phi from p, q, r and theta."""
    assert s.p is not None and s.phi is not None
    par = _Params()
    ib, ik, it = par.add("p", "bias", 0.1), par.add("p", "scale", 0.5), par.add("phi", "shift", 0.5)
    filled = _filled(s.t, s.measured["theta"])
    theta = np.zeros_like(s.t) if filled is None else filled
    coupling = (q * np.sin(s.phi) + r * np.cos(s.phi)) * np.tan(theta)
    b_one = _cumint(s.t, np.ones_like(s.t), s.segs)
    ones = np.ones((len(s.t), 1))
    p_m = s.p

    def model(g: FloatArray, loc: FloatArray, derivatives: bool = True) -> list[_Output]:
        p = (p_m - g[ib]) / (1.0 + g[ik])
        value = loc[s.segs, 0] + _cumint(s.t, p + coupling, s.segs)
        dg = np.zeros((len(s.t), len(par.names)))
        if not derivatives:
            return [_Output("phi", s.measured["phi"], value, ones, dg, it)]
        dg[:, ib] = -b_one / (1.0 + g[ik])
        dg[:, ik] = -_cumint(s.t, p, s.segs) / (1.0 + g[ik])
        return [_Output("phi", s.measured["phi"], value, ones, dg, it)]

    return par, model


@dataclass
class _Velocity:
    """The velocity stage's set-up: attitude, specific forces at the CG, which NED axes
    the initial velocity has, whether GPS velocity and wind are in it."""

    col0: FloatArray
    col2: FloatArray
    ax: FloatArray
    az: FloatArray
    q: FloatArray
    basis: FloatArray
    """[pieces x 3 x 2] the body x and z axes (NED) at each piece's start: its initial air
    velocity is u0 along the one and w0 along the other (no sideslip: coordinated flight,
    which the missing lateral accelerometer assumes anyway)."""
    gps: bool
    vane: tuple[float, float]
    attitude: tuple[FloatArray, FloatArray, FloatArray]
    """phi, theta, psi as the body axes col0, col2 were made from."""

    def noisy(self, rng: np.random.Generator, s: _Signals) -> _Velocity:
        """The specific forces' noise and the pitch angle's (integrated from the pitch
        rate's) drawn anew."""
        n = len(s.t)
        phi, theta, psi = self.attitude
        walk = _cumint(s.t, s.noise.get("q", 0.0) * rng.standard_normal(n), s.segs)
        col0, col2 = _body_axes(phi, theta + walk, psi)
        ax = self.ax + s.noise.get("a_x", 0.0) * rng.standard_normal(n)
        az = self.az + s.noise.get("a_z", 0.0) * rng.standard_normal(n)
        return replace(self, col0=col0, col2=col2, ax=ax, az=az)


def _body_axes(
    phi: FloatArray, theta: FloatArray, psi: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The body x and z axes in NED (the first and third columns of R(phi, theta, psi))."""
    cf, sf, ct, st, cp, sp = (
        np.cos(phi),
        np.sin(phi),
        np.cos(theta),
        np.sin(theta),
        np.cos(psi),
        np.sin(psi),
    )
    col0 = np.column_stack([ct * cp, ct * sp, -st])
    col2 = np.column_stack([cf * st * cp + sf * sp, cf * st * sp - sf * cp, cf * ct])
    return col0, col2


def _chain(
    d: FloatArray, base: FloatArray, c0: FloatArray, c2: FloatArray, n_local: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Derivatives of an output by the initial velocity's components (base: each
    sample's piece's basis) and the two accelerometer biases, from its derivative d
    [N x 3] by the air velocity."""
    dl = np.zeros((len(d), n_local))
    for j in range(2):
        dl[:, j] = (d * base[:, :, j]).sum(axis=1)
    return dl, -(d * c0).sum(axis=1), -(d * c2).sum(axis=1)


def _velocity_params(s: _Signals, v: _Velocity) -> tuple[_Params, dict[str, int]]:
    par = _Params()
    ix = {"bax": par.add("a_x", "bias", 2.0), "baz": par.add("a_z", "bias", 2.0)}
    if "airspeed" in s.measured:
        ix["kv"], ix["tv"] = par.add("airspeed", "scale", 0.5), par.add("airspeed", "shift", 0.5)
    if "alpha" in s.measured:
        ix["ka"], ix["ba"] = par.add("alpha", "scale", 0.5), par.add("alpha", "bias", 0.2)
        ix["ta"] = par.add("alpha", "shift", 0.5)
    if "vz" in s.measured:
        ix["tz"] = par.add("vz", "shift", 0.5)
    if v.gps:
        ix["tg"] = par.add("gps", "shift", 0.5)
    return par, ix


def _air_velocity(
    s: _Signals, v: _Velocity, g: FloatArray, loc: FloatArray, ix: dict[str, int]
) -> FloatArray:
    f = v.col0 * (v.ax - g[ix["bax"]])[:, None] + v.col2 * (v.az - g[ix["baz"]])[:, None]
    f[:, 2] += G
    va = _cumint(s.t, f, s.segs)
    va += np.einsum("nij,nj->ni", v.basis[s.segs], loc[s.segs, :2])
    return va


def _velocity_model(s: _Signals, v: _Velocity) -> tuple[_Params, Model, int]:
    """Airspeed, angle of attack, climb rate and GPS velocity from the integrated
    specific forces (module docstring)."""
    par, ix = _velocity_params(s, v)
    n_local = 2 + (2 if v.gps else 0)
    c0, c2 = _cumint(s.t, v.col0, s.segs), _cumint(s.t, v.col2, s.segs)
    base = v.basis[s.segs]
    n, ng = len(s.t), len(par.names)

    wanted = [True]

    def output(name: str, value: FloatArray, d: FloatArray, shift: str) -> _Output:
        if not wanted[0]:
            return _Output(
                name, s.measured[name], value, np.empty((n, n_local)), np.empty((n, ng)), ix[shift]
            )
        dl, dbx, dbz = _chain(d, base, c0, c2, n_local)
        dg = np.zeros((n, ng))
        dg[:, ix["bax"]], dg[:, ix["baz"]] = dbx, dbz
        return _Output(name, s.measured[name], value, dl, dg, ix[shift])

    def model(g: FloatArray, loc: FloatArray, derivatives: bool = True) -> list[_Output]:
        wanted[0] = derivatives
        va = _air_velocity(s, v, g, loc, ix)
        outs: list[_Output] = []
        if "kv" in ix:
            speed = np.maximum(np.linalg.norm(va, axis=1), 1e-3)
            o = output(
                "airspeed", (1 + g[ix["kv"]]) * speed, (1 + g[ix["kv"]]) * va / speed[:, None], "tv"
            )
            o.d_global[:, ix["kv"]] = speed
            outs.append(o)
        if "ka" in ix:
            ub = (v.col0 * va).sum(axis=1) + v.q * v.vane[1]
            wb = (v.col2 * va).sum(axis=1) - v.q * v.vane[0]
            den = np.maximum(ub * ub + wb * wb, 1e-6)[:, None]
            alpha = np.arctan2(wb, ub)
            d = (1 + g[ix["ka"]]) * (ub[:, None] * v.col2 - wb[:, None] * v.col0) / den
            o = output("alpha", (1 + g[ix["ka"]]) * alpha + g[ix["ba"]], d, "ta")
            o.d_global[:, ix["ka"]], o.d_global[:, ix["ba"]] = alpha, 1.0
            outs.append(o)
        if "tz" in ix:
            outs.append(output("vz", va[:, 2], np.tile([0.0, 0.0, 1.0], (n, 1)), "tz"))
        if v.gps:
            outs += _gps_outputs(va, loc, s, output, 2)
        return outs

    return par, model, n_local


def _gps_outputs(
    va: FloatArray,
    loc: FloatArray,
    s: _Signals,
    output: Callable[[str, FloatArray, FloatArray, str], _Output],
    k: int,
) -> list[_Output]:
    """GPS velocity north, east, down: the air velocity plus each piece's wind."""
    outs = []
    for axis, name in enumerate(("vn", "ve", "vd")):
        d = np.zeros((len(s.t), 3))
        d[:, axis] = 1.0
        value = va[:, axis] + (loc[s.segs, k + axis] if axis < 2 else 0.0)
        o = output(name, value, d, "tg")
        if axis < 2:
            o.d_local[:, k + axis] = 1.0
        outs.append(o)
    return outs


# ------------------------------------------------------------------------ the check


def _aux(rec: Recording, name: str) -> FloatArray | None:
    x = rec.aux.get(name)
    return None if x is None or np.isfinite(x).sum() < MIN_SAMPLES else np.asarray(x, float)


def _signals(rec: Recording) -> _Signals | None:
    """The channels, or None where the record has no pitch rate or pitch angle."""
    t = np.asarray(rec.t_s, float)
    m = rec.measurements
    q = _filled(t, m[:, Q])
    if q is None or len(t) < 2 * MIN_SAMPLES or np.isfinite(m[:, THETA]).sum() < MIN_SAMPLES:
        return None
    measured = {"theta": m[:, THETA]}
    for name, col in (("airspeed", V), ("alpha", ALPHA)):
        if np.isfinite(m[:, col]).sum() >= MIN_SAMPLES:
            measured[name] = m[:, col]
    for name in ("phi", "vz", "vn", "ve", "vd"):
        x = _aux(rec, name)
        if x is not None:
            measured[name] = x
    psi = _aux(rec, "psi")
    if psi is not None:
        ok = np.isfinite(psi)
        psi = np.interp(t, t[ok], np.unwrap(psi[ok]))
    segs = segments(t)
    p, r = _filled(t, _aux(rec, "p")), _filled(t, _aux(rec, "r"))
    raw = {"q": m[:, Q], "p": _aux(rec, "p"), "r": _aux(rec, "r")}
    noise = {k: noise_sigma(t, x) for k, x in raw.items() if x is not None}
    phi = _filled(t, _aux(rec, "phi"))
    return _Signals(t, segs, _keep(t, segs), q, p, r, phi, psi, measured, noise)


def _stage(
    par: _Params,
    model: Model,
    s: _Signals,
    n_local: int,
    local_prior: float,
    start: FloatArray,
    sigma0: dict[str, float],
    replicas: Replicas,
    excited: np.ndarray,
) -> _Fit:
    """One stage's fit, its global parameters from the pieces the manoeuvres excite (the
    others' only their own initial conditions; all, with the scale factors held at zero,
    where none is excited: a scale is told from the motion it scales, and in calm
    straight flight that motion is smaller than the integrated noise, which biases the
    scale towards -1, as errors in a regressor do: -25 % on the airspeed, -65 % on alpha
    over an hour of simulated steady flight)."""
    informs = excited[s.segs]
    if not excited.any():
        par.pin_scales()
        informs = np.ones(len(s.t), dtype=bool)
    prior = (np.array(par.prior), np.full(n_local, local_prior))
    start_ = (np.zeros(len(par.names)), start)
    return _fit(model, s.t, s.segs, (s.keep, informs), prior, start_, sigma0, replicas)


def _excited(s: _Signals, x: FloatArray, walk: float) -> np.ndarray:
    """Which pieces the output x moves in by over EXCITED times the random walk its
    model's integrated inputs make there (walk: that walk's sigma per sqrt(second))."""
    n_seg = int(s.segs.max()) + 1
    ok = np.isfinite(x)
    out = np.zeros(n_seg, dtype=bool)
    for k in range(n_seg):
        idx = np.nonzero(ok & (s.segs == k))[0]
        if len(idx) >= MIN_SAMPLES:
            span = float(s.t[idx[-1]] - s.t[idx[0]])
            own, _ = own_noise(s.t[idx], x[idx])
            out[k] = float(np.std(x[idx])) > EXCITED * math.hypot(walk * math.sqrt(span), own)
    return out


def _velocity_excited(s: _Signals, speed: FloatArray) -> np.ndarray:
    """Pieces in which the airspeed (or the climb rate) or the angle of attack moves."""
    walk = max(_walk(s, "a_x"), _walk(s, "a_z"))
    out = _excited(s, speed, walk)
    if "alpha" in s.measured:
        v = max(float(np.nanmedian(speed)), 1.0)
        out |= _excited(s, s.measured["alpha"], walk / v)
    return out


def _walk(s: _Signals, name: str) -> float:
    """The random walk per sqrt(second) of an input's integrated white noise."""
    return s.noise.get(name, 0.0) * math.sqrt(float(np.median(np.diff(s.t))))


def _first_values(s: _Signals, x: FloatArray) -> FloatArray:
    """Each piece's first finite value of x (0 where it has none)."""
    n_seg = int(s.segs.max()) + 1
    out = np.zeros(n_seg)
    ok = np.isfinite(x)
    for k in range(n_seg):
        idx = np.nonzero(ok & (s.segs == k))[0]
        if len(idx):
            out[k] = x[idx[0]]
    return out


@dataclass
class _Found:
    findings: list[Finding] = field(default_factory=list)
    rms: dict[str, float] = field(default_factory=dict)
    aux: dict[str, FloatArray] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def add(self, par: _Params, fit: _Fit) -> dict[tuple[str, str], float]:
        self.findings += par.findings(fit)
        self.rms.update(fit.rms)
        return {name: float(fit.globals_[i]) for i, name in enumerate(par.names)}


def _attitudes(
    s: _Signals, found: _Found
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Roll and pitch as reconstructed, heading, and the corrected pitch and yaw rates."""
    phi_hat = None
    if s.p is not None and s.phi is not None and "phi" in s.measured:
        r0 = np.zeros_like(s.t) if s.r is None else s.r
        par, model = _attitude_phi(s, s.q, r0)
        first = _first_values(s, s.measured["phi"])[:, None]
        fit = _stage(
            par,
            model,
            s,
            1,
            1.0,
            first,
            {"phi": 0.005},
            lambda rng: _attitude_phi(s.noisy(rng), s.q, r0)[1],
            _excited(s, s.measured["phi"], _walk(s, "p")),
        )
        found.add(par, fit)
        phi_hat = fit.outputs[0].value
    roll = phi_hat if phi_hat is not None else s.phi
    par, model = _attitude_theta(s, roll)
    first = _first_values(s, s.measured["theta"])[:, None]
    fit = _stage(
        par,
        model,
        s,
        1,
        1.0,
        first,
        {"theta": 0.005},
        lambda rng: _attitude_theta(s.noisy(rng), roll)[1],
        _excited(s, s.measured["theta"], _walk(s, "q")),
    )
    got = found.add(par, fit)
    theta_hat = fit.outputs[0].value
    q = (s.q - got[("q", "bias")]) / (1.0 + got[("q", "scale")])
    r = np.zeros_like(s.t) if s.r is None else s.r - got.get(("r", "bias"), 0.0)
    phi = np.zeros_like(s.t) if phi_hat is None else phi_hat
    if s.psi is not None:
        psi = s.psi
    elif phi_hat is not None:
        psi = _cumint(
            s.t, (q * np.sin(phi) + r * np.cos(phi)) / np.cos(theta_hat), np.zeros_like(s.segs)
        )
    else:
        psi = np.zeros_like(s.t)
    return phi, theta_hat, psi, q, r


def _velocity_stage(
    rec: Recording,
    s: _Signals,
    sensors: SensorPlacement,
    found: _Found,
    att: tuple[FloatArray, ...],
) -> None:
    phi, theta, psi, q, _r = att
    m = rec.measurements
    ax, az = _filled(s.t, m[:, AX]), _filled(s.t, m[:, AZ])
    gps = all(k in s.measured for k in ("vn", "ve", "vd")) and s.psi is not None
    if ax is None or az is None or not ({"airspeed", "vz"} & set(s.measured) or gps):
        found.notes.append(
            "no accelerations, or no airspeed, climb rate or GPS velocity: velocity not checked"
        )
        return
    if not gps:
        for k in ("vn", "ve", "vd"):
            s.measured.pop(k, None)
    qdot = _filled(s.t, m[:, QDOT])
    qdot = np.gradient(q, s.t) if qdot is None else qdot
    xa, za = sensors.accel_x_m, sensors.accel_z_m
    ax_cg = ax - (qdot * za - q * q * xa)
    az_cg = az + qdot * xa + q * q * za
    col0, col2 = _body_axes(phi, theta, psi)
    starts = np.array([np.nonzero(s.segs == k)[0][0] for k in range(int(s.segs.max()) + 1)])
    v = _Velocity(
        col0,
        col2,
        ax_cg,
        az_cg,
        q,
        np.stack([col0[starts], col2[starts]], axis=2),
        gps,
        (sensors.vane_x_m, sensors.vane_z_m),
        (phi, theta, psi),
    )
    s.noise["a_x"], s.noise["a_z"] = noise_sigma(s.t, m[:, AX]), noise_sigma(s.t, m[:, AZ])
    par, model, n_local = _velocity_model(s, v)
    speed = s.measured.get("airspeed")
    if speed is None and gps:
        speed = np.linalg.norm(np.column_stack([s.measured[k] for k in ("vn", "ve", "vd")]), axis=1)
    if speed is None:
        speed = s.measured["vz"]
    first = _first_values(s, speed)
    start = np.zeros((len(first), n_local))
    aoa = s.measured.get("alpha")
    first_alpha = _first_values(s, aoa) if aoa is not None else np.zeros(len(first))
    start[:, 0], start[:, 1] = first * np.cos(first_alpha), first * np.sin(first_alpha)
    sigma0 = {"airspeed": 0.3, "alpha": 0.005, "vz": 0.3, "vn": 0.3, "ve": 0.3, "vd": 0.3}
    fit = _stage(
        par,
        model,
        s,
        n_local,
        100.0,
        start,
        sigma0,
        lambda rng: _velocity_model(s, v.noisy(rng, s))[1],
        _velocity_excited(s, speed),
    )
    found.add(par, fit)
    if gps:
        _, ix = _velocity_params(s, v)
        va = _air_velocity(s, v, fit.globals_, fit.locals_, ix)
        found.aux["alpha_fpr"] = np.arctan2((col2 * va).sum(axis=1), (col0 * va).sum(axis=1))
        found.aux["wind_n_fpr"] = fit.locals_[s.segs, 2]
        found.aux["wind_e_fpr"] = fit.locals_[s.segs, 3]


def check(
    rec: Recording, sensors: SensorPlacement | None = None, correct: bool = True
) -> Compatibility:
    """The record's data compatibility (module docstring): each channel's findings, and
    the record with the significant ones removed (as given where correct is False), the
    reconstructed alpha and wind in its aux where it has GPS velocity and a heading."""
    s = _signals(rec)
    if s is None:
        return Compatibility((), rec, False, notes=("no pitch rate or pitch angle to check",))
    found = _Found()
    att = _attitudes(s, found)
    _velocity_stage(rec, s, sensors or SensorPlacement(), found, att)
    out = _corrected(rec, found.findings) if correct else rec
    if found.aux:
        out = replace(out, aux={**out.aux, **found.aux})
    return Compatibility(tuple(found.findings), out, correct, found.rms, tuple(found.notes))


def of_frames(
    t: FloatArray, u: FloatArray, y: FloatArray, sensors: SensorPlacement | None = None
) -> Compatibility:
    """The check of a run's frames, reported only: times t [N], inputs u [N x k] (the
    bank angle and the roll and yaw rates where k reaches them, model.channels), the
    observations y [N x c] (the climb rate, where present, as vz). What a link or a
    tlog's replay gives, whose frames no reader checked before the filters took them."""
    u = np.asarray(u, float)
    y = np.asarray(y, float)
    aux: dict[str, FloatArray] = {}
    for name, channel in (("phi", Channel.PHI), ("p", Channel.ROLL_RATE), ("r", Channel.YAW_RATE)):
        col = int(channel) - int(Channel.ELEVATOR)
        if u.shape[1] > col and np.isfinite(u[:, col]).any():
            aux[name] = u[:, col]
    if y.shape[1] > Channel.HDOT and np.isfinite(y[:, Channel.HDOT]).any():
        aux["vz"] = -y[:, Channel.HDOT]
    rec = Recording(np.asarray(t, float), u[:, :3], y, "throttle", aux=aux)
    return check(rec, sensors, correct=False)


def checked(rec: Recording, config: AircraftConfig) -> Recording:
    """The record as [data] compatibility_check says: corrected ("correct"), as it is
    ("report"), each with the report in its notes and the findings on it; "off": as it is."""
    mode = config.data.compatibility_check
    if mode == "off":
        return rec
    found = check(rec, config.sensors, correct=mode == "correct")
    return replace(
        found.recording,
        notes=(*rec.notes, *found.lines()),
        compatibility={"mode": mode, **found.as_dict()},
    )


# ------------------------------------------------------------------- the correction


def _unshift(t: FloatArray, x: FloatArray, tau: float) -> FloatArray:
    """A channel that lags by tau put back in time: its value at t is x(t + tau); missing
    samples stay missing."""
    ok = np.isfinite(x)
    out = np.full_like(x, np.nan)
    out[ok] = np.interp(t[ok] + tau, t[ok], x[ok])
    return out


MEASURED_COLUMNS = {"theta": THETA, "airspeed": V, "alpha": ALPHA}
"""Shifted channels in the measurement columns; the others are in aux by their name."""


def _corrected(rec: Recording, findings: list[Finding]) -> Recording:
    """The record without its significant findings: shifts first (a lag back to the rates'
    time), then biases and scale factors."""
    m = rec.measurements.copy()
    aux = dict(rec.aux)
    t = rec.t_s
    on = {(f.channel, f.kind): f.value for f in findings if f.significant}
    for (ch, kind), value in on.items():
        if kind != "shift":
            continue
        for name in ("vn", "ve", "vd") if ch == "gps" else (ch,):
            if name in MEASURED_COLUMNS:
                col = MEASURED_COLUMNS[name]
                m[:, col] = _unshift(t, m[:, col], value)
            elif name in aux:
                aux[name] = _unshift(t, aux[name], value)
    _rescale(m, aux, on)
    return replace(rec, measurements=m, aux=aux)


def _rescale(m: FloatArray, aux: dict[str, FloatArray], on: dict[tuple[str, str], float]) -> None:
    """Biases and scale factors removed (in place): measured = (1 + k) true + b."""
    k_q = on.get(("q", "scale"), 0.0)
    m[:, Q] = (m[:, Q] - on.get(("q", "bias"), 0.0)) / (1.0 + k_q)
    m[:, QDOT] /= 1.0 + k_q
    m[:, AX] -= on.get(("a_x", "bias"), 0.0)
    m[:, AZ] -= on.get(("a_z", "bias"), 0.0)
    m[:, V] /= 1.0 + on.get(("airspeed", "scale"), 0.0)
    m[:, ALPHA] = (m[:, ALPHA] - on.get(("alpha", "bias"), 0.0)) / (
        1.0 + on.get(("alpha", "scale"), 0.0)
    )
    if "p" in aux:
        aux["p"] = (aux["p"] - on.get(("p", "bias"), 0.0)) / (1.0 + on.get(("p", "scale"), 0.0))
    if "r" in aux:
        aux["r"] = aux["r"] - on.get(("r", "bias"), 0.0)
