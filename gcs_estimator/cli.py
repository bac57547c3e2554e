"""Command line: `gcs-estimator COMMAND ...`; main(argv) -> exit status, callable from tests."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import socket
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from gcs_estimator import blas
from gcs_estimator.config import (
    REFINE_METHODS,
    STARTER_AIRFRAME,
    VIEW_OUTPUTS,
    AircraftConfig,
    ConfigError,
    FlightAirframe,
    config_path,
    config_reference,
    flight_airframe,
    load_config,
    load_reference,
    load_truths,
    shipped_configs,
    truths_text,
)
from gcs_estimator.estimation.filters.core import Backend
from gcs_estimator.estimation.segments import (
    Limits,
    Window,
    excluding,
    parse_window,
    parse_windows,
)
from gcs_estimator.ingest import endpoints
from gcs_estimator.ingest.flightdata import FlightDataError, Recording, data_file
from gcs_estimator.ingest.logs import detect
from gcs_estimator.ingest.logs.reader import (
    LogError,
    NotAFlightError,
    load_flight,
    stderr_progress,
)
from gcs_estimator.ingest.sources import (
    RCVBUF_BYTES,
    LiveSource,
    SerialSource,
    SourceError,
    TcpSource,
    UdpSource,
    open_udp,
)
from gcs_estimator.ingest.telemetry.link import MavlinkLink, link_of
from gcs_estimator.ingest.telemetry.mavlink import TlogWriter
from gcs_estimator.ingest.telemetry.vehicle_setup import link_config
from gcs_estimator.outputs.checks import Checks, live_advice_text
from gcs_estimator.outputs.diagnosis import set_argv
from gcs_estimator.outputs.sinks import (
    ProgressSink,
    RefineAsk,
    ResultsSink,
    RunEnd,
    StatusSink,
    vehicle_heading,
)
from gcs_estimator.outputs.table import LiveEstimate, live_table
from gcs_estimator.outputs.view.live import RerunView, ViewSink, open_outlets, resolve_outputs
from gcs_estimator.runtime import options
from gcs_estimator.runtime.decode_worker import LinkArgs, tlog_source
from gcs_estimator.runtime.filter_worker import ShardedSession, TablesSink
from gcs_estimator.runtime.flights import (
    NoSegmentError,
    check_one_aircraft,
    limits_of,
    source_of,
    tlog_recording,
    what_flew,
)
from gcs_estimator.runtime.link_worker import LiveJob, WorkerUdpSource
from gcs_estimator.runtime.session import (
    BATCH_BLOCK_FRAMES,
    Hold,
    RecordingSource,
    Session,
    Source,
    warm_up,
)
from gcs_estimator.stop import PROCESS_STOP, Stop
from gcs_estimator.uncertainty import weighting
from gcs_estimator.uncertainty.result import VehicleResult

DEFAULT_CONFIG = "noc_uav"
VIEW_FILE = "view.rrd"
TLOG_FILE = "telemetry.tlog"
ADVICE_FILE = "advice.json"  # --follow-advice's account of its rounds
"""The same file names from every command, in the run's own folder."""


OUTPUT_GLOBS = ("results_sys*.json", VIEW_FILE, TLOG_FILE, "replays.json", ADVICE_FILE)
"""What in a folder says a run wrote it."""


def run_folder(args: argparse.Namespace, started: datetime) -> Path:
    """The run's folder: --out exactly (refused if it holds a run's outputs, unless
    --force), else out/<command>_<UTC time> (with _2, _3 ... if taken)."""
    if args.out is not None:
        out = Path(args.out)
        taken = [p.name for g in OUTPUT_GLOBS for p in out.glob(g)] if out.is_dir() else []
        if taken and not args.force:
            raise ConfigError(
                f"--out {out}: holds a run's outputs already ({', '.join(sorted(taken))}); "
                "choose another folder, or --force to overwrite them"
            )
        return out
    base = Path("out") / f"{args.command}_{started:%Y%m%dT%H%M%SZ}"
    out, k = base, 1
    while out.exists():
        k += 1
        out = base.with_name(f"{base.name}_{k}")
    return out


