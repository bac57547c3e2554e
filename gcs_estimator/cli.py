"""Command line: `gcs-estimator COMMAND ...`; main(argv) -> exit status, callable from tests."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gcs_estimator.config import (
    VIEW_OUTPUTS,
    AircraftConfig,
    ConfigError,
    load_config_with,
    load_reference,
)
from gcs_estimator.estimator import Estimator
from gcs_estimator.flightdata import (
    FlightDataError,
    Recording,
    data_file,
    load_csv,
    load_hfb320,
)
from gcs_estimator.metrics import summarise
from gcs_estimator.report import (
    config_truth,
    final_table,
    live_table,
    markdown_table,
    write_results,
)
from gcs_estimator.view.live import RerunView, open_outlets, resolve_outputs
from gcs_estimator.view.outlets import Outlet

if TYPE_CHECKING:
    from gcs_estimator.station import Station

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
    p.add_argument(
        "--reference",
        default=None,
        metavar="TOML",
        help="reference coefficient values to show and compare against (a [truth] table, "
        "e.g. a textbook's); replaces the config's [truth]",
    )
    v = p.add_argument_group("live view (Rerun)")
    v.add_argument(
        "--view",
        default=None,
        metavar="OUTPUTS",
        help="comma-separated: save (an .rrd), serve (viewers join at any time), spawn (a "
        "local viewer), connect (a running viewer), off, auto (spawn+save with a display, "
        "else save). Default: [view] outputs of the config, normally auto",
    )
    v.add_argument("--rrd", default=None, help="the .rrd to save (default: OUT/<session>.rrd)")
    v.add_argument(
        "--serve-port", type=int, default=None, help="port of the served view (default 9877)"
    )
    v.add_argument(
        "--connect",
        default=None,
        metavar="URL",
        help="stream to the viewer at this URL (implies connect), e.g. "
        "rerun+http://127.0.0.1:9876/proxy",
    )


def _config(args: argparse.Namespace) -> AircraftConfig:
    """The config with --set overrides, --reference values and view options applied."""
    config = load_config_with(args.config, args.set)
    view = config.view
    outputs = list(view.outputs)
    if args.view is not None:
        outputs = [o.strip() for o in args.view.split(",") if o.strip()]
        for o in outputs:
            if o not in VIEW_OUTPUTS:
                raise ConfigError(f"--view: unknown output {o!r}; allowed: {list(VIEW_OUTPUTS)}")
    if args.connect is not None:
        outputs = [o for o in outputs if o != "off"] + ["connect"]
        view = replace(view, connect_url=args.connect)
    if args.rrd is not None:
        view = replace(view, rrd_path=str(args.rrd))
    if args.serve_port is not None:
        if not 1 <= args.serve_port <= 65535:
            raise ConfigError(f"--serve-port: ports are 1..65535, got {args.serve_port}")
        view = replace(view, serve_port=args.serve_port)
    config = replace(config, view=replace(view, outputs=tuple(dict.fromkeys(outputs))))
    if args.reference is not None:
        values, label = load_reference(args.reference, config.coefficient_names)
        config = config.with_truth(values, label)
    return config


def _outlets(config: AircraftConfig, args: argparse.Namespace, session: str) -> list[Outlet]:
    """The view's outlets as chosen on the command line or in the config (may be none)."""
    choice = resolve_outputs(config, config.view.outputs, Path(args.out) / f"{session}.rrd")
    return open_outlets(config, choice)


