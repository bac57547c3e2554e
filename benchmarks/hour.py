"""A long flight over UDP into `listen`, then `replay` of its recording: same estimates?

The simulated vehicle streams to `listen`; `replay` of what `listen` recorded must give
the same estimates.

    python benchmarks/hour.py [--minutes 60] [--speed 20] [--boot-s 4000]

The vehicle has been up --boot-s seconds when the flight starts, so its 32-bit
SERVO_OUTPUT_RAW clock wraps during the flight (at 4295 s). The manoeuvre repeats every
minute, as in benchmarks/replay.py. Prints frames, link and clock counters of both runs,
whether every estimate and sigma is identical, and the wall times.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import record  # benchmarks/record.py: the script's directory is on sys.path
from flights import repeated_manoeuvre
from station import BIN, ROOT, start_listen

LISTEN = ("--idle-exit", "5", "--view", "off", "--out")


def manoeuvre(minutes: int) -> list[str]:
    return [arg for s in repeated_manoeuvre(minutes) for arg in ("--set", s)]


def _listen(out: Path, sets: list[str], args: argparse.Namespace) -> tuple[int, float]:
    station, port = start_listen(*sets, *LISTEN, str(out))
    assert station.stderr is not None
    pace = ["--speed", str(args.speed), "--boot-s", str(args.boot_s)]
    t0 = time.monotonic()
    subprocess.run(
        [sys.executable, "-m", "sim.cli", *sets, "--target", f"127.0.0.1:{port}", *pace],
        cwd=ROOT,
        check=True,
        stderr=subprocess.DEVNULL,
    )
    station.communicate(timeout=600)
    return station.returncode, time.monotonic() - t0


def _replay(tlog: Path, out: Path, sets: list[str]) -> tuple[int, float]:
    t0 = time.monotonic()
    proc = subprocess.run(
        [
            str(BIN / "gcs-estimator"),
            "replay",
            str(tlog),
            *sets,
            "--view",
            "off",
            "--out",
            str(out),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    return proc.returncode, time.monotonic() - t0


def _summary(name: str, res: dict[str, Any], status: int, wall: float) -> None:
    link = res["link"]
    clock = link["vehicles"]["1"]
    print(
        f"{name:7s}: exit {status}, {res['diagnostics']['frames']} frames in {wall:.0f} s; "
        f"packets {link['received']}, lost {link['lost']}, corrupt {link['corrupt']}; clock "
        f"{clock['clock_wraps']} wraps, {clock['clock_resets']} resets, "
        f"{clock['time_jumps']} jumps"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--minutes", type=int, default=60)
    ap.add_argument("--speed", type=float, default=20.0, help="the vehicle's pace")
    ap.add_argument("--boot-s", type=float, default=4000.0)
    record.add_argument(ap, "hour")
    args = ap.parse_args(argv)
    with record.recorded("hour", args.record, "A long flight: listen over UDP, then replay"):
        return run(args)


def run(args: argparse.Namespace) -> int:
    sets = manoeuvre(args.minutes)
    with tempfile.TemporaryDirectory() as tmp:
        live, again = Path(tmp) / "live", Path(tmp) / "replay"
        status_live, wall_live = _listen(live, sets, args)
        status_replay, wall_replay = _replay(live / "telemetry.tlog", again, sets)
        a = json.loads((live / "results_sys1.json").read_text())
        b = json.loads((again / "results_sys1.json").read_text())
    print(
        f"flight {args.minutes} min at {args.speed:g}x, vehicle up {args.boot_s:g} s at the "
        "start (its 32-bit servo clock wraps at 4295 s)"
    )
    _summary("listen", a, status_live, wall_live)
    _summary("replay", b, status_replay, wall_replay)
    for kind in ("EKF", "IEKF"):
        ea, eb = a["filters"][kind]["estimates"], b["filters"][kind]["estimates"]
        same = all(ea[n]["estimate"] == eb[n]["estimate"] and ea[n]["sigma"] == eb[n]["sigma"]
                   for n in ea)  # fmt: skip
        print(f"{kind:4s}: replay {'identical to' if same else 'DIFFERS from'} listen")
    return 0


if __name__ == "__main__":
    sys.exit(main())