def run_info(
    args: argparse.Namespace, config: AircraftConfig, source: str | None
) -> dict[str, Any]:
    """What the JSON says of the run: version, command line, source (a file's path and
    hash), config and its hash, start and end times (UTC)."""
    config_text = json.dumps(config.raw, sort_keys=True, default=str)
    started: datetime = args.started
    info: dict[str, Any] = {
        "version": _version(),
        "command": args.command,
        "command_line": sys.argv[:] if args.argv is None else ["gcs-estimator", *args.argv],
        "config": config.source,
        "config_sha256": hashlib.sha256(config_text.encode()).hexdigest(),
        "source": None,
        "source_sha256": None,
        "started_utc": started.isoformat(timespec="seconds"),
        "ended_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    info["source"] = source
    if getattr(args, "compatibility", None) is not None:  # ingest/compat.py's findings
        info["compatibility"] = args.compatibility
    if source is not None and Path(source).is_file():
        digest = hashlib.sha256()
        with open(source, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
        info["source_sha256"] = digest.hexdigest()
    return info


def _config_arg(p: options.Parser, default: str | None) -> None:
    options.config_option(
        p,
        default,
        "a log needs one, unless it is the simulator's (its truth file beside it names the "
        "airframe) or the bundled HFB-320 record",
    )


SIMULATED = ("demo", "simulate")
"""Commands whose aircraft is the simulator's: the config's [truth] is what it flies."""
SIDE_SUFFIX = ".truth.toml"
"""The truth file beside a recording (telemetry.tlog: telemetry.truth.toml) that names
the airframe it was flown or estimated with, and its vehicles' truth where known."""
AIRFRAME_NEEDS = (
    "give --config FILE, a TOML with [airframe] mass_kg, wing_area_m2, mean_chord_m, "
    "inertia_yy_kgm2, air_density_kgpm3, trim_airspeed_mps, [propulsion] model and "
    "[coefficients]; `gcs-estimator airframe FILE` writes one to fill in"
)


def side_file(recording: str | Path) -> Path:
    """The truth file beside a recording (SIDE_SUFFIX)."""
    return Path(recording).with_suffix(SIDE_SUFFIX)


def _flight_file(args: argparse.Namespace) -> Path | None:
    """The truth file that names the airframe of a run without --config: --truth's, else
    the one beside the (first) recording."""
    truth = getattr(args, "truth", None)
    if truth is not None and flight_airframe(truth) is not None:
        return Path(truth)
    logs = getattr(args, "tlogs", None) or []
    beside = side_file(logs[0]) if logs else None
    if beside is not None and beside.is_file() and flight_airframe(beside) is not None:
        return beside
    return None


def _airframe(args: argparse.Namespace) -> AircraftConfig:
    """The airframe file of the run: --config (its [truth] is the user's reference),
    else the simulator's own (demo, simulate), else the one a truth file names, else the
    bundled record's; listen without one takes the simulated vehicle's airframe (no
    truth) and says so; a log without one is refused (AIRFRAME_NEEDS)."""
    args.flight_file = None
    if args.config is not None:
        return load_config(args.config, args.set)
    if args.command in SIMULATED:
        return load_config(DEFAULT_CONFIG, args.set)
    flight = _flight_file(args)
    if flight is not None:
        named = flight_airframe(flight)
        assert named is not None
        print(f"note: the airframe is {named.config}, as {flight} says", file=sys.stderr)
        config = load_config(named.config, [*named.overrides, *args.set])
        args.flight_file = flight
        return config if named.own_truth else replace(config, reference=None)
    data = getattr(args, "data", None)
    if data is not None and _bundled_hfb320(data):
        return load_config("hfb320", args.set)
    if args.command == "listen":
        print(
            f"note: no --config: the airframe is the simulated vehicle's ({DEFAULT_CONFIG}), "
            f"and no truth is applied; for a real aircraft, {AIRFRAME_NEEDS}",
            file=sys.stderr,
        )
        return replace(load_config(DEFAULT_CONFIG, args.set), reference=None)
    if data is not None:
        what = str(data_file(data))  # a file that is not there says so first
    else:
        logs = getattr(args, "tlogs", None) or []
        for log in logs:
            if not Path(log).is_file():
                raise ConfigError(f"{log}: cannot read: no such file")
        what = ", ".join(logs) or "the log"
    raise ConfigError(f"{what}: no airframe file: {AIRFRAME_NEEDS}")


def _bundled_hfb320(data: str) -> bool:
    """Whether a data argument is the bundled HFB-320 record (its name, folder or file)."""
    from gcs_estimator.ingest.flightdata import bundled

    if data == "hfb320":
        return True
    folder = bundled("hfb320").resolve()
    p = Path(data).resolve()
    return p == folder or p.parent == folder


def _truths(
    args: argparse.Namespace, config: AircraftConfig
) -> dict[int, tuple[float, ...]] | None:
    """Each vehicle's truth by system id: --truth's, else the truth file the airframe came
    from (None: the config's [truth] scores the first vehicle, see session.truth_of)."""
    path = getattr(args, "truth", None) or getattr(args, "flight_file", None)
    if path is None:
        return None
    truths = load_truths(path, config.coefficient_names)
    if not truths and getattr(args, "flight_file", None) is not None:
        named = flight_airframe(path)
        if named is not None and named.own_truth:
            return None  # the airframe's [truth] is the flight's own
    return truths


def _write_flight_file(
    args: argparse.Namespace,
    config: AircraftConfig,
    record: Path,
    truths: dict[int, tuple[float, ...]] | None,
) -> None:
    """The truth file beside a recording: the airframe the run used (so that a replay
    without --config uses it too) and the vehicles' truth the run scored against."""
    if args.flight_file is not None:
        named = flight_airframe(args.flight_file)
        assert named is not None
        airframe = replace(named, overrides=(*named.overrides, *args.set))
    else:
        name = args.config or DEFAULT_CONFIG
        if name not in shipped_configs():
            name = str(config_path(name).resolve())
        own = args.command in SIMULATED or (args.config is not None and config.truth is not None)
        airframe = FlightAirframe(name, tuple(args.set), own)
    try:
        record.parent.mkdir(parents=True, exist_ok=True)
        side_file(record).write_text(
            truths_text(truths or {}, config.coefficient_names, airframe), encoding="utf-8"
        )
    except OSError:
        return  # nor can the recording be written there: opening it says why, and stops


AIRCRAFT = "the aircraft"
READING = "what is read"
"""Its title differs by command (_common's `reading`): the simulated flight, the link,
the recordings."""
OUTPUTS = "where the results go"
FRAMES = "which frames the filters take"
FIT = "the whole-record fit (maximum likelihood, after the filters)"
CHECKS = "the model checked, and what to fly next"
PROCESSES = "more than one core"
VIEW = "live view (Rerun)"
"""The groups of a command's options in its --help, in this order (options.group)."""


def _common(
    p: argparse.ArgumentParser, config_default: str | None = None, reading: str = READING
) -> None:
    """The options of every command that estimates, grouped as --help lists them (the
    command's own options about what it reads under `reading`)."""
    for title in (AIRCRAFT, reading, OUTPUTS, FRAMES, FIT, CHECKS, PROCESSES, VIEW):
        options.group(p, title)
    a = options.group(p, AIRCRAFT)
    _config_arg(a, config_default)
    options.set_option(a)
    a.add_argument(
        "--reference",
        default=None,
        metavar="TOML",
        help="reference coefficient values to show and compare against (a [truth] table, "
        "e.g. a textbook's); replaces the config's [truth]",
    )
    o = options.group(p, OUTPUTS)
    options.out_options(
        o,
        "this run's folder (default: out/COMMAND_UTCTIME); one that holds a run's outputs "
        "already is refused unless --force",
        "overwrite the outputs in --out",
    )
    options.history_option(o, "each vehicle's")
    options.group(p, FRAMES).add_argument(
        "--window",
        action="append",
        default=[],
        metavar="FROM:TO",
        help="only these seconds after the (each) flight's first frame go to the filters and "
        "the fit, e.g. 60:300 or 60: (either side may be empty; repeatable)",
    )
    f = options.group(p, FIT)
    f.add_argument(
        "--refine",
        choices=REFINE_METHODS,
        default=None,
        help="at the end, also fit the whole record by maximum likelihood from the IEKF's "
        "estimate: auto (filter error where the filters found turbulence, else output "
        "error), output-error (calm air) or filter-error (with process noise); see `refine`",
    )
    f.add_argument(
        "--hold-noise",
        action="store_true",
        help="the fit keeps the noise levels the filters used (measurement sigmas; filter "
        "error: the config's process noise) instead of estimating them: for sensors and air "
        "whose noise you know",
    )
    _checks_options(p)
    v = options.group(p, VIEW)
    v.add_argument(
        "--view",
        default=None,
        metavar="OUTPUTS",
        help="comma-separated: save (an .rrd), serve (viewers join at any time), spawn (a "
        "local viewer), connect (a running viewer), off, auto (spawn+save with a display, "
        "else save). Default: [view] outputs of the config, normally auto",
    )
    v.add_argument(
        "--rrd", default=None, metavar="FILE", help=f"the .rrd to save (default: OUT/{VIEW_FILE})"
    )
    v.add_argument(
        "--serve-port",
        type=int,
        default=None,
        metavar="PORT",
        help="port of the served view (default 9877)",
    )
    v.add_argument(
        "--connect",
        default=None,
        metavar="URL",
        help="stream to the viewer at this URL (implies connect), e.g. "
        "rerun+http://127.0.0.1:9876/proxy",
    )


def _checks_options(p: argparse.ArgumentParser) -> None:
    """The held-out check and the advice (decisions 0051, 0052)."""
    c = options.group(p, CHECKS)
    c.add_argument(
        "--validate",
        default=None,
        metavar="FROM:TO|LOG",
        help="at the end, fly the identified model (refine's where asked, else the IEKF's) "
        "over a held-out segment, a window of this record (seconds after its first frame) "
        "or another log of the same aircraft (.bin, .ulg, .csv), and give each channel's "
        "Theil U and RMS error; coefficients whose channels it misses are weak at best",
    )
    c.add_argument(
        "--no-advice",
        action="store_true",
        help="at the end, do not work out what to fly next (the manoeuvre that would "
        "identify what the flight has not)",
    )


def _follow_advice_option(p: argparse.ArgumentParser) -> None:
    """--follow-advice: a recorded flight run again as its warnings advise (follow_advice)."""
    options.group(p, CHECKS).add_argument(
        "--follow-advice",
        action="store_true",
        help="run again, up to 4 times in all, with the settings each run's warnings advise "
        "(the JSON's diagnostics.advised_settings, and a filter-error fit where they ask "
        "for one) until they advise nothing new: each run in OUT/round_N, what each changed "
        "and its NIS in OUT/advice.json; the last round is the run to read",
    )


def _live_advice(
    args: argparse.Namespace, session: Session | ShardedSession
) -> Callable[[int, float], str] | None:
    """The live view's advice of a vehicle at an airspeed (None: --no-advice)."""
    if getattr(args, "no_advice", False):
        return None
    return lambda sid, airspeed: live_advice_text(session.estimator(sid), airspeed)


def run_end(args: argparse.Namespace) -> RunEnd:
    """The end of the run the command line asked for (outputs.sinks.RunEnd: --refine,
    --validate, --no-advice, --history), one value per run whichever path ends it: the
    results sink in this process, or the filter workers (--filter-workers); the view's
    final panels read what its checks checked."""
    made = getattr(args, "run_end_made", None)
    if isinstance(made, RunEnd):
        return made
    end = RunEnd(_refiner(args), _new_checks(args), args.history)
    args.run_end_made = end
    return end


def _hold(args: argparse.Namespace) -> Hold | None:
    """What keeps the frames of the window --validate holds out as they come (None: no
    window held out)."""
    checks = run_end(args).checks
    return None if checks.window is None else checks.hold


def _held_window(args: argparse.Namespace) -> Window | None:
    """The window --validate holds out (None: no --validate, or a log)."""
    text = getattr(args, "validate", None)
    if not text or Path(text).exists():
        return None
    try:
        return parse_window(text)
    except ConfigError:
        raise ConfigError(
            f"--validate {text!r}: neither a file nor a window FROM:TO in seconds (e.g. 60:90)"
        ) from None


def _fitted_windows(args: argparse.Namespace) -> tuple[Window, ...]:
    """The windows the filters and the fit take: --window's (none: the whole flight),
    less the window --validate holds out."""
    windows = parse_windows(getattr(args, "window", None))
    held = _held_window(args)
    return windows if held is None else excluding(windows, held)


def _new_checks(args: argparse.Namespace) -> Checks:
    text = getattr(args, "validate", None)
    advise = not getattr(args, "no_advice", False)
    # The filter workers step every frame (only refine takes a window there).
    fitted = () if getattr(args, "filter_workers", None) else _fitted_windows(args)
    if not text:
        return Checks(advise=advise, fitted=fitted)
    if Path(text).exists():
        if Path(text).is_file() and detect.kind(text) == "tlog":
            raise ConfigError(
                f"--validate {text}: a .tlog is not read as a held-out log; give a window "
                "of this record (FROM:TO), or the flight as a .bin, .ulg or .csv"
            )
        return Checks(log=text, advise=advise, fitted=fitted)
    return Checks(window=_held_window(args), advise=advise, fitted=fitted)


def _station_options(p: argparse.ArgumentParser) -> None:
    """What a station over a MAVLink link takes besides _common (listen, replay): each
    vehicle's truth, and its vehicles' filters in worker processes."""
    options.group(p, AIRCRAFT).add_argument(
        "--truth",
        default=None,
        metavar="FILE",
        help="each vehicle's true coefficients by system id (as gcs-sim --truth writes); "
        "without it only the first vehicle heard is scored, against --reference or the "
        "[truth] of the airframe file given with --config",
    )
    options.group(p, PROCESSES).add_argument(
        "--filter-workers",
        type=_positive_int,
        default=None,
        metavar="K",
        help="the vehicles' filters in K processes (the n-th vehicle heard in process n mod "
        "K): a station with many vehicles on more than one core; a replay with the same K "
        "gives the same estimates and history",
    )


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: at least 1")
    return value


def _config(args: argparse.Namespace) -> AircraftConfig:
    """The config with --set overrides, --reference values and view options applied."""
    config = _airframe(args)
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


def _view_sink(
    config: AircraftConfig,
    args: argparse.Namespace,
    session: Session | ShardedSession,
    link: MavlinkLink | None = None,
) -> ViewSink | None:
    """The live view as chosen on the command line or in the config (None: no view)."""
    choice = resolve_outputs(config, config.view.outputs, Path(args.out) / VIEW_FILE)
    outlets = open_outlets(config, choice)
    if not outlets:
        return None
    view = RerunView(
        outlets,
        config,
        link_source=None if link is None else lambda: (link.session_time(), link.health.as_dict()),
        table_source=lambda sid: live_table(session.estimator(sid), session.truth_of(sid)),
        truth_of=session.truth_of,
        advice_source=_live_advice(args, session),
    )
    checks = run_end(args).checks
    return ViewSink(
        view,
        None if link is None else (lambda: link.t_first_recv),
        checked=lambda: checks.done,
    )


def _limits(args: argparse.Namespace, config: AircraftConfig) -> Limits:
    """The segments' limits of the run: the airframe's, and the --window given less the
    window --validate holds out."""
    return limits_of(config, _fitted_windows(args))


def _refiner(args: argparse.Namespace) -> RefineAsk | None:
    """The whole-record fit the command line asked for (None: not asked). It fits the
    frames the filters used: --window has chosen them already (segments.py), but for the
    filter workers, which use every frame: there the fit alone takes the (one) window."""
    method = getattr(args, "refine", None)
    if method is None:
        return None
    window: tuple[float | None, float | None] = (None, None)
    if getattr(args, "filter_workers", None):
        windows = parse_windows(getattr(args, "window", None))
        if len(windows) > 1:
            raise ConfigError("--window with --filter-workers: one window, which refine fits")
        window = windows[0] if windows else window
    return RefineAsk(method, window, bool(getattr(args, "hold_noise", False)))


EXIT_NOTHING_ESTIMATED = 1
"""The run ended without a usable frame, no frame's observations matched the config, or
the filters diverged on most frames."""
EXIT_REFINE_FAILED = 3
"""The run's results are written, but the whole-record fit asked for (--refine, refine)
failed for some vehicle."""


def _run(session: Session | ShardedSession, source: Source, stop: Stop) -> int:
    """Drive the session; a source that fails still leaves the results of what it gave.
    Exit status: 0, or 2 when a source failed, or EXIT_NOTHING_ESTIMATED or
    EXIT_REFINE_FAILED with the reason."""
    try:
        results = session.run(source, stop)
    except SourceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if getattr(source, "errors", None) or getattr(session, "errors", None):
        return 2
    if not results or all(v.result.frames == 0 for v in results.values()):
        print("error: no usable frame arrived: nothing was estimated", file=sys.stderr)
        return EXIT_NOTHING_ESTIMATED
    unmatched = [sid for sid, v in results.items() if not v.any_update()]
    if len(unmatched) == len(results):
        print(
            "error: no frame's observations could be used (every update had no channel): "
            "check that the data match the config (its [link] mapping and [data] units)",
            file=sys.stderr,
        )
        return EXIT_NOTHING_ESTIMATED
    if _nothing_identifiable(results, session.config):
        return EXIT_NOTHING_ESTIMATED
    failed = [
        why
        for sink in session.sinks
        if isinstance(sink, ResultsSink) and isinstance(sink.refine, RefineAsk)
        for why in sink.refine.failures
    ]
    if isinstance(session, ShardedSession):  # the fits ran in the filter processes
        failed += session.refine_failures
    if failed:
        print(
            f"error: the whole-record fit failed ({'; '.join(failed)}); the filters' results "
            "are written",
            file=sys.stderr,
        )
        return EXIT_REFINE_FAILED
    return 0


def _nothing_identifiable(results: Mapping[int, VehicleResult], config: AircraftConfig) -> bool:
    """Say which vehicles never flew (_never_flew) and whose filters diverged on most
    frames (_mostly_diverged); True when that is every vehicle: nothing was estimated."""
    grounded = [sid for sid, v in results.items() if _never_flew(v, config)]
    for sid in grounded:
        print(
            f"error: vehicle {sid} never flew: its airspeed never reached "
            f"{FLYING_SHARE:g} x [airframe] trim_airspeed_mps "
            f"({FLYING_SHARE * config.airframe.trim_airspeed_mps:g} m/s): on the ground or "
            "hovering, nothing a fixed wing's coefficients could be read from",
            file=sys.stderr,
        )
    diverged = [sid for sid, v in results.items() if sid not in grounded and _mostly_diverged(v)]
    if diverged:
        print(
            f"error: the filters diverged on most frames of vehicle(s) {diverged} and started "
            "again from the prior each time: their numbers are not estimates (check the data: "
            "an input or channel misread, empty or in the wrong unit)",
            file=sys.stderr,
        )
    return len(grounded) + len(diverged) == len(results)


DIVERGED_SHARE = 0.5
"""A vehicle whose filter diverged on more than this share of its frames was not
estimated: its numbers are the prior's (exit EXIT_NOTHING_ESTIMATED)."""


def _mostly_diverged(v: VehicleResult) -> bool:
    """Whether a filter of the vehicle diverged on most of its frames (DIVERGED_SHARE)."""
    frames = max(v.result.frames, 1)
    return any(f.health.divergences > DIVERGED_SHARE * frames for f in v.result.filters.values())


FLYING_SHARE = 0.5
"""A vehicle whose airspeed never reached this share of the trim airspeed never flew."""


def _never_flew(v: VehicleResult, config: AircraftConfig) -> bool:
    """Whether the vehicle's measured airspeed never reached FLYING_SHARE of the trim
    airspeed (False where no airspeed was measured, or no history kept: not known)."""
    track = next((f.track for f in v.result.filters.values() if f.track is not None), None)
    if track is None or not len(track.y) or not np.isfinite(track.y[:, 0]).any():
        return False
    return float(np.nanmax(track.y[:, 0])) < FLYING_SHARE * config.airframe.trim_airspeed_mps


def _results_sink(
    args: argparse.Namespace,
    config: AircraftConfig,
    session: Session,
    heading: Callable[[VehicleResult, float], str],
    origin: str | None,
) -> ResultsSink:
    """The end of the run (run_end) as this process's results sink: the table on stdout
    and the result files in the run's folder, with the run's record."""
    return run_end(args).sink(
        Path(args.out),
        heading,
        lambda: session.elapsed_s,
        run=lambda: run_info(args, config, origin),
        estimators=lambda: session.estimators,
    )


def _recording_session(
    config: AircraftConfig,
    args: argparse.Namespace,
    source: RecordingSource,
    label: str,
    origin: str | None,
) -> int:
    stop = PROCESS_STOP.install()
    session = Session(config, backend=args.backend)
    source.hold = _hold(args)  # the held-out window, whether the plan takes it or not
    view = _view_sink(config, args, session)
    if sys.stderr.isatty():
        session.add_sink(ProgressSink(source.progress, label, unit="frames"))

    def heading(v: VehicleResult, elapsed: float) -> str:
        n = v.result.frames
        return (
            f"{config.airframe.name}: {label}, {n} frames in {elapsed:.2f} s "
            f"({n / max(elapsed, 1e-9):,.0f} frames/s, both filters)"
        )

    session.add_sink(_results_sink(args, config, session, heading, origin))
    if view is not None:  # after the results: its final panels show their checks
        session.add_sink(view)
    else:  # nothing needs every frame: the filters take them in blocks (decision 0065)
        session.block_frames = BATCH_BLOCK_FRAMES
    return _run(session, source, stop)


def cmd_simulate(args: argparse.Namespace) -> int:
    from sim.scenario import scenario_of
    from sim.truth import simulate

    config = _config(args)
    if config.truth is None:
        raise ConfigError(f"{config.source}: [truth] is needed to simulate this aircraft")
    scenario = scenario_of(config)
    seed = args.seed if args.seed is not None else scenario.seed
    flight = simulate(config, seed=seed, scenario=scenario)
    source = RecordingSource(flight.t_s, flight.inputs, flight.measurements)
    return _recording_session(config, args, source, f"simulated flight, seed {seed}", None)


def _flight(
    data: str, config: AircraftConfig, progress: bool
) -> tuple[Path, Recording, str | None]:
    """A data file or an autopilot's log (by its content); a log's account on stderr."""
    show = sys.stderr.isatty() or progress
    report = stderr_progress(f"reading {Path(data).name}") if show else None
    path, rec, account = load_flight(data, config, report)
    if account:
        print(account, file=sys.stderr)
    return path, rec, account


def cmd_offline(args: argparse.Namespace) -> int:
    data = [args.data] if isinstance(args.data, str) else list(args.data)
    if len(data) == 1 and Path(data[0]).is_file() and detect.kind(data[0]) == "tlog":
        args.tlogs, args.speed, args.progress = data, 0.0, False
        return cmd_replay(args)
    args.data = data[0]  # the airframe: the bundled record's where it is one
    config = _config(args)
    recs, names, paths, flew = [], [], [], []
    for item in data:
        path, rec, account = _flight(item, config, getattr(args, "progress", False))
        for note in rec.notes:
            print(f"note: {note}", file=sys.stderr)
        want = config.propulsion.input_name
        if rec.power != want:
            raise ConfigError(
                f"{config.source}: [propulsion] model: {config.propulsion.model!r} needs "
                f"{want} in the data, but {path} has {rec.power}"
            )
        recs.append(rec)
        names.append(path.name)
        paths.append(str(path))
        flew.append((path.name, what_flew(account)))
    check_one_aircraft(flew)
    findings = {n: r.compatibility for n, r in zip(names, recs, strict=True) if r.compatibility}
    # ingest/compat.py's findings: the one flight's, or each flight's by its file's name
    args.compatibility = recs[0].compatibility if len(recs) == 1 else findings or None
    label = f"offline {names[0]}" if len(names) == 1 else f"{len(names)} flights"
    origin = ", ".join(paths)  # the files read (a bundled record's too: hashed in the JSON)
    return _flights_session(config, args, recs, names, label, origin)


def _flights_session(
    config: AircraftConfig,
    args: argparse.Namespace,
    recs: list[Recording],
    names: list[str],
    label: str,
    origin: str,
) -> int:
    """One estimate from the recordings' segments (flights of one aircraft), its
    segments summarised in a line first."""
    try:
        source = source_of(recs, names, _limits(args, config))
    except NoSegmentError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_NOTHING_ESTIMATED
    assert source.plan is not None
    print(source.plan.summary(), file=sys.stderr)
    return _recording_session(config, args, source, label, origin)


STATUS_VEHICLES = 12
"""Vehicles the status shows a line each for (the rest are counted in one line)."""
STATUS_COEFFICIENTS = ("CLa", "Cma", "Cmq", "Cmde")


def _status_lines(
    link: MavlinkLink, session: Session | ShardedSession, elapsed_s: float
) -> list[str]:
    """The link's counters, then one line per vehicle (frames, key coefficients)."""
    h = link.health.total()
    estimators: Mapping[int, LiveEstimate] = session.estimators
    lines = [
        f"{elapsed_s:7.1f} s  packets {h.received}  lost {h.lost}  dup {h.duplicates}  "
        f"late {h.out_of_order}  bad {h.corrupt}  vehicles {len(estimators)}"
    ]
    for sid, est in list(estimators.items())[:STATUS_VEHICLES]:
        line = f"  sys {sid:3d}: {est.frames:7d} frames"
        cur = est.snapshot().get("IEKF")
        if cur is not None:
            names = est.names
            line += "  " + "  ".join(
                f"{n} {cur.coefficients[names.index(n)]:+.3g}"
                for n in STATUS_COEFFICIENTS
                if n in names
            )
        lines.append(line)
        rates = link.rates_status(sid)
        if rates:
            lines.append(f"    {rates}")
    more = len(estimators) - STATUS_VEHICLES
    if more > 0:
        lines.append(f"  ... and {more} more vehicle{'s' if more > 1 else ''}")
    return lines


def _link_session(
    config: AircraftConfig,
    args: argparse.Namespace,
    origin: str | None,
    record: Path | None = None,
    status: bool = True,
    recorder: bool = True,
    blocks: bool = False,
) -> tuple[Session | ShardedSession, MavlinkLink]:
    """A session over a MAVLink link, with its view and result sinks (and, live, its
    status line); recorder False: the link records nothing here (a link worker records
    `record`); blocks: a recording read as fast as it goes, whose frames the filters
    take in blocks where no view needs every frame (decision 0065). With
    --filter-workers the vehicles' filters run in worker processes (filter_worker.py),
    which write their results. Alpha from AOA_SSA is weighed as
    [link] aoa_ssa says (vehicle_setup.link_config)."""
    config = link_config(config)
    workers = getattr(args, "filter_workers", None)
    truths = _truths(args, config)
    if record is not None:
        _write_flight_file(args, config, record, truths)
    session: Session | ShardedSession
    if workers:
        warm_up(config, args.backend, compile_kernels=False)  # the workers compile theirs
        session = ShardedSession(
            config,
            workers,
            args.out,
            backend=args.backend,
            truths=truths,
            end=run_end(args),
            run_info=lambda: run_info(args, config, origin),
        )
    else:
        warm_up(config, args.backend)
        session = Session(
            config,
            backend=args.backend,
            truths=truths,
            gate=_limits(args, config),
            hold=_hold(args),  # the held-out window, which the gate leaves out
            check_frames=True,  # a link's frames: no reader checked them (decision 0084)
        )
    link = link_of(
        config,
        recorder=TlogWriter(record) if record and recorder else None,
        rejected_path=record.with_name(record.stem + ".rejected.tlog") if record else None,
    )
    view = _view_sink(config, args, session, link)
    if status:
        session.add_sink(StatusSink(lambda elapsed: _status_lines(link, session, elapsed)))
    if isinstance(session, ShardedSession):
        session.add_sink(TablesSink(session))
    else:
        session.add_sink(_results_sink(args, config, session, vehicle_heading, origin))
    if view is not None:  # after the results: its final panels show their checks
        session.add_sink(view)
    elif blocks and isinstance(session, Session):
        session.block_frames = BATCH_BLOCK_FRAMES
    return session, link


def cmd_listen(args: argparse.Namespace) -> int:
    stop = PROCESS_STOP.install()
    config = _config(args)
    endpoint = endpoints.parse(args.endpoint, default_listen=True)
    worker = getattr(args, "link_worker", False)
    if worker and (endpoint.serial or endpoint.tcp):
        raise ConfigError("--link-worker: UDP endpoints only (udpin:, udpout:)")
    record = Path(args.record) if args.record else Path(args.out) / TLOG_FILE
    if args.record and record.exists() and not args.force:
        raise ConfigError(f"--record {record}: the file exists; --force to overwrite it")
    # Bound before anything is opened for writing: a busy port leaves a recording as it was.
    if endpoint.serial:
        port = endpoints.open_serial(endpoint)
    else:
        sock = (
            endpoints.open_tcp(endpoint)
            if endpoint.tcp
            else endpoints.open_socket(endpoint, RCVBUF_BYTES)
        )
    session, link = _link_session(config, args, args.endpoint, record, recorder=not worker)
    sharded = ""
    if isinstance(session, ShardedSession):
        try:
            session.start()
        except SourceError as exc:
            link.close()
            print(f"error: {exc}", file=sys.stderr)
            return 2
        sharded = f", the filters in {len(session.shards)} processes"
    source: LiveSource | WorkerUdpSource
    if worker:
        where = _where(endpoint, sock)
        job = LiveJob(
            sock.fileno(),
            LinkArgs(link.config, link.linear_inputs, link.ranges, link.elevator_travel_deg),
            str(record),
            str(link.rejected_path) if link.rejected_path else None,
            args.idle_exit,
            args.duration,
            None if endpoint.listen else endpoint.address,
        )
        source = WorkerUdpSource(sock, job, link)
        try:
            source.start()
        except SourceError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        where += " (the link in a second process)"
    elif endpoint.serial:
        where = f"reading serial {endpoint.device} at {endpoint.port} baud"
        source = SerialSource(port, link, args.idle_exit, args.duration)
    elif endpoint.tcp:
        where = _where(endpoint, sock)
        source = TcpSource(sock, link, endpoint.listen, args.idle_exit, args.duration)
    else:
        where = _where(endpoint, sock)
        peer = None if endpoint.listen else endpoint.address
        source = UdpSource(sock, link, args.idle_exit, args.duration, peer)
    print(f"{where}{sharded}, recording to {record} (Ctrl-C to stop)", file=sys.stderr)
    return _run(session, source, stop)


def _where(endpoint: endpoints.Endpoint, sock: socket.socket) -> str:
    """What the station listens on or connects to, with the port the system chose when
    asked for port 0."""
    bound = sock.getsockname()[1]
    host = f"[{endpoint.host}]" if ":" in endpoint.host else endpoint.host
    proto = "tcp" if endpoint.tcp else "udp"
    if endpoint.listen:
        return f"listening on {proto} {host}:{bound}"
    if endpoint.tcp:
        return f"connected to tcp {host}:{endpoint.port}"
    return f"listening on udp port {bound}, sending to udp {host}:{endpoint.port} first"


def tlog_paths(paths: Sequence[str]) -> list[str]:
    """The files to replay: each path as given, a folder as the .tlog files in it (by
    name); a folder without one is refused."""
    out: list[str] = []
    for p in paths:
        folder = Path(p)
        if not folder.is_dir():
            out.append(p)
            continue
        found = sorted(str(f) for f in folder.glob("*.tlog") if f.is_file())
        if not found:
            raise ConfigError(f"{p}: a folder with no .tlog file in it")
        out += found
    return out


def cmd_replay(args: argparse.Namespace) -> int:
    stop = PROCESS_STOP.install()
    args.tlogs = tlog_paths(args.tlogs)
    if any(detect.is_log(p) for p in args.tlogs):
        if getattr(args, "each", False) or not all(detect.is_log(p) for p in args.tlogs):
            raise ConfigError(
                "autopilot logs (.bin, .log, .ulg) are replayed on their own, or several "
                "together as flights of one aircraft, not with .tlog files or --each"
            )
        args.data = args.tlogs
        return cmd_offline(args)
    if getattr(args, "each", False):
        from gcs_estimator.runtime.batch import run_each

        return run_each(args, stop)
    if getattr(args, "jobs", None) is not None:
        raise ConfigError("--jobs: only with --each (the files of one flight are read in order)")
    if getattr(args, "flights", False):
        return _tlog_flights(args)
    config = _config(args)
    origin = args.tlogs[0] if len(args.tlogs) == 1 else ", ".join(args.tlogs)
    session, link = _link_session(config, args, origin, status=False, blocks=args.speed == 0)
    source = tlog_source(args.tlogs, link, speed=args.speed)
    if sys.stderr.isatty() or args.progress:
        session.add_sink(ProgressSink(source.progress, "replay"))
    return _run(session, source, stop)


def _tlog_flights(args: argparse.Namespace) -> int:
    """Several .tlog files as flights of one aircraft (replay --flights, refine): each
    read into its frames, then one estimate from all of them (runtime/flights.py)."""
    if getattr(args, "each", False):
        raise ConfigError("--flights and --each: one estimate from all files, or one each")
    flew = []
    for log in args.tlogs:
        named = flight_airframe(side_file(log)) if side_file(log).is_file() else None
        flew.append((Path(log).name, None if named is None else f"airframe {named.config}"))
    check_one_aircraft(flew)
    config = link_config(_config(args))
    recs = [tlog_recording(log, config) for log in args.tlogs]
    names = [Path(log).name for log in args.tlogs]
    return _flights_session(config, args, recs, names, f"{len(recs)} flights", ", ".join(names))


def cmd_demo(args: argparse.Namespace) -> int:
    """The simulated UAV and the ground station as two processes talking UDP."""
    import subprocess

    from sim.scenario import scenario_of

    stop = PROCESS_STOP.install()
    config = _config(args)
    duration_s = scenario_of(config).manoeuvre.duration_s
    sock = open_udp("127.0.0.1", 0)
    port = sock.getsockname()[1]
    record = Path(args.out) / TLOG_FILE
    session, link = _link_session(config, args, "the simulated vehicle over udp", record)
    from sim.cli import command as vehicle_command

    cmd = vehicle_command(args.config, f"127.0.0.1:{port}", args.speed, args.set, seed=args.seed)
    print(
        f"demo: simulated NOC UAV -> udp 127.0.0.1:{port} -> ground station "
        f"({duration_s:.0f} s flight at {args.speed:g}x; "
        f"recording {record})",
        file=sys.stderr,
    )
    vehicle = subprocess.Popen(cmd)
    try:
        return _run(session, UdpSource(sock, link, idle_exit_s=1.5), stop)
    finally:
        if vehicle.poll() is None:
            vehicle.terminate()
        vehicle.wait(timeout=10)


def cmd_refine(args: argparse.Namespace) -> int:
    """Both filters over a recorded flight, then the whole-record fit from their estimate."""
    args.refine = args.refine or args.method
    flights = list(args.flight)
    if any(Path(f).is_file() and detect.kind(f) == "tlog" for f in flights):
        args.tlogs, args.speed, args.progress = flights, 0.0, False
        args.flights = len(flights) > 1  # several: flights of one aircraft, fitted together
        return cmd_replay(args)
    args.data = args.flight
    return cmd_offline(args)


def cmd_airframe(args: argparse.Namespace) -> int:
    """Write a starter airframe file to fill in from the aircraft's spec sheet."""
    path = Path(args.file)
    if path.exists() and not args.force:
        raise ConfigError(f"{path}: the file exists; choose another name, or --force")
    try:
        path.write_text(STARTER_AIRFRAME, encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write: {exc.strerror}") from exc
    print(
        f"wrote {path}: fill in the values marked FILL IN, then give it with --config {path}",
        file=sys.stderr,
    )
    return 0


def cmd_keys(args: argparse.Namespace) -> int:
    """Print the configuration reference (Markdown) for the config's coefficient names."""
    names = load_config(args.config).coefficient_names
    print(config_reference(names), end="")
    return 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("gcs-estimator")
    except PackageNotFoundError:  # run from a source tree that is not installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="gcs-estimator",
        description="Identify a fixed-wing aircraft's longitudinal aerodynamic coefficients "
        "(lift, drag, pitching moment) from flight data, with an EKF and an iterated EKF "
        "side by side, live or from recordings; each run ends with a table of the "
        "estimates, how far to trust each, and what to fly next.",
        epilog="Start with `demo` (no aircraft needed). For your own aircraft: `airframe "
        "my_plane.toml`, fill it in, then `replay`/`offline`/`listen --config my_plane.toml`. "
        "`gcs-estimator COMMAND --help` lists a command's options.",
    )
    ap.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_simulated(sub)
    _add_listen(sub)
    _add_replay(sub)
    _add_recorded(sub)

    p = sub.add_parser(
        "airframe",
        help="write a starter airframe file to fill in from the aircraft's spec sheet "
        "(each key with what it means and where to find it)",
    )
    p.add_argument("file", help="the TOML file to write, e.g. my_plane.toml")
    p.add_argument("--force", action="store_true", help="overwrite the file if it exists")
    p.set_defaults(func=cmd_airframe)

    p = sub.add_parser(
        "keys", help="list every config key: its default, unit, allowed values and meaning"
    )
    _config_arg(p, DEFAULT_CONFIG)
    p.set_defaults(func=cmd_keys)

    from gcs_estimator.runtime.fleet import add_commands  # `batch` and `trend`

    add_commands(sub)
    return ap


def _add_simulated(sub: Any) -> None:
    """`simulate` and `demo`: the simulator's aircraft, no data needed."""
    p = sub.add_parser(
        "simulate",
        help="fly the simulated aircraft and estimate from its data in this process (seconds)",
    )
    _common(p, DEFAULT_CONFIG, SIMULATED_FLIGHT)
    _seed_option(p)
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "demo",
        help="the whole chain: the simulated UAV sends MAVLink over UDP to a ground station "
        "that runs both filters live (view, table, JSON)",
    )
    _common(p, DEFAULT_CONFIG, SIMULATED_FLIGHT)
    _seed_option(p)
    options.group(p, SIMULATED_FLIGHT).add_argument(
        "--speed",
        type=float,
        default=1.0,
        metavar="X",
        help="the flight at X times real time (default 1; 0 = as fast as possible)",
    )
    p.set_defaults(func=cmd_demo)


SIMULATED_FLIGHT = "the simulated flight"


def _seed_option(p: argparse.ArgumentParser) -> None:
    options.group(p, SIMULATED_FLIGHT).add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="N",
        help="the simulated flight's noise and turbulence seed (default: the config's)",
    )