def _run_recording(
    config: AircraftConfig,
    rec: Recording,
    truth: np.ndarray | None,
    args: argparse.Namespace,
    label: str,
    session: str,
) -> int:
    est = Estimator(config, backend=args.backend)
    outlets = _outlets(config, args, session)
    view = RerunView(outlets, config, table_source=lambda sid: live_table(est)) if outlets else None
    start = time.perf_counter()
    n = len(rec)
    next_report = 0.0
    t0 = float(rec.t_s[0]) if n else 0.0
    for i in range(n):
        t = float(rec.t_s[i])
        outs = est.step(t, rec.inputs[i], rec.measurements[i])
        if view is not None:
            view.step(1, t - t0, t, rec.inputs[i], rec.measurements[i], outs)
        frac = (i + 1) / n
        if frac >= next_report and sys.stderr.isatty():
            print(f"\r{label}: {frac * 100:5.1f} % of {n} frames", end="", file=sys.stderr)
            next_report += 0.05
    elapsed = time.perf_counter() - start
    if sys.stderr.isatty():
        print(file=sys.stderr)
    if view is not None:
        view.close({1: final_table(est)})
    summaries = summarise(est, truth)
    print(
        f"\n{config.airframe.name}: {label}, {n} frames in {elapsed:.2f} s "
        f"({n / max(elapsed, 1e-9):,.0f} frames/s, both filters)\n"
    )
    print(markdown_table(summaries, config.truth_label))
    paths = write_results(Path(args.out), est, truth)
    print("results: " + ", ".join(str(p) for p in paths.values()))
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from sim.truth import simulate

    config = _config(args)
    if config.truth is None:
        raise ConfigError(f"{config.source}: [truth] is needed to simulate this aircraft")
    seed = args.seed if args.seed is not None else config.simulation.seed
    flight = simulate(config, seed=seed)
    rec = Recording(flight.t_s, flight.inputs, flight.measurements, "throttle")
    return _run_recording(
        config, rec, flight.truth, args, f"simulated flight, seed {seed}", f"simulate_seed{seed}"
    )


def cmd_offline(args: argparse.Namespace) -> int:
    config = _config(args)
    path = data_file(args.data)
    rec = load_csv(path) if path.suffix.lower() == ".csv" else load_hfb320(path)
    want = "thrust" if config.propulsion.model == "measured" else "throttle"
    if rec.power != want:
        raise ConfigError(
            f"{config.source}: [propulsion] model: {config.propulsion.model!r} needs {want} "
            f"in the data, but {path} has {rec.power}"
        )
    return _run_recording(
        config, rec, config_truth(config), args, f"offline {path.name}", f"offline_{path.stem}"
    )


def _station(
    config: AircraftConfig, args: argparse.Namespace, session: str, record: Path | None = None
) -> Station:
    """The ground station with its live view (if any) attached."""
    from gcs_estimator.station import Station

    station = Station(config, backend=args.backend, record=record)
    outlets = _outlets(config, args, session)
    if outlets:
        station.attach_view(outlets)
    return station


def _finish_station(station: Station, args: argparse.Namespace, elapsed: float) -> int:
    """Results per vehicle: table on stdout, JSON/Markdown/CSV in --out."""
    station.finish()
    if station.view is not None:
        station.view.close({sid: final_table(v.estimator) for sid, v in station.vehicles.items()})
    if not station.vehicles:
        print("no vehicle data received", file=sys.stderr)
    link = station.link_stats()
    for v in station.vehicles.values():
        est = v.estimator
        truth = config_truth(station.config)
        print(f"\nvehicle {v.system_id}: {est.frames} frames in {elapsed:.2f} s\n")
        print(markdown_table(summarise(est, truth), station.config.truth_label))
        paths = write_results(
            Path(args.out),
            est,
            truth,
            extra={"link": link, "system_id": v.system_id},
            stem=f"results_sys{v.system_id}",
        )
        print("results: " + ", ".join(str(p) for p in paths.values()))
    print("link: " + ", ".join(f"{k} {v}" for k, v in link.items() if k != "vehicles"))
    return 0


def cmd_listen(args: argparse.Namespace) -> int:
    from gcs_estimator.station import Stop, listen, open_udp

    config = _config(args)
    host, _, port = args.endpoint.removeprefix("udpin:").rpartition(":")
    if not port.isdigit():
        raise ConfigError(f"endpoint {args.endpoint!r}: expected udpin:HOST:PORT")
    record = (
        Path(args.record)
        if args.record
        else Path(args.out) / (time.strftime("live_%Y%m%d_%H%M%S") + ".tlog")
    )
    station = _station(config, args, record.stem, record)
    sock = open_udp(host or "0.0.0.0", int(port))
    stop = Stop()
    stop.install()
    print(
        f"listening on udp {host or '0.0.0.0'}:{port}, recording to {record} (Ctrl-C to stop)",
        file=sys.stderr,
    )
    start = time.time()
    try:
        listen(station, sock, stop, idle_exit_s=args.idle_exit, max_seconds=args.duration)
    finally:
        sock.close()
    return _finish_station(station, args, time.time() - start)


