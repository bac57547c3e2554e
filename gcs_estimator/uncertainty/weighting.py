"""The structure check: how far each coefficient depends on how much each channel is
trusted, as an uncertainty the covariance does not hold (docs/decisions/0017).

A filter weighs every channel by the inverse of its measurement noise. Where the model
holds, the channels agree on the coefficients: trusting one of them less loses some of
its information and moves the estimates only as far as that lost information allows,
which the covariance predicts (the variance of the move is the variance gained; Hausman
1978). Where the model's structure misses something the aircraft does, the channels
pull towards different values, and the estimate is a compromise set by the weights: it
moves further than the covariance predicts, and no data from the same manoeuvre can say
which weighting is right.

So, at the end of a run, its final pass is replayed through both filters over the run's
history, once as it ran and once per channel the data carry with that channel's
measurement variance doubled (its weight halved): d_i, the move of the estimates in
replay i, beyond the variance the covariance predicts for it, is the estimate's
sensitivity to that channel's weight. Each weight is taken as
known within a factor of 2 either way (log-uniform: Var(ln w) = (ln 2)^2 / 3), so to
first order the estimate's variance from the weights is

    sum_i max(0, d_i^2 - |sigma_i^2 - sigma^2|) / 3,

the structure sigma. The sigma to trust (sigma.trusted_sigma) adds it in quadrature to
the covariance's sigma widened by how the estimates moved over the run (0008): that
correction sees drift and colour, this one a bias that the channels' disagreement sets
and the estimates settle on.

The same replays carry what the data cannot decide (docs/decisions/0047): the final pass
again with the inputs TIMING_TOLERANCE_S later (the inputs' timing: the hold between
samples, a servo's lag, a skewed log), with each sensor position moved by the placement
tolerance (the vane's and the accelerometers' place, from an airframe file's measurement
or guess), and, where the run read a channel's noise below the configured sigma
(measurement_noise = "auto" on a record with almost no noise), at the configured noise.
Where the likelihood over a pair is far narrower than the pair, a close pair places the
quantity (docs/decisions/0073). Each tolerance is taken as uniform, so a move d gives
the variance d^2 / 3; the noise replay's covariance sigma is a floor under the run's (a
record read as clean is trusted no further than one at the sensors' nominal noise: what
the model misses stays as the noise goes). These parts are added to the structure sigma
in quadrature (the floor as its excess over the run's covariance), and kept apart in
`parts`.

Two more replays carry what the data cannot decide and no likelihood sharpens
(docs/decisions/0059): the final pass with the inputs held the other way between frames
("hold": linear against held at the earlier sample, [data] input_hold; an input that
steps between two samples lies somewhere between the two), and the estimates' move in the
noise replay ("noise_level": the noise of a record read as clean lies between the level
read and the configured). Each is a quantity uniform between the run's value and the
replay's, so the move beyond what the two covariances allow gives the variance d^2 / 3.
The hold's replay sums its likelihood, which decides only between the two ends
(docs/decisions/0071): where the other hold fits decisively better the whole move counts
(d^2), and where the run holds each input until the next frame and fits decisively
better, nothing (the inputs change at the frames; how far from them, the timing part's
profile places).
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextvars import ContextVar
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.delay import delayed_inputs
from gcs_estimator.estimation.estimator import FILTER_KINDS, Estimator, FilterKind
from gcs_estimator.model.channels import N_OBS, OBS_NAMES

TIMING_TOLERANCE_S = 0.01
"""How far the inputs' timing is taken as unknown either way, at least [s] (the data's
half sample interval where that is longer: the linear and the held inputs differ by
about that); a moved coefficient's variance is its move squared over 3."""
PLACEMENT_SHARE = 0.05
"""How far each sensor position is taken as unknown either way: this share of the mean
chord, and at least PLACEMENT_MIN_M."""
PLACEMENT_MIN_M = 0.01
PLACEMENT_KEYS: tuple[str, ...] = ("vane_x_m", "accel_x_m", "accel_z_m")
"""The [sensors] positions whose tolerance enters the sigma (the vane's height moves
alpha by q times it over V only in its cosine: negligible)."""
PLACEMENT_CHANNELS: dict[str, tuple[str, ...]] = {
    "vane_x_m": ("alpha",),
    "accel_x_m": ("a_x", "a_z"),
    "accel_z_m": ("a_x", "a_z"),
}
"""The channels each position moves (equations.sensor_placement, turn_placement): on a
record where none of them has data the position moves nothing, so its replays are not
run (decision 0070: a record without a vane saves four)."""
PROFILE_WIDE = 4.0
"""Where the likelihood over +-tolerance has no least between (the quantity lies beyond),
the pair is replayed again this many tolerances out."""
LIKELIHOOD_TIE = 4.0
"""Two replays whose -2 log likelihoods differ by less than this (two standard
deviations of one parameter's chi-square) do not say which side is likelier."""
PROFILE_LOCAL = 10.0
"""Where a filter's likelihood over a pair is a parabola at least this many times narrower
than the pair's step, the pair is replayed again LOCAL_SPREADS of that width either side
of the configured value (decision 0073)."""
LOCAL_SPREADS = 3.0
LOCAL_AGREE = 4.0
"""A close pair's parabola is taken only where it predicts the rise of the pair's ends
within this factor either way: one valley, not a dip in a rugged likelihood whose least
lies elsewhere (decision 0073)."""
PROFILE_REACH = 10.0
"""How many tolerances from the configured value a quantity's likelihood parabola may
place its least (beyond, three replays cannot tell)."""
UNIFORM_SHARE = 1.0 / 3.0
"""A quantity uniform within +-a has variance a^2 / 3."""
VARIANCE_FACTOR = 2.0
"""A channel's measurement variance is multiplied by this in its run (its weight
halved)."""
WEIGHT_SHARE = 1.0 / 3.0
"""Var(ln w) / (ln VARIANCE_FACTOR)^2 for a weight known within VARIANCE_FACTOR either
way (log-uniform)."""
_THREADS: ContextVar[int | None] = ContextVar("check_threads", default=None)
_PROCESS_THREADS: list[int] = []
"""The process's cap on the check's threads, where one is set (set_process_threads)."""


