"""The filters' CPU per log, frame by frame and in blocks (decision 0065).

    python benchmarks/filter_blocks.py [--seconds 600] [--rounds 3] [--blocks 0 256]

Simulates one flight of the NOC UAV (.tlog, the simulator's native message set), decodes
its frames once, then runs a session over them (both filters, the restarts, the results
and their summaries; the structure check where the flight is within
filter.structure_check_max_frames) once per block size (0: frame by frame), by the CPU
time charged to this process (threads included), the least of --rounds after a warm-up;
the structure check's own share beside it. Each block size's estimates are compared with
the first's (the final beliefs, bit for bit).
"""

from __future__ import annotations

import argparse
import io
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from fleet_dask import _overrides, write_flight

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.frames import Frame
from gcs_estimator.runtime.logs import reader_of
from gcs_estimator.runtime.session import Session
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.weighting import StructureCheck


class Frames:
    """A source of frames decoded before."""

    def __init__(self, frames: list[Frame]) -> None:
        self.list = frames

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        yield from self.list

    def link_stats(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass


class TimedSession(Session):
    """A session whose structure check's CPU time is added up."""

    check_s = 0.0

    def structure_check(self, system_id: int, est: Any, checked: int = 0) -> StructureCheck:
        c0 = time.process_time()
        try:
            return super().structure_check(system_id, est, checked)
        finally:
            self.check_s += time.process_time() - c0


def run(config: AircraftConfig, frames: list[Frame], block: int) -> tuple[float, float, Session]:
    """CPU seconds of one session over the frames, of its structure check, and the session."""
    session = TimedSession(config, block_frames=block)
    c0 = time.process_time()
    session.run(Frames(frames))
    return time.process_time() - c0, session.check_s, session


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--blocks", type=int, nargs="+", default=[0, 256])
    args = ap.parse_args(argv)
    config = load_config("noc_uav", _overrides(args.seconds))
    with tempfile.TemporaryDirectory() as tmp_dir:
        path = Path(tmp_dir) / "flight.tlog"
        write_flight(config, path, 100)
        source, _ = reader_of(path)(path, config, io.StringIO())
        frames = [f for f in source.frames(Stop()) if f is not None]
    print(f"{args.seconds:g} s flight, {len(frames)} frames; load average {os.getloadavg()[0]:.1f}")
    first: Session | None = None
    for block in args.blocks:
        run(config, frames, block)  # warm-up
        best = min((run(config, frames, block) for _ in range(args.rounds)), key=lambda r: r[0])
        cpu, check, session = best
        same = ""
        if first is None:
            first = session
        else:
            same = ", estimates identical" if _same(first, session) else ", ESTIMATES DIFFER"
        label = f"blocks of {block}" if block else "frame by frame"
        print(
            f"  {label:<16} {cpu:6.2f} s CPU ({1e6 * cpu / len(frames):.1f} µs a frame), "
            f"the structure check {check:.2f} s{same}"
        )
    print(f"load average at the end {os.getloadavg()[0]:.1f}")
    return 0


def _same(a: Session, b: Session) -> bool:
    """Whether both sessions' filters ended on the same beliefs, bit for bit."""
    for sid, est in a.estimators.items():
        for kind, lane in est.states.items():
            other = b.estimators[sid].states[kind]
            if lane is None or other is None:
                return lane is other
            if not (np.array_equal(lane.x, other.x) and np.array_equal(lane.P, other.P)):
                return False
    return True


if __name__ == "__main__":
    sys.exit(main())
