"""Seconds from starting `gcs-estimator listen` to its listening line, and to stopping.

    ./run bench startup [--runs 5] [--cold]

Each run starts the station as its own process on a free loopback port with the view off
and a fresh output folder, times the line that says where it listens, then stops it with
Ctrl-C (SIGINT) and times how long it takes to close its link and exit (no vehicle
came, so there are no results to write).
Warm: the compiled kernels come from numba's cache, as on every start after the first.
`--cold` gives each run an empty cache of its own (NUMBA_CACHE_DIR), as a fresh clone's
first start: the kernels compile then.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import record  # benchmarks/record.py: the script's directory is on sys.path
from station import BIN, ROOT

TARGET_WARM_S = 3.0
"""The listening line within this many seconds when the cache is warm (issue target)."""


def one_start(cold: bool) -> tuple[float, float]:
    """(seconds to the listening line, seconds from SIGINT to exit) of one station."""
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ)
        if cold:
            env["NUMBA_CACHE_DIR"] = str(Path(tmp) / "numba")
        args = [str(BIN / "gcs-estimator"), "listen", "udpin:127.0.0.1:0", "--view", "off"]
        args += ["--out", str(Path(tmp) / "out")]
        t0 = time.perf_counter()
        station = subprocess.Popen(
            args, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        assert station.stderr is not None
        listening = None
        for line in station.stderr:
            if line.startswith("listening on"):
                listening = time.perf_counter() - t0
                break
        if listening is None:
            raise SystemExit(f"listen did not start: {station.stderr.read()}")
        t1 = time.perf_counter()
        station.send_signal(signal.SIGINT)
        rest = station.stderr.read()
        code = station.wait()
        stopped = time.perf_counter() - t1
        # No vehicle came, so listen says that nothing was estimated (exit status 1): a
        # graceful stop all the same.
        if code != 0 and "nothing was estimated" not in rest:
            raise SystemExit(f"listen did not stop cleanly after Ctrl-C: {rest}")
        return listening, stopped


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--cold", action="store_true", help="an empty compile cache for each run")
    record.add_argument(ap, "startup")
    args = ap.parse_args(argv)
    name = args.record if not (args.cold and args.record == "startup") else "startup_cold"
    with record.recorded("startup", name, "Station start-up: to the listening line, and stop"):
        if not args.cold:
            one_start(False)  # the cache filled, whatever ran before
        starts, stops = zip(*(one_start(args.cold) for _ in range(args.runs)), strict=True)
        kind = "cold (empty compile cache)" if args.cold else "warm (compile cache filled)"
        print(f"{args.runs} starts of `gcs-estimator listen` with the view off, {kind}:\n")
        print("| | min | median | max |")
        print("|---|---|---|---|")
        for label, v in (("to the listening line [s]", starts), ("Ctrl-C to exit [s]", stops)):
            print(f"| {label} | {min(v):.2f} | {statistics.median(v):.2f} | {max(v):.2f} |")
        if not args.cold:
            ok = "met" if statistics.median(starts) <= TARGET_WARM_S else "not met"
            print(f"\ntarget: the listening line within {TARGET_WARM_S:.0f} s warm: {ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