@contextlib.contextmanager
def replay_threads(count: int) -> Iterator[None]:
    """The check's replays in at most `count` threads while the block runs, in this
    thread (a batch's task: its worker runs as many tasks at once as it has threads, so
    each task's replays take one; decision 0070)."""
    token = _THREADS.set(max(1, count))
    try:
        yield
    finally:
        _THREADS.reset(token)


def set_process_threads(count: int) -> None:
    """Cap the check's threads in every thread of this process (a process one of several
    sharing the machine's cores: each of `replay --each`'s replays)."""
    _PROCESS_THREADS[:] = [max(1, count)]


def check_threads() -> int:
    """The threads the check's replays may use here: replay_threads' count, else the
    process's cap, else the cores this process may run on."""
    count = _THREADS.get()
    if count is not None:
        return count
    if _PROCESS_THREADS:
        return _PROCESS_THREADS[0]
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


class StructureCheck(NamedTuple):
    """The check's outcome for one vehicle."""

    sigma: dict[FilterKind, FloatArray]
    """Per filter, per coefficient: the structure sigma (empty when skipped)."""
    moves: dict[FilterKind, FloatArray]
    """Per filter, [channels x coefficients]: how far each estimate moved with that
    channel's weight halved."""
    channels: tuple[str, ...] = ()
    """The channels re-weighted (those the data carry)."""
    skipped: str = ""
    """Why the check was not made ("" when it was)."""
    parts: dict[str, dict[FilterKind, FloatArray]] = {}  # noqa: RUF012  (never mutated)
    """The sigma's parts per filter and coefficient: "weights" (the channels' weights),
    "timing" (the inputs TIMING_TOLERANCE_S later), "placement" (the sensor positions
    within their tolerance), "noise_floor" (the excess of the covariance sigma at the
    configured noise over the run's) and "noise_level"
    (the estimates' move at the configured noise), both absent where no channel was read
    below it; "hold" (the estimates' move with the inputs held the other way between
    frames); `sigma` is their root sum of squares."""
    tolerances: dict[str, float] = {}  # noqa: RUF012  (never mutated)
    """The tolerances the check took: "timing" [s], "placement" [m]."""
    found: dict[str, tuple[float, float]] = {}  # noqa: RUF012  (never mutated)
    """Per quantity ("input_delay_s", "vane_x_m", ...), where the first filter's
    likelihood puts it from the configured value, and its sigma (NaN: not decided):
    the inputs' delay beyond [data] input_delay_s, each position's offset [SI]."""
    linear_inputs: bool = True
    """The run's hold between frames ([data] input_hold: linear, or held at the earlier)."""
    hold_change: float = math.nan
    """The first filter's -2 log likelihood over the final pass with the inputs held the
    other way, minus the run's (NaN: not replayed): below -LIKELIHOOD_TIE the other hold
    fits decisively better (decision 0071)."""

    @property
    def input_hold(self) -> str:
        """The run's hold by its [data] input_hold name."""
        return "linear" if self.linear_inputs else "previous"

    @property
    def hold_preferred(self) -> str:
        """The hold the likelihood prefers decisively ("linear" or "previous", the
        [data] input_hold names), or "" where it does not."""
        if not math.isfinite(self.hold_change) or abs(self.hold_change) <= LIKELIHOOD_TIE:
            return ""
        linear = self.linear_inputs if self.hold_change > 0.0 else not self.linear_inputs
        return "linear" if linear else "previous"


