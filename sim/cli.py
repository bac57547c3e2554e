"""`gcs-sim`: fly the simulated UAV (or play back a data file) as MAVLink vehicles on UDP."""

from __future__ import annotations

import argparse
import sys
import threading
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from gcs_estimator.config import (
    AircraftConfig,
    ConfigError,
    FlightAirframe,
    load_config,
    shipped_configs,
    truths_text,
)
from gcs_estimator.ingest import endpoints
from gcs_estimator.ingest.endpoints import Endpoint
from gcs_estimator.ingest.flightdata import FlightDataError, Recording, load_recording
from gcs_estimator.model.channels import Channel
from sim.formats import flight_record, numbered, write_truth
from sim.formats.ardupilot import (
    DEFAULT_STREAM_HZ,
    ArduPlaneVehicle,
    check_rates,
    parse_rates,
)
from sim.ports import Port, SerialPort, Shared, UdpIn
from sim.scenario import mission, scenario_of, scenario_reference
from sim.truth import simulate
from sim.vehicle import BOOT_OFFSET_S, SimulatedVehicle


def _target(text: str) -> tuple[str, int] | Endpoint:
    """Where the vehicle speaks: udpout:HOST:PORT, udp:HOST:PORT or HOST:PORT (send to
    the station; IPv6 as [ADDR]:PORT), udpin:HOST:PORT (wait for the station to speak
    first), or a serial port DEVICE[,BAUD]; resolved now so that a bad host is an error
    here, not a hang later."""
    try:
        endpoint = endpoints.parse(text, default_listen=False)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if endpoint.tcp:
        raise argparse.ArgumentTypeError(
            f"{text!r}: the simulated vehicle speaks UDP or serial: give udpout:HOST:PORT, "
            "udpin:HOST:PORT or DEVICE[,BAUD]"
        )
    if endpoint.serial or (endpoint.listen and text.startswith("udpin:")):
        return endpoint
    return endpoint.address  # udp: sends, as MAVProxy's --out=udp: does


def _ports(target: tuple[str, int] | Endpoint, vehicles: int) -> list[tuple[str, int] | Port]:
    """Each vehicle's target: its own UDP socket to the station, or its share of one
    udpin or serial port (opened here, so a busy port is an error before any flight)."""
    if isinstance(target, tuple):
        return [target] * vehicles
    port: UdpIn | SerialPort
    if target.serial:
        port = SerialPort(target)
        print(f"gcs-sim: serial {target.device} at {target.port} baud", file=sys.stderr)
    else:
        port = UdpIn(target)
        host, bound = port.bound
        print(
            f"gcs-sim: waiting for a ground station to speak on udp {host}:{bound} "
            "(listen udpout:HOST:PORT there)",
            file=sys.stderr,
            flush=True,
        )
        port.wait_for_peer(None)
        print(f"gcs-sim: ground station at {port.peer}", file=sys.stderr, flush=True)
    shared = Shared(port, vehicles)
    return [shared.user(k) for k in range(vehicles)]