def _add_listen(sub: Any) -> None:
    p = sub.add_parser(
        "listen",
        help="estimate live from a vehicle's (or several vehicles') MAVLink telemetry: UDP, "
        "TCP or a serial port; every packet recorded to a .tlog",
    )
    _common(p, reading="the link, and for how long")
    r = options.group(p, "the link, and for how long")
    p.add_argument(
        "endpoint",
        nargs="?",
        default="udpin:127.0.0.1:14550",
        help="udpin:HOST:PORT (or udp:) to bind and wait for the vehicle, udpout:HOST:PORT to "
        "send to it first, tcp:HOST:PORT to connect, tcpin:HOST:PORT to wait for a "
        "connection, or a serial port DEVICE[,BAUD] (/dev/ttyUSB0,57600); IPv6 as "
        "[ADDR]:PORT (default: %(default)s, this machine only; udpin:0.0.0.0:14550 for a "
        "vehicle on the network)",
    )
    r.add_argument(
        "--record",
        default=None,
        metavar="FILE",
        help=f".tlog to record every packet to (default: OUT/{TLOG_FILE}; an existing file "
        "only with --force); replay it later for the same estimates",
    )
    r.add_argument(
        "--idle-exit",
        type=float,
        default=None,
        metavar="S",
        help="stop after S seconds without data (once data came); default: run until Ctrl-C",
    )
    r.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    options.group(p, PROCESSES).add_argument(
        "--link-worker",
        action="store_true",
        help="UDP only: receive, decode and record in a second process while this one runs "
        "the filters (two cores; the same frames and estimates)",
    )
    _station_options(p)
    p.set_defaults(func=cmd_listen)