def skipped(reason: str) -> StructureCheck:
    return StructureCheck({}, {}, (), reason)


def why_not(config: AircraftConfig, frames: int, history: bool, checked: int = 0) -> str:
    """Why the check is not made for a vehicle's run of `frames` frames, `checked` frames
    of the session's other vehicles having been checked before it ("" when it is)."""
    mode = config.filter.structure_check
    if mode == "off":
        return "filter.structure_check is off"
    if not history:
        return "the run kept no history to replay"
    if frames < 2:
        return "too few frames"
    limit = config.filter.structure_check_max_frames
    if mode == "auto" and checked + frames > limit:
        others = f" (with the {checked} of the vehicles checked before it)" if checked else ""
        return (
            f"{frames} frames{others}, more than filter.structure_check_max_frames = "
            f'{limit} (set it higher, or filter.structure_check = "on")'
        )
    return ""


class Replay(NamedTuple):
    """One replay of the final pass: the measurement variances times scale (None: as they
    were), over inputs u, with the airframe `config` (None: the run's)."""

    scale: FloatArray | None
    u: FloatArray
    config: AircraftConfig | None = None
    profile: bool = False
    """Sum each filter's -2 log likelihood over the pass (frame by frame)."""
    linear_inputs: bool | None = None
    """The inputs between two frames linear (True) or held at the earlier (False); None:
    as the run took them ([data] input_hold)."""


Final = dict[FilterKind, tuple[FloatArray, FloatArray, float]]
"""Per filter: final coefficients, their covariance sigma, -2 log likelihood (NaN where
not summed)."""
Replayer = Callable[[list[Replay]], list[Final]]
"""Runs a batch of replays (on the check's one thread pool) and gives their finals in
order."""


def _final(est: Estimator, t: FloatArray, y: FloatArray, replay: Replay) -> Final:
    """Each filter's final coefficients, their covariance sigma and (replay.profile) the
    pass's -2 log likelihood with the run's final pass replayed as `replay` says."""
    scale, u = replay.scale, replay.u
    config = est.config if replay.config is None else replay.config
    again = Estimator(config, backend=est.backend, keep_history=False, noise_scale=scale)
    if replay.profile:
        again.runner.likelihood = {}
    source = est
    if replay.linear_inputs is not None:  # the run's pass under the other hold
        source = copy.copy(est)
        hold = replay.linear_inputs
        source.tunings = {k: tn._replace(linear_inputs=hold) for k, tn in est.tunings.items()}
    again.replay_final_pass(source, t, u, y)
    coef = again.model.coefficients
    sums = again.runner.likelihood or {}
    out: Final = {}
    for kind, state in again.states.items():
        if state is not None:
            like = sums.get(kind, math.nan)
            out[kind] = (state.x[coef].copy(), np.sqrt(np.diag(state.P))[coef], like)
    return out


