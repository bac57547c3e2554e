"""Many system ids on one port: does `listen` with the default view stay small?

    python benchmarks/fleet.py [--system-ids 254] [--seconds 12]

One sender streams a short simulated flight under every system id 1..N at once (the
packets of one flight, re-encoded per id, interleaved) to `listen` with its default
view (an .rrd saved). The station estimates at most link.max_vehicles of them and counts
the rest. Prints the vehicles estimated and refused and the station's peak resident
memory (VmHWM; target: under 500 MB for 254 ids).
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import tempfile
import time
from pathlib import Path

import record  # benchmarks/record.py: the script's directory is on sys.path
from station import start_listen

from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.telemetry.mavlink import Codec, read_tlog
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--system-ids", type=int, default=254)
    ap.add_argument("--seconds", type=float, default=12.0)
    record.add_argument(ap, "fleet")
    args = ap.parse_args(argv)
    with record.recorded("fleet", args.record, "Fleet: many system ids on one port"):
        return run(args)


def _packets(seconds: float, tmp: Path) -> list[tuple[int, bytes]]:
    """(receive time [us], packet) of one simulated flight."""
    config = load_config("noc_uav", [f"simulation.manoeuvre.duration_s={seconds}"])
    fl = simulate(config, seed=1)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    path = tmp / "one.tlog"
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
    return [(r.t_recv_us, r.packet) for r in read_tlog(path)]


def _peak_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        one = _packets(args.seconds, tmp)
        station, port = start_listen(
            "--view", "save", "--idle-exit", "3", "--out", str(tmp / "out")
        )
        assert station.stderr is not None
        codecs = [Codec(sid, 1) for sid in range(1, args.system_ids + 1)]
        parse = Codec(9, 9)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        peak = 0.0
        t0 = time.monotonic()
        for k, (_, packet) in enumerate(one):
            (msg,) = parse.parse(packet)
            for codec in codecs:  # every vehicle's copy of this message
                sock.sendto(codec.pack(msg), ("127.0.0.1", port))
            if k % 200 == 0:
                peak = max(peak, _peak_mb(station.pid))
                time.sleep(0.001)  # the station's socket buffer drains
        sent = time.monotonic() - t0
        peak = max(peak, _peak_mb(station.pid))
        while station.poll() is None:  # it leaves 3 s after the last packet
            peak = max(peak, _peak_mb(station.pid))
            time.sleep(0.2)
        err = station.stderr.read()
        results = sorted((tmp / "out").glob("results_sys*.json"))
        link = json.loads(results[0].read_text())["link"] if results else {}
        rrd = tmp / "out" / "view.rrd"
        print(
            f"{args.system_ids} system ids x {args.seconds:g} s flight, "
            f"{len(one) * args.system_ids} packets sent in {sent:.1f} s; listen exit "
            f"{station.returncode}"
        )
        refused = link.get("refused_vehicles", {})
        print(
            f"estimated {len(results)} vehicles (link.max_vehicles); refused "
            f"{len(refused)} system ids, {sum(refused.values())} packets counted; "
            f"{link.get('lost', 0)} packets lost (the kernel's socket buffer: one station "
            "is one core); "
            f".rrd {rrd.stat().st_size / 1e6 if rrd.exists() else 0:.1f} MB"
        )
        print(f"listen peak resident memory: {peak:.0f} MB (target < 500 MB)")
        if station.returncode != 0:
            print(err, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