def cmd_replay(args: argparse.Namespace) -> int:
    from gcs_estimator.station import Stop, replay
    from gcs_estimator.telemetry.mavlink import TlogError, TlogStats, read_tlog

    config = _config(args)
    station = _station(config, args, Path(args.tlogs[0]).stem)
    stop = Stop()
    stop.install()
    start = time.time()
    for path in args.tlogs:
        stats = TlogStats()
        try:
            records = list(read_tlog(path, stats))
        except TlogError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        except OSError as exc:
            print(f"error: {path}: cannot read: {exc.strerror}", file=sys.stderr)
            return 2
        if stats.junk_bytes:
            print(f"note: {path}: {stats.junk_bytes} garbage bytes skipped", file=sys.stderr)
        if stats.truncated_tail:
            print(
                f"note: {path}: truncated at the end; the last partial record is ignored",
                file=sys.stderr,
            )
        replay(
            station,
            records,
            total=len(records),
            speed=args.speed,
            stop=stop,
            progress_out=sys.stderr if sys.stderr.isatty() or args.progress else None,
        )
    elapsed = time.time() - start
    return _finish_station(station, args, elapsed)


def cmd_demo(args: argparse.Namespace) -> int:
    """The simulated UAV and the ground station as two processes talking UDP."""
    import subprocess

    from gcs_estimator.station import Stop, listen, open_udp

    config = _config(args)
    sock = open_udp("127.0.0.1", 0)
    port = sock.getsockname()[1]
    record = Path(args.out) / "demo.tlog"
    station = _station(config, args, "demo", record)
    cmd = [
        sys.executable,
        "-m",
        "sim.cli",
        "--config",
        args.config,
        "--target",
        f"127.0.0.1:{port}",
        "--speed",
        str(args.speed),
    ]
    for item in args.set:
        cmd += ["--set", item]
    if args.seed is not None:
        cmd += ["--seed", str(args.seed)]
    print(
        f"demo: simulated NOC UAV -> udp 127.0.0.1:{port} -> ground station "
        f"({config.simulation.manoeuvre.duration_s:.0f} s flight at {args.speed:g}x; "
        f"recording {record})",
        file=sys.stderr,
    )
    vehicle = subprocess.Popen(cmd)
    stop = Stop()
    stop.install()
    start = time.time()
    try:
        listen(station, sock, stop, idle_exit_s=1.5)
    finally:
        sock.close()
        if vehicle.poll() is None:
            vehicle.terminate()
        vehicle.wait(timeout=10)
    return _finish_station(station, args, time.time() - start)


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
        "demo", help="the main job: simulated UAV -> MAVLink over UDP -> both filters -> table"
    )
    _common(p)
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: config)")
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="flight speed, multiple of real time (0 = as fast as possible)",
    )
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("listen", help="estimate live from MAVLink telemetry on UDP")
    _common(p)
    p.add_argument(
        "endpoint",
        nargs="?",
        default="udpin:0.0.0.0:14550",
        help="udpin:HOST:PORT to bind (default: %(default)s)",
    )
    p.add_argument(
        "--record",
        default=None,
        help=".tlog to record every packet to (default: OUT/live_<time>.tlog)",
    )
    p.add_argument(
        "--idle-exit",
        type=float,
        default=None,
        help="stop after this many seconds without data (once data came)",
    )
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.set_defaults(func=cmd_listen)

    p = sub.add_parser("replay", help="estimate from recorded .tlog files")
    _common(p)
    p.add_argument("tlogs", nargs="+", help=".tlog files, in order")
    p.add_argument(
        "--speed",
        type=float,
        default=0.0,
        help="0 = as fast as possible (default), else a multiple of real time",
    )
    p.add_argument("--progress", action="store_true", help="progress bar even when not a tty")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("offline", help="estimate from a data file (HFB-320 .asc or CSV)")
    _common(p, "configs/hfb320.toml")
    p.add_argument(
        "data",
        help="flight data: the HFB-320 ASCII record or a CSV (see README), or a folder holding one",
    )
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


if __name__ == "__main__":
    entrypoint()