def structure_check(est: Estimator, t: FloatArray, u: FloatArray, y: FloatArray) -> StructureCheck:
    """The check of a finished run (est) over its frames (t [N], u [N x 3] as the
    equations take them, y [N x 7]: its history): its final pass replayed as it ran, then
    once per channel with data, that channel's weight halved, and twice per quantity the
    data cannot decide for sure (module docstring)."""
    if np.any(np.diff(t) <= 0.0):
        return skipped("the vehicle clock restarted during the run (its frames are not one record)")
    channels = _with_data(y)
    if not channels:
        return skipped("no channel has data")
    undecided, tolerances = _undecided(est, t, u, channels)
    replays = _replays(u, channels, undecided, tolerances)

    # The replays are independent and spend most of their time in compiled steps that
    # release the GIL: threads run them side by side on the cores allowed, one pool for
    # every batch the check replays (the pairs it adds later too).
    threads = min(len(replays), check_threads())
    with contextlib.ExitStack() as stack:
        pool = stack.enter_context(ThreadPoolExecutor(threads)) if threads > 1 else None

        def again(batch: list[Replay]) -> list[Final]:
            if pool is None:
                return [_final(est, t, y, r) for r in batch]
            return list(pool.map(lambda r: _final(est, t, y, r), batch))

        return _checked(est, again(replays), channels, undecided, tolerances, again)


def _checked(
    est: Estimator,
    finals: list[Final],
    channels: list[int],
    undecided: Undecided,
    tolerances: dict[str, float],
    again: Replayer,
) -> StructureCheck:
    """The check from its replays' finals (in _replays' order), `again` replaying any
    pair it adds."""
    base, *finals = finals
    if set(base) != set(FILTER_KINDS):
        return skipped("no frame reached the filters")
    p = base[FILTER_KINDS[0]][0].shape[0]
    moves = {k: np.zeros((len(channels), p)) for k in FILTER_KINDS}
    excess = {k: np.zeros(p) for k in FILTER_KINDS}
    for a, run in enumerate(finals[: len(channels)]):
        for kind in FILTER_KINDS:
            (b, s, _), (v, vs, _) = base[kind], run[kind]
            d = v - b
            moves[kind][a] = d
            excess[kind] += np.maximum(0.0, d * d - np.abs(vs * vs - s * s))
    parts = {"weights": {k: np.sqrt(WEIGHT_SHARE * excess[k]) for k in FILTER_KINDS}}
    rest = finals[len(channels) :]
    linear = est.tunings[FILTER_KINDS[0]].linear_inputs
    found = _undecided_parts(parts, base, rest, undecided, tolerances, again, linear)
    hold = found.pop(HOLD_KEY, (math.nan, math.nan))[0]
    sigma = {k: np.sqrt(sum(part[k] ** 2 for part in parts.values())) for k in FILTER_KINDS}
    names = tuple(OBS_NAMES[i] for i in channels)
    return StructureCheck(sigma, moves, names, "", parts, tolerances, found, linear, hold)


def _replays(
    u: FloatArray, channels: list[int], undecided: Undecided, tolerances: dict[str, float]
) -> list[Replay]:
    """The check's replays in order: the final pass as it ran, each channel's weight
    halved, then each undecided quantity's (a pair at +-tol, or one)."""
    replays = [Replay(None, u, profile=True)]
    for ch in channels:
        scale = np.ones(N_OBS)
        scale[ch] = VARIANCE_FACTOR
        replays.append(Replay(scale, u))
    for label, _, make in undecided:
        if make is None:
            continue
        tol = tolerances.get(label, 0.0)
        replays += [make(tol), make(-tol)] if tol > 0.0 else [make(0.0)]
    return replays


Maker = Callable[[float], Replay]
"""The replay of the final pass with a quantity moved by an offset from the configured."""
Undecided = list[tuple[str, str, Maker | None]]
"""Each quantity the data cannot decide for sure: its part's name, its key and its
replay (None: it moves no channel with data, and is not replayed)."""