def _add_replay(sub: Any) -> None:
    p = sub.add_parser(
        "replay",
        help="estimate from recorded .tlog files (one flight, several flights of one "
        "aircraft, or each on its own) or one ArduPilot/PX4 log",
    )
    _common(p, reading="the recordings")
    r = options.group(p, "the recordings")
    p.add_argument(
        "tlogs",
        nargs="+",
        help=".tlog files, in order (one flight); a folder stands for the .tlog files in it; "
        "or one autopilot log (.bin, .log, .ulg)",
    )
    r.add_argument(
        "--flights",
        action="store_true",
        help="every .tlog file is a flight of one aircraft: one set of coefficients from all "
        "of them, each flight's flight states its own, each flight's part reported",
    )
    r.add_argument(
        "--each",
        action="store_true",
        help="every file is a flight of its own: each replayed in a process of its own, into "
        "a folder of its own under --out, the results merged in replays.json and replays.md",
    )
    r.add_argument(
        "--speed",
        type=float,
        default=0.0,
        metavar="X",
        help="replay at X times real time, as the live run saw it (default 0: as fast as possible)",
    )
    r.add_argument("--progress", action="store_true", help="a progress bar even when not a tty")
    options.group(p, PROCESSES).add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="with --each: N files replayed at a time (default: the machine's cores)",
    )
    options.group(p, PROCESSES).add_argument(
        "--check-threads",
        type=_positive_int,
        default=None,
        metavar="N",
        help="the structure check's replays in at most N threads (default: the machine's "
        "cores; with --each, each replay gets the cores over --jobs)",
    )
    _station_options(p)
    _follow_advice_option(p)
    p.set_defaults(func=cmd_replay)


