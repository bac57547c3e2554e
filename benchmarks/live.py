"""Live link: latency from packet receipt to updated estimate, and load with many vehicles.

    python benchmarks/live.py --vehicles 1 --seconds 30
    python benchmarks/live.py --vehicles 10 --seconds 30 [--view]

The simulated vehicles fly in real time in their own process (`gcs-sim --vehicles N`),
streaming MAVLink 2 over UDP on loopback to one port; the ground station listens in this
process exactly as `gcs-estimator listen` does. For every frame it measures the time
from the receipt of the packet that completed the frame to the end of both filters'
update (and the view's, with --view). Prints median, p99 and max latency (target p99 <=
5 ms), and frames received against frames flown (target: none lost).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gcs_estimator.config import load_config_with
from gcs_estimator.report import final_table
from gcs_estimator.station import Station, Stop, Vehicle, listen, open_udp
from gcs_estimator.telemetry.sync import Frame
from gcs_estimator.view.outlets import LocalOutlet

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=30.0, help="flight duration")
    ap.add_argument("--config", default=str(ROOT / "configs/noc_uav.toml"))
    ap.add_argument("--view", action="store_true", help="with the Rerun view saving an .rrd")
    args = ap.parse_args(argv)
    override = f"simulation.manoeuvre.duration_s={args.seconds}"
    config = load_config_with(args.config, [override])

    complete: list[float] = []
    partial: list[float] = []

    def on_frame(v: Vehicle, frame: Frame) -> None:
        late = time.time() - frame.t_recv_s
        (complete if np.all(np.isfinite(frame.y)) else partial).append(late)

    station = Station(config, on_frame=on_frame)  # compiles the kernels before binding
    with tempfile.TemporaryDirectory() as tmp:
        if args.view:
            station.attach_view([LocalOutlet("bench", save=Path(tmp) / "live.rrd")])
        sock = open_udp("127.0.0.1", 0)
        port = sock.getsockname()[1]
        sim = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "sim.cli",
                "--config",
                args.config,
                "--set",
                override,
                "--vehicles",
                str(args.vehicles),
                "--target",
                f"127.0.0.1:{port}",
                "--speed",
                "1",
            ],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        start = time.time()
        listen(
            station, sock, Stop(), idle_exit_s=2.0, status_out=None, max_seconds=args.seconds * 3
        )
        wall = time.time() - start
        sock.close()
        sim.wait(timeout=30)
        station.finish()
        if station.view is not None:
            station.view.close(
                {sid: final_table(v.estimator) for sid, v in station.vehicles.items()}
            )

    per_vehicle = round(args.seconds * config.simulation.sample_rate_hz) + 1
    flown = per_vehicle * args.vehicles
    got = sum(v.frames for v in station.vehicles.values())
    lat = np.array(complete) * 1e3
    h = station.health
    print(
        f"{args.vehicles} vehicle(s) x {args.seconds:.0f} s at the default rates on one port"
        f"{' with the view' if args.view else ''}: {h.received} packets in {wall:.1f} s"
    )
    print(
        f"frames: {got} of {flown} flown ({flown - got} lost); packets lost {h.lost}, "
        f"out of order {h.out_of_order}, corrupt {h.corrupt}; partial frames {len(partial)}"
    )
    if len(lat):
        print(
            f"latency, packet receipt -> both filters updated, over {len(lat)} complete frames: "
            f"median {np.median(lat):.3f} ms, p99 {np.percentile(lat, 99):.3f} ms, "
            f"max {lat.max():.3f} ms (target p99 <= 5 ms)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
