"""The synchroniser: frames by the vehicle's clock, inputs by their own times.

Samples are made directly (decode is tested in test_units.py); a "tick" is what the
simulated vehicle sends at one time: the servo output first, then the observations.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator.config import LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.telemetry.decode import WRAP_US32_S, Sample
from gcs_estimator.ingest.telemetry.sync import Synchronizer
from gcs_estimator.model.channels import N_INPUTS, N_OBS, Channel

LINK = LinkConfig()
OBS = {"v": 24.0, "alpha": 0.05, "theta": 0.05, "q": 0.0, "qdot": 0.0, "ax": 0.1, "az": -9.8}
DT = 0.02


def _sample(
    t: float | None, t_recv: float = 0.0, *, message: str = "test", **values: float
) -> Sample:
    wrap = WRAP_US32_S if message == "SERVO_OUTPUT_RAW" else None
    vals = tuple((Channel[k.upper()], v) for k, v in values.items())
    return Sample(1, message, t, t_recv, vals, wrap)


def _obs(t: float | None, t_recv: float, name: str, value: float) -> Sample:
    return Sample(1, "test", t, t_recv, ((Channel[name.upper()], value),))


def _servo(t: float, elevator: float, t_recv: float = 0.0) -> Sample:
    return _sample(t, t_recv, message="SERVO_OUTPUT_RAW", elevator=elevator, power=0.3)


def _tick(t: float, elevator: float = 0.0, t_recv: float = 0.0, **obs: float) -> list[Sample]:
    """One time's samples: servo output, then each observation (OBS unless given)."""
    values = {**OBS, **obs}
    return [_servo(t, elevator, t_recv)] + [
        _obs(t, t_recv, k, v) for k, v in values.items() if not math.isnan(v)
    ]


def _feed(sync: Synchronizer, samples: Sequence[Sample]) -> list[Frame]:
    out: list[Frame] = []
    for s in samples:
        out += sync.add(s)
    return out


def _flight(n: int, t0: float = 1.0) -> list[list[Sample]]:
    """n ticks with an elevator that changes every tick."""
    return [_tick(t0 + k * DT, elevator=0.01 * k) for k in range(n)]


def test_a_frame_goes_once_complete_with_its_inputs_at_its_time() -> None:
    sync = Synchronizer(1, LINK)
    samples = _tick(1.0, elevator=0.01)
    assert _feed(sync, samples[:-1]) == []
    (frame,) = sync.add(samples[-1])
    # No air density came: NaN, and the estimator flies the airframe's constant.
    # No air density came: NaN, and the estimator flies the airframe's constant; no bank,
    # roll or yaw rate either (wings level).
    np.testing.assert_array_equal(frame.inputs, [0.01, 0.3, *[np.nan] * (N_INPUTS - 2)])
    # No climb rate came: h_dot missing.
    np.testing.assert_array_equal(frame.y, [*OBS.values(), np.nan])
    assert frame.t_vehicle_s == 1.0 and not frame.clock_reset
    assert sync.stats.frames == 1 and sync.stats.partial_frames == 0


def test_a_lost_input_sample_is_interpolated_and_changes_no_other_frame() -> None:
    ticks = _flight(6)
    for hold, expected in ((True, 0.02), (False, 0.01)):
        sync = Synchronizer(1, LINK, linear_inputs=hold)
        lossy = [s for k, tick in enumerate(ticks) for s in tick if not (k == 2 and s is tick[0])]
        frames = _feed(sync, lossy) + sync.finish()
        elev = [f.inputs[0] for f in frames]
        assert len(frames) == 6
        # Tick 2's servo sample is lost: interpolated between 0.01 and 0.03, or held.
        np.testing.assert_allclose(elev, [0.0, 0.01, expected, 0.03, 0.04, 0.05], atol=1e-12)


