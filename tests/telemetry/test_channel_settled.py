"""A message whose channels have settled partly on other messages (ATTITUDE: its pitch
rate from an IMU) takes ChannelSources' remembered path (decision 0064): the same
samples, notes, drops and report as judging every value, whatever the messages, rates,
missing values and receive-time order."""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator.ingest.telemetry.channel_sources import ChannelSources
from gcs_estimator.ingest.telemetry.decode import Sample
from gcs_estimator.model.channels import Channel

CARRIES: dict[str, tuple[tuple[Channel, ...], tuple[str, ...]]] = {
    "HIGHRES_IMU": ((Channel.AX, Channel.AZ, Channel.Q), ()),
    "SCALED_IMU2": ((Channel.AX, Channel.AZ, Channel.Q), ()),
    "ATTITUDE": (
        (Channel.THETA, Channel.Q, Channel.PHI, Channel.ROLL_RATE, Channel.YAW_RATE),
        ("phi", "p", "r"),
    ),
    "VFR_HUD": ((Channel.V,), ("vz",)),
    "GLOBAL_POSITION_INT": ((Channel.HDOT,), ("vz", "vn", "ve", "vd")),
}
MESSAGES = tuple(CARRIES)


class _EveryValue(ChannelSources):
    """The rule itself: every value judged (nothing remembered)."""

    def _remember(self, shape: Any, message: str) -> None:
        return None


def _sample(message: str, t: float, missing: int) -> Sample:
    chans, aux = CARRIES[message]
    values = tuple((ch, float(i)) for i, ch in enumerate(chans) if not (missing >> i) & 1)
    kept_aux = tuple((a, 1.0) for i, a in enumerate(aux) if not (missing >> (i + 5)) & 1)
    return Sample(1, message, t, t, values, None, kept_aux)


STEP = st.tuples(
    st.sampled_from(MESSAGES),
    st.floats(-0.3, 0.6, allow_nan=False),
    st.one_of(st.just(0), st.just(0), st.just(0), st.integers(0, 255)),
)


def _both(steps: list[tuple[str, float, int]]) -> tuple[ChannelSources, ChannelSources]:
    fast, rule = ChannelSources(1), _EveryValue(1)
    t = 1000.0
    for message, dt, missing in steps:
        t += dt
        sample = _sample(message, t, missing)
        assert fast.choose(sample) == rule.choose(sample)
        assert fast.notes == rule.notes
    return fast, rule


@settings(max_examples=300, deadline=None)
@given(steps=st.lists(STEP, max_size=300))
def test_remembered_values_are_the_values_judged(steps: list[tuple[str, float, int]]) -> None:
    fast, rule = _both(steps)
    assert fast.dropped == rule.dropped
    assert fast.report() == rule.report()


def test_a_px4_stream_remembers_attitude_and_still_switches() -> None:
    """HIGHRES_IMU at 50 Hz gives q; ATTITUDE at 50 Hz passes its other values by the
    remembered path; ATTITUDE at 200 Hz later takes q over, in both alike."""
    steps: list[tuple[str, float, int]] = []
    for _ in range(500):
        steps += [("HIGHRES_IMU", 0.01, 0), ("ATTITUDE", 0.01, 0)]
    for _ in range(2000):
        steps.append(("ATTITUDE", 0.005, 0))
        if len(steps) % 8 == 0:
            steps.append(("HIGHRES_IMU", 0.0, 0))
    fast, rule = _both(steps)
    assert fast._partly  # the path under test was taken
    assert fast.source("q") == rule.source("q") == "ATTITUDE"
    assert fast.report() == rule.report()
    assert fast.dropped == rule.dropped > 0