def command(
    config: str | Path,
    target: str,
    speed: float = 1.0,
    overrides: Sequence[str] = (),
    vehicles: int = 1,
    seed: int | None = None,
    boot_s: float | None = None,
) -> list[str]:
    """The command line that runs the simulated vehicle(s) as a process of their own with
    this Python, streaming to target HOST:PORT."""
    cmd = [sys.executable, "-m", "sim.cli", "--config", str(config), "--target", target]
    cmd += ["--speed", str(speed), "--vehicles", str(vehicles)]
    for item in overrides:
        cmd += ["--set", item]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    if boot_s is not None:
        cmd += ["--boot-s", str(boot_s)]
    return cmd


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="gcs-sim", description=__doc__)
    ap.add_argument(
        "--config",
        default="noc_uav",
        help="a shipped config's name or a TOML path (default: %(default)s)",
    )
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument(
        "--scenario",
        choices=("mission", "mission-calm"),
        default=None,
        help="fly a mission as an autopilot does (sim.scenario.mission: about 8 min of legs "
        "and coordinated turns of 20-35 deg, multisteps on every other leg, a climb and a "
        "descent on throttle, light turbulence or calm); --set overrides it",
    )
    ap.add_argument(
        "--no-vane", action="store_true", help="no angle-of-attack vane: alpha is not sent"
    )
    ap.add_argument(
        "--target",
        type=_target,
        default=("127.0.0.1", 14550),
        help="ground station: [udpout:]HOST:PORT to send to it, udpin:HOST:PORT to wait for it "
        "to speak first, or a serial port DEVICE[,BAUD]; IPv6 as [ADDR]:PORT "
        "(default 127.0.0.1:14550)",
    )
    ap.add_argument(
        "--speed", type=float, default=1.0, help="multiple of real time; 0 = as fast as possible"
    )
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--vehicles", type=int, default=1, help="vehicles, system ids 1..N")
    ap.add_argument(
        "--perturb",
        type=float,
        default=0.0,
        help="vehicle k>1 flies true coefficients scaled by 1 +- PERTURB",
    )
    ap.add_argument(
        "--boot-s",
        type=float,
        default=BOOT_OFFSET_S,
        help="the vehicle's uptime when the flight starts (default %(default)s s; past 4295 s "
        "its 32-bit servo clock has wrapped)",
    )
    ap.add_argument("--tlog", default=None, help="write each vehicle's own .tlog (prefix)")
    _add_format_options(ap)
    ap.add_argument(
        "--truth",
        default=None,
        metavar="FILE",
        help="write each vehicle's true coefficients by system id, for "
        "`gcs-estimator listen --truth FILE`",
    )
    ap.add_argument(
        "--keys",
        action="store_true",
        help="print the keys of the [simulation] table (Markdown) and exit",
    )
    ap.add_argument(
        "--playback",
        default=None,
        help="stream flight data instead: a bundled record's name (hfb320), an HFB-320 .asc "
        "or a CSV (see README)",
    )
    return ap


def _add_format_options(ap: argparse.ArgumentParser) -> None:
    """The options that write the flight as an autopilot would (sim/formats)."""
    ap.add_argument(
        "--autopilot",
        choices=("native", "arduplane"),
        default="native",
        help="the MAVLink stream: this tool's own (default) or ArduPlane's message set, "
        "units, stream groups and rates (docs/simulation.md)",
    )
    ap.add_argument(
        "--stream-rate",
        type=float,
        default=DEFAULT_STREAM_HZ,
        metavar="HZ",
        help="arduplane: every SR0 stream's rate before any request (default %(default)s Hz, "
        "what MAVProxy asks)",
    )
    ap.add_argument(
        "--msg-rate",
        action="append",
        default=[],
        metavar="NAME=HZ",
        help="arduplane: one message's rate (as SET_MESSAGE_INTERVAL asks) or one SR0 "
        "stream's (RAW_SENS, EXTRA1, ...)",
    )
    ap.add_argument(
        "--asked",
        action="store_true",
        help="arduplane: the messages the estimator reads at [link] rate_hz, as a station "
        "asks for them",
    )
    ap.add_argument(
        "--bin", default=None, metavar="FILE", help="write an ArduPilot DataFlash log and exit"
    )
    ap.add_argument("--ulg", default=None, metavar="FILE", help="write a PX4 ULog and exit")
    ap.add_argument(
        "--log-rates",
        choices=("default", "fast"),
        default="default",
        help="--bin/--ulg logging rates: the autopilot's defaults, or its fast profile "
        "(ATT at loop rate; PX4 high-rate and system-identification topics)",
    )


def scenario_sets(scenario: str | None, no_vane: bool) -> list[str]:
    """The [simulation] overrides of --scenario and --no-vane."""
    out = [] if scenario is None else mission("none" if scenario == "mission-calm" else "light")
    return [*out, "simulation.vane=false", "simulation.climb_rate=true"] if no_vane else out


def recordings(args: argparse.Namespace) -> list[Recording]:
    """What each vehicle flies (and, with --truth, the file of their true coefficients)."""
    return simulated(args)[0]


def simulated(args: argparse.Namespace) -> tuple[list[Recording], dict[int, tuple[float, ...]]]:
    """What each vehicle flies and, for a simulated flight, each one's true coefficients
    by system id (written to --truth FILE where given)."""
    config = load_config(args.config, args.set)
    truths: dict[int, tuple[float, ...]] = {}
    if args.playback:
        if args.truth:
            raise ConfigError("--truth: played-back data has no true coefficients to write")
        rec = load_recording(args.playback, config.data, config.airframe.elevator_travel_deg)[1]
        for note in rec.notes:
            print(f"note: {note}", file=sys.stderr)
        return [rec] * args.vehicles, truths
    out = []
    base = scenario_of(config).seed if args.seed is None else args.seed
    for k in range(args.vehicles):
        c = config
        if k > 0 and args.perturb and config.truth is not None:
            signs = np.where(np.arange(len(config.truth)) % 2 == 0, 1.0, -1.0)
            c = config.with_truth(tuple(np.array(config.truth) * (1 + args.perturb * signs)))
        fl = simulate(c, seed=base + k)
        # The true climb rate (vz, down positive) beside the measurements: VFR_HUD.climb
        # carries it whether or not the vehicle has a climb-rate sensor (h_dot).
        rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
        out.append(replace(rec, aux={"vz": -fl.clean[:, Channel.HDOT]}))
        truths[k + 1] = tuple(float(v) for v in fl.truth)
    if args.truth:
        Path(args.truth).write_text(truths_text(truths, config.coefficient_names))
    return out, truths


