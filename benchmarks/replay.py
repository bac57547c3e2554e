"""Replay speed: a long simulated flight's .tlog through decode, sync and both filters.

    python benchmarks/replay.py --minutes 10

Prints messages/s, frames/s and the multiple of real time (target >= 100x), for the
whole pipeline and for decoding alone.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from gcs_estimator.config import load_config_with
from gcs_estimator.flightdata import Recording
from gcs_estimator.station import Station, replay
from gcs_estimator.telemetry.mavlink import Decoder, read_tlog
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--config", default="configs/noc_uav.toml")
    args = ap.parse_args(argv)
    seconds = args.minutes * 60
    # The manoeuvre repeats its multisteps and pulses every minute so the filters work
    # on real excitation throughout.
    starts = [m * 60 + s for m in range(int(args.minutes)) for s in (2.0, 6.0)]
    pulses = [m * 60 + s for m in range(int(args.minutes)) for s in (12.0, 30.0)]
    config = load_config_with(
        args.config,
        [
            f"simulation.manoeuvre.duration_s={seconds}",
            f"simulation.manoeuvre.multistep_starts_s={starts}",
            f"simulation.manoeuvre.pulse_starts_s={pulses}",
            f"simulation.manoeuvre.pulse_durations_s={[2.0] * len(pulses)}",
            f"simulation.manoeuvre.pulse_amplitudes_deg={[-3.0, 3.0] * int(args.minutes)}",
        ],
    )
    fl = simulate(config, seed=1)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.tlog"
        rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
        SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
        records = list(read_tlog(path))
        n = len(records)

        dec = Decoder()
        t0 = time.perf_counter()
        for r in records:
            dec.decode(r.packet)
        t_decode = time.perf_counter() - t0

        station = Station(config)  # kernels compiled here, outside the timing
        t0 = time.perf_counter()
        replay(station, records)
        station.finish()
        t_all = time.perf_counter() - t0
    frames = station.vehicles[1].frames
    print(f"flight {seconds:.0f} s, {n} packets, {frames} frames (both filters each frame)")
    print(f"decode only : {n / t_decode:,.0f} messages/s")
    print(
        f"full replay : {t_all:.2f} s, {n / t_all:,.0f} messages/s, {frames / t_all:,.0f} "
        f"frames/s, {seconds / t_all:.0f}x real time (target >= 100x)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