def _undecided_parts(
    parts: dict[str, dict[FilterKind, FloatArray]],
    base: Final,
    rest: list[Final],
    undecided: Undecided,
    tolerances: dict[str, float],
    again: Replayer,
    linear: bool,
) -> dict[str, tuple[float, float]]:
    """Add the undecided quantities' parts to `parts` from their replays `rest` (in
    _undecided's order: a pair at +tol and -tol per quantity, one each for the noise
    floor and the other hold, `linear` the run's hold);
    where the likelihood has no curvature over a pair, the pair again at PROFILE_WIDE
    tolerances (`again` replays them). Returns where the first filter's likelihood puts
    each quantity (_profile), and under HOLD_KEY its likelihood change with the other
    hold (_hold_part)."""
    found: dict[str, tuple[float, float]] = {}
    p = base[FILTER_KINDS[0]][0].shape[0]
    j = 0
    for label, key, make in undecided:
        part = parts.setdefault(label, {k: np.zeros(p) for k in FILTER_KINDS})
        if make is None:  # moves nothing measured: its part 0, where it lies not decided
            found[key] = (math.nan, math.nan)
            continue
        tol = tolerances.get(label, 0.0)
        if tol <= 0.0:  # one replay: the noise floor's or the other hold's
            moved = parts.setdefault(
                ONE_REPLAY_MOVES[label], {k: np.zeros(p) for k in FILTER_KINDS}
            )
            decided = _one_replay_parts(label, part, moved, base, rest[j], linear)
            if decided is not None:
                found[key] = decided
            j += 1
            continue
        profiles = _pair_profiles(base, rest[j], rest[j + 1], tol, make, again)
        j += 2
        for kind in FILTER_KINDS:
            extra, where = profiles[kind]
            part[kind] = np.hypot(part[kind], extra)
            if kind == FILTER_KINDS[0]:
                found[key] = where
    return found


Profile = tuple[FloatArray, tuple[float, float]]
"""A quantity's part of the coefficients' sigma, and where the likelihood puts it
(_profile)."""


def _pair_profiles(
    base: Final,
    up: Final,
    down: Final,
    tol: float,
    make: Maker,
    again: Replayer,
) -> dict[FilterKind, Profile]:
    """Each filter's profile of a quantity from its pair of replays at +-tol (up, down):
    where some filter's likelihood has no curvature over it, from the pair again at
    PROFILE_WIDE tolerances; where some filter's is far narrower than the pair's step,
    each filter's from a close pair (_local_step) where that pair's parabola describes
    the one valley the wide pair shows (_one_valley; `make` makes, `again` replays)."""
    step = tol
    if not all(_curved(base[k], up[k], down[k]) for k in FILTER_KINDS):
        step = PROFILE_WIDE * tol
        up, down = again([make(step), make(-step)])
    profiles = {k: _profile(base[k], up[k], down[k], step, tol) for k in FILTER_KINDS}
    near = _local_step(profiles, step)
    if near > 0.0:
        close_up, close_down = again([make(near), make(-near)])
        for kind in FILTER_KINDS:
            local = _profile(base[kind], close_up[kind], close_down[kind], near, tol)
            ends = (up[kind][2] - base[kind][2], down[kind][2] - base[kind][2])
            if _one_valley(local[1], ends, step, near):
                profiles[kind] = local
    return profiles


def _one_valley(
    where: tuple[float, float], rises: tuple[float, float], step: float, near: float
) -> bool:
    """Whether a close pair's parabola (least, spread: `where`) places the quantity: its
    least between the close pair's ends (+-near), and the -2 log likelihood's rises at
    the wide pair's ends (+-step: `rises`) within LOCAL_AGREE either way of what that
    parabola predicts there."""
    least, spread = where
    if not (math.isfinite(least) and math.isfinite(spread)) or abs(least) > near:
        return False
    for end, rise in zip((step, -step), rises, strict=True):
        predicted = ((end - least) ** 2 - least**2) / spread**2
        if not (predicted > 0.0 and rise > 0.0):
            return False
        if not 1.0 / LOCAL_AGREE <= rise / predicted <= LOCAL_AGREE:
            return False
    return True