def _add_recorded(sub: Any) -> None:
    """`offline` and `refine`: a recorded flight read whole."""
    p = sub.add_parser(
        "offline",
        help="estimate from an autopilot's log or a data file (ArduPilot .bin/.log, PX4 .ulg, "
        "CSV, the HFB-320 record); several: flights of one aircraft",
    )
    _common(p)
    p.add_argument(
        "data",
        nargs="+",
        help="flight data: an ArduPilot .bin/.log or PX4 .ulg log, the HFB-320 ASCII record or "
        "a CSV (see README), or a folder holding one; its content says which. Several: "
        "flights of one aircraft, one set of coefficients from all of them",
    )
    _follow_advice_option(p)
    p.set_defaults(func=cmd_offline)

    p = sub.add_parser(
        "refine",
        help="both filters over a recorded flight, then a maximum-likelihood fit of the whole "
        "record from their estimate, with Cramer-Rao and corrected sigmas",
    )
    _common(p)
    p.add_argument(
        "flight",
        nargs="+",
        help="an ArduPilot/PX4 log, a CSV, the HFB-320 record (or 'hfb320'), or .tlog files; "
        "several logs or data files: flights of one aircraft, fitted together",
    )
    options.group(p, FIT).add_argument(
        "--method",
        choices=REFINE_METHODS,
        default=REFINE_METHODS[0],
        help="the fit's method: auto (default: filter error where the filters found "
        "turbulence over their final pass, else output error), output-error (calm air) or "
        "filter-error (turbulence: a steady-state Kalman filter inside the fit, the "
        "process noise estimated too); --refine METHOD, where given, is taken instead",
    )
    _follow_advice_option(p)
    p.set_defaults(func=cmd_refine)