def test_inputs_sent_slower_than_the_sensors_are_known_and_a_lost_one_is_a_guess() -> None:
    """Servo outputs at a quarter of the sensors' rate (an ArduPlane link at its default
    stream rates): the frames between two servo samples take the input interpolated, and
    it is the data's own resolution, not a guess; a servo sample lost while the elevator
    changed makes the frames around it guesses, and only those."""
    every = 4
    samples: list[Sample] = []
    for k in range(60):
        t = 1.0 + k * DT
        lost = k == 32
        if k % every == 0 and not lost:
            samples.append(_servo(t, 0.01 * k))
        samples += [_obs(t, 0.0, name, value) for name, value in OBS.items()]
    sync = Synchronizer(1, LINK)
    frames = _feed(sync, samples) + sync.finish()
    assert len(frames) == 60
    guessed = [k for k, f in enumerate(frames) if not f.inputs_known]
    # Before three spacings are known every gap counts as a lost sample (frames 1-3 and
    # 5-7, after the first and the second servo samples); then the frames between the
    # samples either side of the lost one (28 and 36), the lost one's own frame too.
    assert guessed == [1, 2, 3, 5, 6, 7, *range(29, 36)]
    assert sync.stats.inputs_guessed == len(guessed)
    # Interpolated between the servo samples, the lost one's too.
    np.testing.assert_allclose([f.inputs[0] for f in frames[:57]], 0.01 * np.arange(57), atol=1e-12)


