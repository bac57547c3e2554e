"""Log reading speed: a large ArduPlane DataFlash log read to a Recording (target >= 50 MB/s).

    python benchmarks/read_logs.py [--mb 100] [--runs 3] [--log FILE]

Builds the log first: an ArduPlane flight of a minute written record by record (the
writer the tests check pymavlink's DFReader against: tests/logs/dataflash_files.py; IMU
twice and ATT at 50 Hz, ARSP, BARO, RCOU, AOA, GPS, XKF2 at 25 Hz), its data records
then tiled with their TimeUS shifted until the file holds --mb megabytes: one long
flight. Then times `read_log` (scan, gather, units, the frames of the Recording) --runs
times in one process, the first one loading the compiled scanner from numba's cache.
--log FILE reads a log of yours as well (optional; nothing outside the repository is
needed otherwise).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.ingest.logs import dataflash
from gcs_estimator.ingest.logs.reader import read_log
from tests.logs.dataflash_files import TRAVEL_DEG, arduplane_log, flight

TILE_S = 60.0


def build(path: Path, megabytes: float) -> Path:
    """A DataFlash log of about `megabytes`: one minute's records tiled, TimeUS shifted."""
    fl = flight(TILE_S)
    fl = replace(fl, takeoff_s=0.0, landing_s=TILE_S)
    base = arduplane_log(path, fl).read_bytes()
    log = dataflash.read_bin(path)
    lengths = {f.type: f.length for f in log.formats.values()}
    # where the header records end and the data records (all starting with TimeUS) begin
    pos, data_start, timed = 0, None, []
    while pos < len(base):
        t = base[pos + 2]
        name = next(f.name for f in log.formats.values() if f.type == t)
        if name not in ("FMT", "FMTU", "UNIT", "MULT", "PARM", "MSG", "VER"):
            data_start = pos if data_start is None else data_start
            timed.append(pos - data_start + 3)
        pos += lengths[t]
    assert data_start is not None
    head, block = base[:data_start], np.frombuffer(base[data_start:], np.uint8)
    at = np.array(timed)[:, None] + np.arange(8)
    us = block[at].copy().view("<u8").reshape(-1)
    tiles = max(1, round((megabytes * 1e6 - len(head)) / len(block)))
    with open(path, "wb") as fh:
        fh.write(head)
        for k in range(tiles):
            shifted = block.copy()
            shifted[at] = (us + np.uint64(k * TILE_S * 1e6)).view(np.uint8).reshape(-1, 8)
            fh.write(shifted.tobytes())
    return path


def timed_reads(path: Path, config: AircraftConfig, runs: int) -> tuple[list[float], list[float]]:
    """Wall-clock and CPU seconds of each read."""
    wall, cpu = [], []
    for _ in range(runs):
        start, start_cpu = time.perf_counter(), time.process_time()
        rec, _account = read_log(path, config)
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    print(f"  {len(rec):,} frames over {rec.t_s[-1] - rec.t_s[0]:,.0f} s of flight")
    return wall, cpu


def report(label: str, size: int, seconds: tuple[list[float], list[float]]) -> None:
    """Best and median of wall-clock time (what a user waits) and of this process's CPU
    time (what the reader costs, whatever else the machine runs)."""
    mb = size / 1e6
    for kind, runs in zip(("wall", "CPU"), seconds, strict=True):
        best, median = min(runs), statistics.median(runs)
        times = ", ".join(f"{s:.2f}" for s in runs)
        print(
            f"{label}, {kind}: {mb:.1f} MB in {best:.2f} s best ({mb / best:.0f} MB/s), "
            f"{median:.2f} s median ({mb / median:.0f} MB/s); runs [s]: {times}"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--mb", type=float, default=100.0, help="size of the log to build [MB]")
    ap.add_argument("--runs", type=int, default=3, choices=range(1, 21), metavar="1..20")
    ap.add_argument("--log", type=Path, help="also read this DataFlash log (optional)")
    record.add_argument(ap, "read_logs")
    args = ap.parse_args(argv)
    with record.recorded("read_logs", args.record, "Log reading: DataFlash to a Recording"):
        config = load_config("noc_uav")
        config = replace(config, airframe=replace(config.airframe, elevator_travel_deg=TRAVEL_DEG))
        with tempfile.TemporaryDirectory() as tmp:
            path = build(Path(tmp) / "long.bin", args.mb)
            size = path.stat().st_size
            print(f"built an ArduPlane log of {size / 1e6:.1f} MB ({TILE_S:g} s tiled)")
            report("read_log", size, timed_reads(path, config, args.runs))
        if args.log is not None:
            report(
                f"read_log {args.log.name}",
                args.log.stat().st_size,
                timed_reads(args.log, config, args.runs),
            )
        print("target: >= 50 MB/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
