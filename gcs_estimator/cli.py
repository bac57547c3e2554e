"""Command line: `gcs-estimator COMMAND ...`; main(argv) -> exit status, callable from tests."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gcs_estimator.config import AircraftConfig, ConfigError, load_config_with
from gcs_estimator.estimator import Estimator
from gcs_estimator.flightdata import FlightDataError, Recording, load_csv, load_hfb320
from gcs_estimator.metrics import summarise
from gcs_estimator.report import config_truth, markdown_table, write_results

DEFAULT_CONFIG = "configs/noc_uav.toml"


def _common(p: argparse.ArgumentParser, config_default: str = DEFAULT_CONFIG) -> None:
    p.add_argument("--config", default=config_default, help="aircraft TOML (default: %(default)s)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set filter.iterations=3 (repeatable)",
    )
    p.add_argument("--out", default="out", help="directory for results (default: %(default)s)")
    p.add_argument(
        "--backend",
        choices=("fast", "reference"),
        default="fast",
        help="compiled filter kernels or the plain numpy reference path",
    )


def _run_recording(
    config: AircraftConfig,
    rec: Recording,
    truth: np.ndarray | None,
    args: argparse.Namespace,
    label: str,
) -> int:
    est = Estimator(config, backend=args.backend)
    start = time.perf_counter()
    n = len(rec)
    next_report = 0.0
    for i in range(n):
        est.step(float(rec.t_s[i]), rec.inputs[i], rec.measurements[i])
        frac = (i + 1) / n
        if frac >= next_report and sys.stderr.isatty():
            print(f"\r{label}: {frac * 100:5.1f} % of {n} frames", end="", file=sys.stderr)
            next_report += 0.05
    elapsed = time.perf_counter() - start
    if sys.stderr.isatty():
        print(file=sys.stderr)
    summaries = summarise(est, truth)
    print(
        f"\n{config.airframe.name}: {label}, {n} frames in {elapsed:.2f} s "
        f"({n / max(elapsed, 1e-9):,.0f} frames/s, both filters)\n"
    )
    print(markdown_table(summaries, config.truth_label))
    paths = write_results(Path(args.out), est, truth, rec.measurements)
    print("results: " + ", ".join(str(p) for p in paths.values()))
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from sim.truth import simulate

    config = load_config_with(args.config, args.set)
    if config.truth is None:
        raise ConfigError(f"{config.source}: [truth] is needed to simulate this aircraft")
    flight = simulate(config, seed=args.seed)
    rec = Recording(flight.t_s, flight.inputs, flight.measurements, "throttle")
    label = (
        f"simulated flight, seed {args.seed if args.seed is not None else config.simulation.seed}"
    )
    return _run_recording(config, rec, flight.truth, args, label)


def cmd_offline(args: argparse.Namespace) -> int:
    config = load_config_with(args.config, args.set)
    path = Path(args.data)
    rec = load_csv(path) if path.suffix.lower() == ".csv" else load_hfb320(path)
    want = "thrust" if config.propulsion.model == "measured" else "throttle"
    if rec.power != want:
        raise ConfigError(
            f"{config.source}: [propulsion] model: {config.propulsion.model!r} needs {want} "
            f"in the data, but {path} has {rec.power}"
        )
    return _run_recording(config, rec, config_truth(config), args, f"offline {path.name}")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="gcs-estimator",
        description="Identify a fixed-wing aircraft's longitudinal aerodynamic coefficients "
        "from flight data with an EKF and an iterated EKF side by side.",
    )
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="fly the simulated aircraft and estimate offline")
    _common(p)
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: config)")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "demo", help="the main job: the simulated NOC UAV through both filters, with the table"
    )
    _common(p)
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: config)")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("offline", help="estimate from a data file (HFB-320 .asc or CSV)")
    _common(p, "configs/hfb320.toml")
    p.add_argument("data", help="flight data: the HFB-320 ASCII record or a CSV (see README)")
    p.set_defaults(func=cmd_offline)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        status: int = args.func(args)
    except (ConfigError, FlightDataError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return status


def entrypoint() -> None:
    sys.exit(main())
