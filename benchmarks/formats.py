"""How long the simulator takes to write a flight as the autopilots do (docs/decisions/0040).

    python benchmarks/formats.py [--minutes 10] [--asked]

Flies one NOC UAV flight of that length, then times each writer on it: the DataFlash
.bin and the PX4 .ulg at the default and fast logging rates, and (with --asked) the
ArduPlane stream as `gcs-sim --autopilot arduplane --asked --tlog` sends it at speed 0
(every packet packed by pymavlink and sent over UDP to a loopback port nobody reads).
Prints seconds and file sizes; writes nothing to keep.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording
from sim.formats import flight_record
from sim.formats.ardupilot import ArduPlaneVehicle, parse_rates
from sim.formats.dataflash import write_bin
from sim.formats.ulog import write_ulg
from sim.truth import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--asked", action="store_true", help="also time the ArduPlane stream")
    args = ap.parse_args()
    config = load_config("noc_uav", [f"simulation.manoeuvre.duration_s={args.minutes * 60}"])
    fl = simulate(config, seed=1)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    fr = flight_record(rec, config.link, config.airframe.air_density_kgpm3)
    print(f"{args.minutes:g}-minute flight, {len(fr)} samples")
    with tempfile.TemporaryDirectory() as tmp:
        for fast in (False, True):
            for suffix, write in ((".bin", write_bin), (".ulg", write_ulg)):
                start = time.perf_counter()
                path = write(fr, Path(tmp) / f"flight_{fast}{suffix}", fast)
                took = time.perf_counter() - start
                size = path.stat().st_size / 1e6
                rates = "fast" if fast else "default"
                print(f"  {suffix} {rates:7s} rates: {took:6.2f} s  {size:5.1f} MB")
        if args.asked:
            vehicle = ArduPlaneVehicle(
                rec,
                config.link,
                ("127.0.0.1", 9),
                speed=0.0,
                tlog=Path(tmp) / "flight.tlog",
                asked_rates=parse_rates([], config.link.rate_hz, True),
            )
            start = time.perf_counter()
            stats = vehicle.run()
            took = time.perf_counter() - start
            print(f"  ArduPlane --asked .tlog: {took:6.2f} s  {stats.sent} packets")


if __name__ == "__main__":
    main()