def test_a_step_between_slow_input_samples_is_a_guess_a_usual_move_is_not() -> None:
    """Servo outputs at a quarter of the sensors' rate. An elevator that moves a little at
    every sample (an autopilot's) is known between them; one that holds and then jumps
    (a doublet) is a guess between the samples around the jump only (STEP_CHANGES), and
    so is a move far beyond the elevator's usual one."""
    every = 4

    def frames_of(elevator: Sequence[float]) -> list[Frame]:
        samples: list[Sample] = []
        for k in range(len(elevator) * every):
            t = 1.0 + k * DT
            if k % every == 0:
                samples.append(_servo(t, elevator[k // every]))
            samples += [_obs(t, 0.0, name, value) for name, value in OBS.items()]
        sync = Synchronizer(1, LINK)
        return _feed(sync, samples) + sync.finish()

    early = [1, 2, 3, 5, 6, 7]  # before three spacings and changes are known
    # An autopilot's elevator: small moves of either sign, one of them ten times as large.
    moves = [0.001 * (1 + k % 3) * (-1) ** k for k in range(30)]
    moves[20] = 0.02
    smooth = frames_of(list(np.cumsum(moves)))
    guessed = [k for k, f in enumerate(smooth) if not f.inputs_known]
    assert guessed == [*early, 77, 78, 79], guessed  # between samples 19 and 20
    # A doublet: the elevator holds, steps at sample 10 and back at sample 20.
    doublet = [0.0] * 10 + [0.05] * 10 + [0.0] * 10
    frames = frames_of(doublet)
    guessed = [k for k, f in enumerate(frames) if not f.inputs_known]
    assert guessed == [37, 38, 39, 77, 78, 79], guessed  # around samples 10 and 20


def test_a_lost_observation_leaves_only_its_own_channel_missing() -> None:
    sync = Synchronizer(1, LINK)
    ticks = _flight(20)
    lost = ticks[3][2]  # tick 3's alpha
    frames = _feed(sync, [s for tick in ticks for s in tick if s is not lost]) + sync.finish()
    assert len(frames) == 20
    assert np.isnan(frames[3].y[Channel.ALPHA])
    assert all(np.isfinite(f.y[: len(OBS)]).all() for k, f in enumerate(frames) if k != 3)
    assert all(np.isnan(f.y[Channel.HDOT]) for f in frames)  # no climb rate sent
    np.testing.assert_allclose([f.inputs[0] for f in frames], 0.01 * np.arange(20), atol=1e-12)
    assert sync.stats.partial_frames == 1


def test_samples_arriving_late_within_the_window_join_their_own_frame() -> None:
    ticks = _flight(10)
    in_order = _feed(Synchronizer(1, LINK), [s for t in ticks for s in t])
    # Tick 4's observations arrive after tick 6's.
    shuffled = [s for k, t in enumerate(ticks) for s in t if k != 4]
    at = sum(len(t) for t in ticks[:6]) - len(ticks[4])
    shuffled[at:at] = ticks[4]
    late = _feed(Synchronizer(1, LINK), shuffled)
    assert [f.t_vehicle_s for f in late] == [f.t_vehicle_s for f in in_order]
    for a, b in zip(late, in_order, strict=True):
        np.testing.assert_array_equal(a.y, b.y)
        np.testing.assert_array_equal(a.inputs, b.inputs)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(0.0, 2.0), min_size=1, max_size=40), st.integers(0, 40))
def test_receive_times_and_stalls_never_change_the_frames(stalls: list[float], lost: int) -> None:
    """The same samples received with any stalls (and one lost) make the same frames."""
    ticks = _flight(40)
    samples = [s for t in ticks for s in t]
    del samples[1 + lost * 3 % (len(samples) - 1)]  # never the first input

    def frames(recv: Sequence[float]) -> list[list[float]]:
        sync = Synchronizer(1, LINK)
        received = [s._replace(t_recv_s=r) for s, r in zip(samples, recv, strict=True)]
        out = _feed(sync, received)
        out += sync.finish()
        return [[f.t_vehicle_s, *f.inputs, *f.y] for f in out]

    steady = [100.0 + k * 0.003 for k in range(len(samples))]
    stalled = list(steady)
    for k, pause in enumerate(stalls):
        at = (k * 37) % len(samples)
        stalled[at:] = [r + pause for r in stalled[at:]]
    a, b = np.array(frames(steady)), np.array(frames(stalled))
    assert a.shape == (40, 1 + N_INPUTS + N_OBS)
    np.testing.assert_array_equal(a, b)


def test_a_far_future_time_is_dropped_and_a_real_gap_is_taken() -> None:
    sync = Synchronizer(1, LINK)
    ticks = _flight(10)
    samples = [s for t in ticks[:5] for s in t]
    samples.append(_sample(1e5, alpha=0.3))  # one valid packet with an absurd time
    samples += [s for t in ticks[5:] for s in t]
    frames = _feed(sync, samples)
    assert [round(f.t_vehicle_s, 6) for f in frames] == [round(1.0 + k * DT, 6) for k in range(10)]
    assert sync.stats.implausible_times == 1 and sync.stats.time_jumps == 0
    # The vehicle goes on 30 s later: a gap, taken once three samples agree.
    after = [s for t in _flight(5, t0=31.0) for s in t]
    frames = _feed(sync, after) + sync.finish()
    assert sync.stats.time_jumps == 1
    assert [f.t_vehicle_s for f in frames] == [31.0 + k * DT for k in range(5)]
    assert all(not f.clock_reset for f in frames)


def test_a_reboot_is_taken_once_confirmed_and_a_stale_copy_is_not_one() -> None:
    sync = Synchronizer(1, LINK)
    frames = _feed(sync, [s for t in _flight(100, t0=10.0) for s in t])
    # A stale copy of a sample from 5 s ago: not a reboot.
    frames += _feed(sync, _tick(7.0)[1:2])
    frames += _feed(sync, [s for t in _flight(5, t0=12.0) for s in t])
    assert sync.stats.clock_resets == 0 and sync.stats.late_samples == 1
    # The vehicle reboots: its clock starts again near zero.
    after = _feed(sync, [s for t in _flight(5, t0=0.5) for s in t]) + sync.finish()
    assert sync.stats.clock_resets == 1
    assert [f.clock_reset for f in after] == [True, False, False, False, False]
    assert after[0].t_vehicle_s == 0.5
    assert [f.inputs[0] for f in after] == [0.0, 0.01, 0.02, 0.03, 0.04]
    assert len(frames) == 105


def test_a_32_bit_vehicle_clock_wraps_without_a_break() -> None:
    sync = Synchronizer(1, LINK)
    t0 = WRAP_US32_S - 0.5
    samples: list[Sample] = []
    for k in range(50):
        t = t0 + k * DT
        # The servo output's 32-bit time wraps; the observations' 64-bit times do not.
        tick = _tick(t, elevator=0.01 * k)
        tick[0] = _servo(t % WRAP_US32_S, 0.01 * k)
        samples += tick
    frames = _feed(sync, samples) + sync.finish()
    assert len(frames) == 50 and sync.stats.clock_wraps == 1
    assert sync.stats.clock_resets == 0 and sync.stats.time_jumps == 0
    np.testing.assert_allclose([f.inputs[0] for f in frames], 0.01 * np.arange(50), atol=1e-12)


def test_a_32_bit_clock_that_wrapped_before_the_first_sample_is_aligned_by_whole_wraps() -> None:
    """Up 2 hours: the servo output's time wrapped once before the station heard it (its
    sample comes first in every tick); the frames and inputs are those of a vehicle whose
    clocks agree."""
    frames_by_uptime = {}
    for uptime in (10.0, 7200.0):
        sync = Synchronizer(1, LINK)
        samples: list[Sample] = []
        for k in range(50):
            t = uptime + k * DT
            tick = _tick(t, elevator=0.01 * k)
            tick[0] = _servo(t % WRAP_US32_S, 0.01 * k)
            samples += tick
        frames = _feed(sync, samples) + sync.finish()
        assert sync.stats.clock_resets == sync.stats.time_jumps == sync.stats.late_samples == 0
        frames_by_uptime[uptime] = frames
    young, old = frames_by_uptime[10.0], frames_by_uptime[7200.0]
    assert len(old) == len(young) == 50
    np.testing.assert_allclose(
        [f.t_vehicle_s - 7190.0 for f in old], [f.t_vehicle_s for f in young]
    )
    np.testing.assert_allclose([f.inputs for f in old], [f.inputs for f in young], atol=1e-12)


def test_only_a_wrapping_clock_is_taken_as_it_is() -> None:
    """A vehicle whose only timed message is the servo output: its samples are not held
    for ever waiting for another clock."""
    sync = Synchronizer(1, LINK)
    obs = tuple((Channel[k.upper()], v) for k, v in OBS.items())
    samples = []
    for k in range(200):
        t = 100.0 + k * DT
        samples += [_servo(t, 0.001 * k), Sample(1, "OBS32", t, 0.0, obs, WRAP_US32_S)]
    frames = _feed(sync, samples) + sync.finish()
    assert len(frames) == 200 and sync.stats.late_samples == 0
    np.testing.assert_allclose([f.t_vehicle_s for f in frames], 100.0 + DT * np.arange(200))
    np.testing.assert_allclose([f.inputs[0] for f in frames], 0.001 * np.arange(200))


def test_untimed_samples_a_channel_never_sent_and_frames_before_inputs() -> None:
    sync = Synchronizer(1, LINK)
    # No inputs yet: nothing to estimate with.
    assert _feed(sync, [_obs(0.5, 0.0, k, v) for k, v in OBS.items()]) == []
    assert sync.finish() == [] and sync.stats.waiting_for_inputs == 1
    frames: list[Frame] = []
    for k in range(20):
        t = 1.0 + k * DT
        # VFR_HUD (airspeed) has no time: it joins the newest frame. q-dot is never sent.
        tick = [*_tick(t, v=math.nan, qdot=math.nan), _sample(None, v=20.0 + k)]
        got = _feed(sync, tick)
        if k >= 15:
            # Once the vehicle is known not to send q-dot, a frame goes at its last sample.
            assert len(got) == 1 and got[0].t_vehicle_s == t
        frames += got
    frames += sync.finish()
    assert [f.y[Channel.V] for f in frames] == [20.0 + k for k in range(20)]
    assert sync.stats.partial_frames <= 3