ADVICE_ROUNDS = 4
"""--follow-advice runs a flight at most this many times (as given, then as advised)."""


def follow_advice(argv: Sequence[str], args: argparse.Namespace) -> int:
    """A recorded flight run as given, then again with what its warnings advise (the JSON's
    diagnostics.advised_settings as `--set` arguments after the user's, and
    `--refine filter-error` for the one run after a run whose warnings ask for that fit),
    until a run advises nothing it has not applied, or ADVICE_ROUNDS runs. Each run goes to
    OUT/round_N; ADVICE_FILE says what each applied and read. The exit status is the last
    run's (a run that estimated nothing or failed ends the rounds with its own)."""
    if getattr(args, "each", False):
        raise ConfigError(
            "--follow-advice with --each: the advice is each flight's own; follow it on one "
            "flight at a time"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    applied: dict[str, Any] = {}
    fit: str | None = None  # the fit the next round adds, as the last one's warnings ask
    fitted = False  # one such fit is run at most once
    rounds: list[dict[str, Any]] = []
    status = 0
    for n in range(1, ADVICE_ROUNDS + 1):
        folder = out / f"round_{n}"
        extra = set_argv(applied) + ([] if fit is None else ["--refine", fit])
        shown = " ".join(a for a in extra if a != "--set") or "as given"
        print(f"follow-advice: round {n} ({shown}) -> {folder}", file=sys.stderr)
        status = _main([*argv, *extra, "--out", str(folder)], rounds=False)
        found = sorted(folder.glob("results_sys*.json"))
        entry: dict[str, Any] = {
            "round": n,
            "folder": folder.name,
            "applied": dict(applied),
            "refine": fit,
            "exit_status": status,
        }
        rounds.append(entry)
        if status not in (0, EXIT_REFINE_FAILED) or len(found) != 1:
            entry["stopped"] = (
                f"exit status {status}"
                if status not in (0, EXIT_REFINE_FAILED)
                else f"{len(found)} vehicles' results: each has advice of its own"
            )
            break
        data = json.loads(found[0].read_text())
        entry["nis"] = {
            kind: {"mean_nis": f["mean_nis"], "mean_channels": f["mean_channels"]}
            for kind, f in data["filters"].items()
        }
        advised = data["diagnostics"]["advised_settings"]
        asked = data["diagnostics"].get("advised_refine")
        new = {k: v for k, v in advised.items() if applied.get(k) != v}
        entry["advised"] = advised
        entry["advised_refine"] = asked
        fitted = fitted or fit is not None
        fit = asked if asked is not None and not fitted else None
        if not new and fit is None:
            entry["stopped"] = "nothing new advised"
            break
        applied |= new
    else:
        rounds[-1]["stopped"] = f"{ADVICE_ROUNDS} rounds: the advice had not settled"
    (out / ADVICE_FILE).write_text(
        json.dumps({"rounds": rounds, "last": rounds[-1]["folder"]}, indent=1)
    )
    for entry in rounds:
        nis = ", ".join(
            f"{kind} NIS {v['mean_nis']:.2f} over {v['mean_channels']:.2f} channels"
            for kind, v in entry.get("nis", {}).items()
        )
        print(f"follow-advice: round {entry['round']}: {nis or entry['stopped']}", file=sys.stderr)
    print(
        f"follow-advice: {len(rounds)} round(s), {rounds[-1]['stopped']}; the run to read: "
        f"{out / rounds[-1]['folder']} (each round's settings and NIS: {out / ADVICE_FILE})",
        file=sys.stderr,
    )
    return status


BACKEND_VARIABLE = "GCS_ESTIMATOR_BACKEND"
"""A developer's switch, not the user's: the filters' backend, "fast" (compiled, the
default) or "reference" (the numpy path the compiled kernels are tested against)."""


def backend_of(environ: Mapping[str, str]) -> Backend:
    """The filters' backend from the environment (BACKEND_VARIABLE), read here only."""
    value = environ.get(BACKEND_VARIABLE, "fast") or "fast"
    if value not in ("fast", "reference"):
        raise ConfigError(f"{BACKEND_VARIABLE}={value!r}: must be 'fast' or 'reference'")
    return "reference" if value == "reference" else "fast"


def _cap_check_threads(args: argparse.Namespace) -> None:
    """--check-threads: the process's cap on the structure check's threads."""
    count = getattr(args, "check_threads", None)
    if count is not None:
        weighting.set_process_threads(count)


def main(argv: Sequence[str] | None = None) -> int:
    return _main(argv, rounds=True)


def _main(argv: Sequence[str] | None, rounds: bool) -> int:
    """One command line's run; with --follow-advice (and `rounds`, False inside its
    rounds) the rounds of follow_advice."""
    blas.one_thread()
    args = build_parser().parse_args(argv)
    args.argv = None if argv is None else list(argv)
    started = datetime.now(UTC)
    try:
        args.backend = backend_of(os.environ)
        _cap_check_threads(args)
        if getattr(args, "hold_noise", False) and args.func is not cmd_refine and not args.refine:
            raise ConfigError("--hold-noise is for the refinement: add --refine METHOD")
        parse_windows(getattr(args, "window", None))  # a bad --window: refused before any work
        if hasattr(args, "out"):
            args.out = str(run_folder(args, started))
            args.started = started
        if rounds and getattr(args, "follow_advice", False):
            given = list(sys.argv[1:] if argv is None else argv)
            return follow_advice(given, args)
        status: int = args.func(args)
    except LogError as exc:  # what the log holds, then why it cannot be used
        print(f"{exc.account}\nerror: {exc}", file=sys.stderr)
        return EXIT_NOTHING_ESTIMATED if isinstance(exc, NotAFlightError) else 2
    except (ConfigError, FlightDataError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return status
