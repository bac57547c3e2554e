"""The synchroniser's common-case shortcuts (decision 0058) keep its rules: an input
track appended to, read and pruned as the sorted-insert rule says, whatever the order the
samples come in; and the same frames when samples arrive late into a frame before the
newest, the shortcuts then not taken."""

from __future__ import annotations

import bisect
import math
import random

from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator.config import load_config
from gcs_estimator.ingest.telemetry.decode import Sample
from gcs_estimator.ingest.telemetry.sync import FRAME_WINDOW_S, InputTrack, Synchronizer
from gcs_estimator.model.channels import Channel

TIMES = st.lists(st.tuples(st.integers(0, 40), st.floats(-1.0, 1.0, allow_nan=False)), max_size=40)


def _sorted_insert(samples: list[tuple[int, float]]) -> tuple[list[float], list[float]]:
    """The track's rule stated once, plainly: by time, a repeated time's value replaced."""
    t: list[float] = []
    v: list[float] = []
    for k, value in samples:
        at = k * 0.01
        i = bisect.bisect_left(t, at)
        if i < len(t) and t[i] == at:
            v[i] = value
        else:
            t.insert(i, at)
            v.insert(i, value)
    return t, v


@settings(max_examples=200, deadline=None)
@given(samples=TIMES, cut=st.integers(0, 45), probe=st.integers(-2, 45))
def test_an_input_track_is_the_sorted_insert_of_its_samples(
    samples: list[tuple[int, float]], cut: int, probe: int
) -> None:
    track = InputTrack()
    for k, value in samples:
        track.add(k * 0.01, value)
    t, v = _sorted_insert(samples)
    assert (track.t, track.v) == (t, v)
    before = cut * 0.01
    track.prune(before)
    i = bisect.bisect_left(t, before)
    keep = i - 1 if i > 1 else 0  # all but the last sample before `before`
    assert (track.t, track.v) == (t[keep:], v[keep:])
    at = probe * 0.01
    value = track.at(at, FRAME_WINDOW_S, True)
    if not track.t or at + FRAME_WINDOW_S < track.t[0]:
        assert math.isnan(value)
    else:
        assert min(track.v) <= value <= max(track.v)


def _frame_samples(k: int) -> list[Sample]:
    """Frame k of a vehicle's 50 Hz loop: the servo outputs (the inputs), an IMU and an
    attitude sample, then an untimed airspeed."""
    t = 10.0 + 0.02 * k
    r = 1e9 + 0.02 * k
    q = 0.01 * math.sin(0.3 * k)
    return [
        Sample(1, "SERVO_OUTPUT_RAW", t, r, ((Channel.ELEVATOR, q), (Channel.POWER, 0.5))),
        Sample(1, "HIGHRES_IMU", t, r, ((Channel.AX, 0.1), (Channel.AZ, -9.8), (Channel.Q, q))),
        Sample(1, "ATTITUDE", t + 0.001, r, ((Channel.THETA, 0.05 + q),)),
        Sample(1, "VFR_HUD", None, r, ((Channel.V, 20.0 + q),)),
    ]


def _frames(samples: list[Sample]) -> list[tuple[object, ...]]:
    sync = Synchronizer(1, load_config("noc_uav").link)
    frames = [f for s in samples for f in sync.add(s)] + sync.finish()
    return [
        (f.t_vehicle_s, f.t_recv_s, f.inputs.tobytes(), f.y.tobytes(), f.inputs_known)
        for f in frames
    ]


def test_a_sample_late_into_the_frame_before_makes_the_same_frames() -> None:
    """Some frames' attitude sample arrives after the next frame has opened: the frame
    it belongs to is found by search, not as the newest (the shortcut), and the frames
    are those of the samples in order."""
    n = 300
    blocks = [_frame_samples(k) for k in range(n)]
    in_order = [s for b in blocks for s in b]
    rng = random.Random(58)
    late = sorted(rng.sample(range(n - 1), 60))
    for k in late:
        if blocks[k][2].message == "ATTITUDE":
            blocks[k + 1].insert(1, blocks[k].pop(2))
    shuffled = [s for b in blocks for s in b]
    assert shuffled != in_order
    expected = _frames(in_order)
    assert len(expected) > 250
    assert _frames(shuffled) == expected