def _local_step(profiles: dict[FilterKind, Profile], step: float) -> float:
    """The step of a close pair (decision 0073): LOCAL_SPREADS times the narrowest of the
    filters' likelihood parabolas over a pair `step` either side, where that is at least
    PROFILE_LOCAL times narrower than the step; else 0 (no close pair). Over a pair
    that far out, a likelihood that narrow is not a parabola: the one through its three
    points puts the least where the two ends' difference sets it, which can be many of
    its widths from where the likelihood is least."""
    spreads = [where[1] for _, where in profiles.values() if math.isfinite(where[1])]
    if not spreads or min(spreads) * PROFILE_LOCAL > step:
        return 0.0
    return LOCAL_SPREADS * min(spreads)


def _one_replay_parts(
    label: str,
    part: dict[FilterKind, FloatArray],
    moved: dict[FilterKind, FloatArray],
    base: Final,
    run: Final,
    linear: bool,
) -> tuple[float, float] | None:
    """Fill a one-replay quantity's parts from its replay `run`: the noise floor's
    (`part`) and the move (`moved`: "noise_level", or "hold" as the likelihood decides
    it, _hold_part); returns the hold's likelihood change as `found` keeps it (None for
    the noise floor)."""
    decided = None
    for kind in FILTER_KINDS:
        floor, move = _one_replay(base[kind], run[kind])
        if label == "hold":
            move, where = _hold_part(base[kind], run[kind], move, linear)
            if kind == FILTER_KINDS[0]:
                decided = where
        moved[kind] = move
        if label == "noise_floor":
            part[kind] = floor
    return decided


def _one_replay(
    base: tuple[FloatArray, FloatArray, float], run: tuple[FloatArray, FloatArray, float]
) -> tuple[FloatArray, FloatArray]:
    """Two parts from one replay (the noise floor's, at the configured noise; the hold's,
    with the inputs held the other way between frames): the excess of the replay's
    covariance sigma over the run's (the noise floor), and the move of the estimates
    beyond the variance their covariances differ by, the quantity taken as uniform
    between the run's value and the replay's (UNIFORM_SHARE of the move squared)."""
    (b, s, _), (v, vs, _) = base, run
    d = v - b
    floor = np.sqrt(np.maximum(0.0, vs * vs - s * s))
    moved = np.sqrt(UNIFORM_SHARE * np.maximum(0.0, d * d - np.abs(vs * vs - s * s)))
    return np.asarray(floor), np.asarray(moved)


def _hold_part(
    base: tuple[FloatArray, FloatArray, float],
    run: tuple[FloatArray, FloatArray, float],
    uniform: FloatArray,
    linear: bool,
) -> tuple[FloatArray, tuple[float, float]]:
    """The hold's part where the pass's likelihood decides between the two holds
    (docs/decisions/0071): `uniform` is the part as a quantity uniform between the run's
    estimates and the replay's (_one_replay); `linear` the run's hold. With L the pass's
    -2 log likelihood, the replay's minus the run's:

    - L < -LIKELIHOOD_TIE (the other hold fits decisively better): the run's estimates
      sit at the end the data reject, so the whole move counts (sqrt(3) times uniform);
    - L > LIKELIHOOD_TIE and the run holds each input until the next frame: the inputs
      change at the frames, where the held inputs put them (a change elsewhere shows as a
      delay, which the timing part's likelihood profile places): no part;
    - otherwise, uniform (the linear hold that fits better is not where a step between
      two samples was: decision 0059's records).

    Returns the part and (L, NaN) as `found` keeps it (NaN where no likelihood was
    summed)."""
    change = run[2] - base[2]
    if not math.isfinite(change):
        return uniform, (math.nan, math.nan)
    if change < -LIKELIHOOD_TIE:
        return uniform / math.sqrt(UNIFORM_SHARE), (change, math.nan)
    if change > LIKELIHOOD_TIE and not linear:
        return np.zeros_like(uniform), (change, math.nan)
    return uniform, (change, math.nan)


