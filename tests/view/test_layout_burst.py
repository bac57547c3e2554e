"""A fleet coming up at once costs one layout, not one per vehicle with every vehicle
before it (80 vehicles used to send 3,240 vehicle layouts)."""

from __future__ import annotations

import numpy as np

from gcs_estimator.config import load_config
from gcs_estimator.estimation.estimator import Estimator
from gcs_estimator.model.aircraft import trim
from gcs_estimator.outputs.view.live import FLUSH_INTERVAL_S, RerunView
from gcs_estimator.outputs.view.outlets import Layout, Op, Outlet


class Collect(Outlet):
    """An outlet that keeps what it is sent."""

    def __init__(self) -> None:
        self.ops: list[Op] = []

    def send(self, op: Op) -> None:
        self.ops.append(op)

    def close(self) -> None:
        pass


def test_vehicles_appearing_together_share_one_layout() -> None:
    config = load_config("noc_uav")
    now = [0.0]
    out = Collect()
    view = RerunView([out], config, clock=lambda: now[0])
    est = Estimator(config, keep_history=False)
    tr = trim(est.model, np.array(config.truth))
    y = np.concatenate([tr.state, np.zeros(3)])
    outs = est.step(0.0, tr.inputs, y)
    for sid in range(1, 21):  # twenty vehicles within one batch
        view.step(sid, 0.01 * sid, 0.0, est.model.inputs(tr.inputs), y, outs)
    layouts = [op for op in out.ops if isinstance(op, Layout)]
    assert [len(op.system_ids) for op in layouts] == [1]  # the first at once
    now[0] += 2 * FLUSH_INTERVAL_S
    view.tick()
    layouts = [op for op in out.ops if isinstance(op, Layout)]
    assert [len(op.system_ids) for op in layouts] == [1, 20]
    view.step(21, 3.0, 0.0, est.model.inputs(tr.inputs), y, outs)
    view.flush()
    layouts = [op for op in out.ops if isinstance(op, Layout)]
    assert [len(op.system_ids) for op in layouts] == [1, 20, 21]