def write_logs(
    args: argparse.Namespace,
    config: AircraftConfig,
    recs: list[Recording],
    truths: dict[int, tuple[float, ...]],
) -> list[Path]:
    """--bin and --ulg: each vehicle's flight as an autopilot's log, each with its truth
    side file where the flight was simulated. Returns the files written."""
    from sim.formats.dataflash import write_bin
    from sim.formats.ulog import write_ulg

    fast = args.log_rates == "fast"
    written: list[Path] = []
    for k, rec in enumerate(recs):
        sid = k + 1
        fr = flight_record(rec, config.link, config.airframe.air_density_kgpm3, sid, args.boot_s)
        for target, write in ((args.bin, write_bin), (args.ulg, write_ulg)):
            if target:
                path = write(fr, numbered(target, sid, len(recs)), fast)
                written.append(path)
                if sid in truths:
                    write_truth(
                        path, {sid: truths[sid]}, config.coefficient_names, flown_with(args)
                    )
    return written


def _vehicle(
    args: argparse.Namespace, config: AircraftConfig, rec: Recording, target: Any, k: int
) -> SimulatedVehicle:
    """Vehicle k's streamer: this tool's own message set, or ArduPlane's."""
    tlog = Path(f"{args.tlog}_{k + 1}.tlog") if args.tlog else None
    common = dict(system_id=k + 1, speed=args.speed, boot_s=args.boot_s, tlog=tlog)
    if args.autopilot == "arduplane":
        rates = parse_rates(args.msg_rate, config.link.rate_hz, args.asked)
        return ArduPlaneVehicle(
            rec,
            config.link,
            target,
            density=config.airframe.air_density_kgpm3,
            stream_hz=args.stream_rate,
            asked_rates=rates,
            **common,
        )
    return SimulatedVehicle(rec, config.link, target, **common)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.set = [*scenario_sets(args.scenario, args.no_vane), *args.set]
    if args.keys:
        print(scenario_reference(), end="")
        return 0
    try:
        config = load_config(args.config, args.set)
        check_rates(args.autopilot, args.msg_rate, config.link.rate_hz, args.asked)
        recs, truths = simulated(args)
    except (ConfigError, FlightDataError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.bin or args.ulg:
        for path in write_logs(args, config, recs, truths):
            print(f"gcs-sim: wrote {path}", file=sys.stderr)
        if not args.tlog:
            return 0
    try:
        targets = _ports(args.target, len(recs))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    vehicles = [_vehicle(args, config, rec, targets[k], k) for k, rec in enumerate(recs)]
    if args.tlog:
        for sid, truth in truths.items():
            write_truth(
                f"{args.tlog}_{sid}.tlog", {sid: truth}, config.coefficient_names, flown_with(args)
            )
    return _fly(vehicles)


def flown_with(args: argparse.Namespace) -> FlightAirframe:
    """The airframe file (and the station's --set overrides) a flight was flown with, as
    its truth file names it: a shipped config by name, any other by its full path."""
    name = args.config if args.config in shipped_configs() else str(Path(args.config).resolve())
    station = tuple(s for s in args.set if not s.strip().startswith("simulation."))
    return FlightAirframe(name, station, True)


def _fly(vehicles: list[SimulatedVehicle]) -> int:
    """Every vehicle's flight in a thread of its own, to the end (or Ctrl-C)."""
    threads = [threading.Thread(target=v.run, daemon=True) for v in vehicles]
    for t in threads:
        t.start()
    try:
        for t in threads:
            t.join()
    except KeyboardInterrupt:
        return 0
    for v in vehicles:
        print(
            f"vehicle {v.system_id}: sent {v.stats.sent} packets, "
            f"{v.stats.gcs_heartbeats} GCS heartbeats, {v.stats.rate_changes} rate changes",
            file=sys.stderr,
        )
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