def _curved(
    base: tuple[FloatArray, FloatArray, float],
    up: tuple[FloatArray, FloatArray, float],
    down: tuple[FloatArray, FloatArray, float],
) -> bool:
    """Whether the likelihood over three replays has a least between their ends."""
    c = up[2] + down[2] - 2.0 * base[2]
    return math.isfinite(c) and c > 0.0


def _profile(
    base: tuple[FloatArray, FloatArray, float],
    up: tuple[FloatArray, FloatArray, float],
    down: tuple[FloatArray, FloatArray, float],
    step: float,
    tol: float,
) -> tuple[FloatArray, tuple[float, float]]:
    """A quantity's part of the coefficients' sigma from the final pass replayed with it
    at +step and -step: the coefficients' slope in it (central difference) times how far
    it may lie from where the run took it, sqrt(s^2 + m^2). The tolerance is a prior of
    sigma tol / sqrt(3) about the configured value (uniform within +-tol); where the
    pass's likelihood over the three replays is a parabola (least at theta, curvature
    2 / sigma_theta^2; |theta| at most PROFILE_REACH tolerances), the data sharpen it:
    1 / s^2 = 1 / sigma_theta^2 + 3 / tol^2 and m = theta s^2 / sigma_theta^2. Where it
    has no curvature: s is the prior's, and m = 0 where the ends' likelihoods agree
    within LIKELIHOOD_TIE, else PROFILE_REACH tolerances towards the likelier end (the
    data put the quantity beyond both, and cannot say how far). Returns the part and
    (theta, sigma_theta), NaN where the likelihood has no least."""
    (_, _, l0), (vp, _, lp), (vm, _, lm) = base, up, down
    slope = np.abs(vp - vm) / (2.0 * step)
    prior = math.sqrt(UNIFORM_SHARE) * tol
    if not _curved(base, up, down):
        far = abs(lp - lm) > LIKELIHOOD_TIE
        least = math.copysign(PROFILE_REACH * tol, lm - lp) if far else 0.0
        return slope * math.hypot(prior, least), (math.nan, math.nan)
    curvature = (lp + lm - 2.0 * l0) / (step * step)
    spread = math.sqrt(2.0 / curvature)
    least = (lm - lp) / (2.0 * step * curvature)
    least = min(max(least, -PROFILE_REACH * tol), PROFILE_REACH * tol)
    share = 1.0 / (1.0 + (spread / prior) ** 2)  # s^2 / sigma_theta^2
    s2 = share * spread * spread
    return slope * math.sqrt(s2 + (least * share) ** 2), (least, spread)


def timing_tolerance(t: FloatArray) -> float:
    """TIMING_TOLERANCE_S, or half the record's median sample interval where longer."""
    half = 0.5 * float(np.median(np.diff(t))) if t.shape[0] > 1 else 0.0
    return max(TIMING_TOLERANCE_S, half)


def placement_tolerance(config: AircraftConfig) -> float:
    """PLACEMENT_SHARE of the mean chord, at least PLACEMENT_MIN_M [m]."""
    return max(PLACEMENT_MIN_M, PLACEMENT_SHARE * config.airframe.mean_chord_m)


def _undecided(
    est: Estimator, t: FloatArray, u: FloatArray, channels: list[int]
) -> tuple[Undecided, dict[str, float]]:
    """What the data cannot decide for sure: each quantity with its part's name, its
    key and the replay with it moved by an offset (None for a sensor position that moves
    none of the `channels` with data); then the noise floor's (an offset of 0: the
    replay at the configured noise); and the tolerances taken."""
    config = est.config

    def timing(offset: float) -> Replay:
        shifted = delayed_inputs(t, u, np.arange(2), np.full(2, offset))
        return Replay(None, shifted, profile=True)

    def placement(key: str) -> Maker:
        def make(offset: float) -> Replay:
            where = replace(config.sensors, **{key: getattr(config.sensors, key) + offset})
            return Replay(None, u, replace(config, sensors=where), profile=True)

        return make

    out: Undecided = [("timing", "input_delay_s", timing)]
    out += [
        ("placement", key, placement(key) if _moves_data(key, channels) else None)
        for key in PLACEMENT_KEYS
    ]
    tolerances = {"timing": timing_tolerance(t), "placement": placement_tolerance(config)}
    for label, key, tol, make in _propulsion(config, u):
        out.append((label, key, make))
        tolerances[label] = tol
    floor = _configured_noise_scale(est)
    if floor is not None:
        out.append(("noise_floor", "", lambda _: Replay(floor, u)))
    held = not est.tunings[FILTER_KINDS[0]].linear_inputs
    out.append(("hold", HOLD_KEY, lambda _: Replay(None, u, linear_inputs=held, profile=True)))
    return out, tolerances


