"""The .bin's estimates against the native stream's and truth over several seeds (issue
51's target, decision 0045): each seed's NOC flight written as a DataFlash .bin, read
back (`read_log`) and run through both filters beside the simulator's own samples.
Prints, per coefficient, the largest |bin - native| in the .bin's sigma, how many seeds
lie within 1 sigma of the native stream and within 3 sigma of truth (IEKF).

    python benchmarks/log_agreement.py --seeds 5 --duration 50
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.logs.reader import read_log
from gcs_estimator.runtime.session import run_recording
from sim.formats import flight_record
from sim.formats.dataflash import write_bin
from sim.truth import simulate


def _iekf(config: AircraftConfig, t: np.ndarray, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """[coefficients x 2]: the IEKF's final estimate and sigma to trust."""
    res = run_recording(config, t, u, y, keep_history=True)
    return np.array([(c.estimate, c.sigma) for c in res.summaries["IEKF"].coefficients])


def seed_row(config: AircraftConfig, seed: int, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(|bin - native| / sigma_bin, |bin - truth| / sigma_bin) per coefficient."""
    fl = simulate(config, seed=seed)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    fr = flight_record(rec, config.link, config.airframe.air_density_kgpm3)
    path = write_bin(fr, folder / f"seed{seed}.bin")
    logged, _ = read_log(path, config)
    ours = _iekf(config, logged.t_s, logged.inputs, logged.measurements)
    native = _iekf(config, fl.t_s, fl.inputs, fl.measurements)
    sigma = ours[:, 1]
    return np.abs(ours[:, 0] - native[:, 0]) / sigma, np.abs(ours[:, 0] - fl.truth) / sigma


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--duration", type=float, default=50.0)
    args = ap.parse_args()
    config = load_config("noc_uav", [f"simulation.manoeuvre.duration_s={args.duration:g}"])
    rows_native, rows_truth = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(1, args.seeds + 1):
            z_native, z_truth = seed_row(config, seed, Path(tmp))
            rows_native.append(z_native)
            rows_truth.append(z_truth)
            print(f"seed {seed}: worst |bin - native| {z_native.max():.2f} sigma", flush=True)
    zn, zt = np.array(rows_native), np.array(rows_truth)
    print(f"\nNOC UAV, {args.duration:g} s, {args.seeds} seeds, IEKF, the .bin's sigma")
    print("| coefficient | max z native | within 1 of native | max z truth | within 3 of truth |")
    print("|---|---:|---:|---:|---:|")
    for i, name in enumerate(config.coefficient_names):
        print(
            f"| {name} | {zn[:, i].max():.2f} | {(zn[:, i] <= 1).sum()}/{args.seeds} "
            f"| {zt[:, i].max():.2f} | {(zt[:, i] <= 3).sum()}/{args.seeds} |"
        )


if __name__ == "__main__":
    main()
