"""A sensor position that moves no channel with data is not replayed by the structure
check (docs/decisions/0070): on a record without a vane the vane's position moves
nothing, and the check is the same without its four replays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs_estimator.config import load_config
from gcs_estimator.model.channels import OBS_NAMES
from gcs_estimator.runtime.session import RecordingSource, Session
from gcs_estimator.uncertainty import weighting
from sim.truth import simulate


def _session(vane: bool) -> Session:
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    fl = simulate(config, seed=3)
    y = fl.measurements.copy()
    if not vane:
        y[:, OBS_NAMES.index("alpha")] = np.nan
    session = Session(config)
    session.run(RecordingSource(fl.t_s, fl.inputs, y))
    return session


def _checked(
    session: Session, monkeypatch: pytest.MonkeyPatch, every: bool
) -> tuple[weighting.StructureCheck, int]:
    """The check, and how many replays it ran; `every`: each position replayed whatever
    it moves (as before decision 0070)."""
    calls = [0]
    final = weighting._final

    def counted(*args: object) -> weighting.Final:
        calls[0] += 1
        return final(*args)  # type: ignore[arg-type]

    with monkeypatch.context() as m:
        m.setattr(weighting, "_final", counted)
        if every:
            m.setattr(weighting, "_moves_data", lambda key, channels: True)
        est = session.estimators[RecordingSource.SYSTEM_ID]
        with weighting.replay_threads(1):
            return weighting.structure_check(est, *est.frame_history.arrays()), calls[0]


def _same(a: weighting.StructureCheck, b: weighting.StructureCheck) -> None:
    assert a.channels == b.channels and a.tolerances == b.tolerances
    assert list(a.parts) == list(b.parts)
    for label, part in a.parts.items():
        for kind, values in part.items():
            np.testing.assert_array_equal(values, b.parts[label][kind], err_msg=label)
    for kind in a.sigma:
        np.testing.assert_array_equal(a.sigma[kind], b.sigma[kind])
        np.testing.assert_array_equal(a.moves[kind], b.moves[kind])
    assert list(a.found) == list(b.found)
    for key, (where, spread) in a.found.items():
        other = b.found[key]
        assert where == other[0] or (math.isnan(where) and math.isnan(other[0])), key
        assert spread == other[1] or (math.isnan(spread) and math.isnan(other[1])), key


def test_without_a_vane_the_vanes_position_is_not_replayed_and_nothing_changes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    session = _session(vane=False)
    lean, lean_runs = _checked(session, monkeypatch, every=False)
    full, full_runs = _checked(session, monkeypatch, every=True)
    # The pair at +-tol, flat, then the pair PROFILE_WIDE tolerances out: four replays.
    assert full_runs - lean_runs == 4
    assert "alpha" not in lean.channels
    _same(lean, full)
    assert all(math.isnan(v) for v in lean.found["vane_x_m"])
    est = session.estimators[RecordingSource.SYSTEM_ID]
    _, _, y = est.frame_history.arrays()
    # runs() counts the +-tol pairs only: a flat position's pair PROFILE_WIDE tolerances
    # out and the timing's close pair (its likelihood far narrower than +-tol: decision
    # 0073) come on top, each where the profiles call for it (both on this record before
    # decision 0079 moved its likelihood; one since).
    assert lean_runs - weighting.runs(y) in (2, 4)


def test_with_a_vane_every_position_is_replayed(monkeypatch: pytest.MonkeyPatch) -> None:
    session = _session(vane=True)
    lean, lean_runs = _checked(session, monkeypatch, every=False)
    full, full_runs = _checked(session, monkeypatch, every=True)
    assert lean_runs == full_runs
    _same(lean, full)