HOLD_KEY = "input_hold"
"""The hold replay's key in _undecided (its likelihood change is kept apart from `found`:
StructureCheck.hold_change)."""
ONE_REPLAY_MOVES = {"noise_floor": "noise_level", "hold": "hold"}
"""The part that holds how far the estimates moved in each one-replay quantity's replay:
with the noise at the configured level rather than the level read (the noise floor's
replay; "noise_level"), and with the inputs held the other way between frames ("hold")."""

THRUST_PARTS = ("thrust", "zero_thrust_speed")
THRUST_FACTORS = ("thrust_scale", "speed_scale")
"""The propeller model's guesses whose tolerance enters the sigma (decision 0054): the
thrust (a factor on it) and the airspeed at which it vanishes (a factor on that), each
as the part's name (THRUST_PARTS) and the [propulsion] factor the replay moves
(THRUST_FACTORS)."""


def _propulsion(config: AircraftConfig, u: FloatArray) -> list[tuple[str, str, float, Maker]]:
    """The propeller model's factors with a prior (PropellerConstants' sigmas): each
    part's name, its key, its tolerance (taken as uniform within +-tol: tol = sqrt(3)
    sigma, so that the prior's sigma is the constant's) and its replay."""
    p = config.propulsion
    if p.model != "propeller":
        return []
    c = p.constants(config.airframe.air_density_kgpm3)
    out: list[tuple[str, str, float, Maker]] = []
    sigmas = (c.scale_sigma, c.speed_sigma)
    for label, key, sd in zip(THRUST_PARTS, THRUST_FACTORS, sigmas, strict=True):
        if sd <= 0.0:
            continue

        def make(offset: float, key: str = key) -> Replay:
            moved = replace(p, **{key: getattr(p, key) + offset})
            return Replay(None, u, replace(config, propulsion=moved), profile=True)

        out.append((label, key, math.sqrt(3.0) * sd, make))
    return out


def _configured_noise_scale(est: Estimator) -> FloatArray | None:
    """The variance scale from the final pass's measurement noise to the configured one,
    where the run took a reading below it on some channel (None where not)."""
    taken = np.diag(est.tunings[FILTER_KINDS[0]].R)
    configured = np.square(np.asarray(est.config.filter.measurement_sigma, float))
    if taken.shape != configured.shape or not np.any(taken < configured * (1.0 - 1e-9)):
        return None
    out: FloatArray = np.maximum(configured / taken, 1.0)
    return out


def _with_data(y: FloatArray) -> list[int]:
    """The channels the check re-weights: those with data."""
    return [i for i in range(N_OBS) if np.isfinite(y[:, i]).any()]


def _moves_data(key: str, channels: list[int]) -> bool:
    """Whether the sensor position `key` moves a channel among `channels` (with data)."""
    return any(OBS_NAMES.index(name) in channels for name in PLACEMENT_CHANNELS[key])


def runs(y: FloatArray, config: AircraftConfig | None = None) -> int:
    """How many replays of the final pass the check takes (but the noise floor's): with
    the config, its propeller's guesses' too."""
    channels = _with_data(y)
    thrust = 0 if config is None else 2 * len(_propulsion(config, y))
    placed = sum(_moves_data(key, channels) for key in PLACEMENT_KEYS)
    return 4 + 2 * placed + len(channels) + thrust
