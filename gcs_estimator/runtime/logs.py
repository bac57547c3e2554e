"""One log, whatever its format, estimated as `replay` or `offline` would: the function a
batch runs per log (runtime/fleet.py), in this process.

    estimate_file(path, config, out_dir) -> LogOutcome

The reader is chosen by the file's content (reader_of, ingest.logs.detect): a .tlog is
decoded in this process (a batch's worker is one core already), by the compiled reader
(ingest.telemetry.tlog_fast); an autopilot's log, a
CSV or the HFB-320 record is read as `offline` reads it (ingest.logs.reader.load_flight). The
result files are the replay's (results_sys<ID>.json, .md, the history), in out_dir.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from gcs_estimator.config import AircraftConfig, ConfigError
from gcs_estimator.estimation.estimator import FilterKind, StepOutput
from gcs_estimator.estimation.segments import Plan
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.flightdata import FlightDataError
from gcs_estimator.ingest.logs import detect
from gcs_estimator.ingest.logs.reader import load_flight
from gcs_estimator.ingest.sources import SourceError
from gcs_estimator.ingest.telemetry.link import link_of
from gcs_estimator.ingest.telemetry.mavlink import Codec, TlogError
from gcs_estimator.ingest.telemetry.tlog_fast import read_records, tlog_source_class
from gcs_estimator.ingest.telemetry.vehicle_setup import link_config
from gcs_estimator.outputs.diagnosis import trust_warnings
from gcs_estimator.outputs.sinks import ResultsSink, results_stem
from gcs_estimator.outputs.tables import coefficient_rows, failed_row, summary_row
from gcs_estimator.runtime.flights import limits_of, source_of
from gcs_estimator.runtime.session import BATCH_BLOCK_FRAMES, Session, Source
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.result import VehicleResult

AUTOPILOT_VERSION_ID = 148
"""MAVLink's AUTOPILOT_VERSION message id: the autopilot's 64-bit `uid` (and `uid2`)."""
UID_SCAN_RECORDS = 5_000
"""Records at the start of a .tlog looked through for AUTOPILOT_VERSION (ground
stations ask for it on connecting: 25 s of a typical stream); a log without one in them
is known by system id."""


class LogError(RuntimeError):
    """The log could not be estimated (its row says why); running it again will not help."""


class TimedOutError(LogError):
    """The log took longer than the batch allows a log."""


@dataclass
class LogOutcome:
    """What one log gave: its rows of the batch's tables (coefficient and summary), or one
    failed row of each; the time it took, and the vehicles' identities."""

    log: str
    coefficients: list[dict[str, Any]] = field(default_factory=list)
    summaries: list[dict[str, Any]] = field(default_factory=list)
    error: str | None = None
    seconds: float = 0.0


class Deadline(Stop):
    """A stop requested by a signal or once `seconds` have passed since it was made."""

    def __init__(self, seconds: float | None, parent: Stop | None = None) -> None:
        self._end = None if seconds is None else time.monotonic() + seconds
        self._parent = parent
        self._set = False
        super().__init__()

    @property
    def requested(self) -> bool:
        if self._set or (self._parent is not None and self._parent.requested):
            return True
        return self._end is not None and time.monotonic() >= self._end

    @requested.setter
    def requested(self, value: bool) -> None:
        self._set = value

    @property
    def expired(self) -> bool:
        return self._end is not None and time.monotonic() >= self._end


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def config_sha256(config: AircraftConfig) -> str:
    """The hash of the config as used (cli.run_info's)."""
    import json

    text = json.dumps(config.raw, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("gcs-estimator")
    except PackageNotFoundError:
        return "unknown (not installed)"


@dataclass
class LogFacts:
    """What the log says of itself before any estimation: its flight time (UTC) and the
    autopilots' unique ids by system id; whether its frames come as a link's (a .tlog,
    gated and checked frame by frame as `replay` does), else the data compatibility check
    its reader made (ingest/compat.py's findings, as `offline` reports them)."""

    flight_time: datetime | None = None
    uids: dict[int, str] = field(default_factory=dict)
    link: bool = False
    compatibility: Any = None


def _time_of(t_us: int) -> datetime | None:
    """A tlog record's receive time, or None where its stamp is no time (a damaged log)."""
    try:
        return datetime.fromtimestamp(t_us / 1e6, UTC)
    except (ValueError, OverflowError, OSError):
        return None


def tlog_facts(path: Path) -> LogFacts:
    """A .tlog's first receive time and every AUTOPILOT_VERSION uid among its first
    UID_SCAN_RECORDS records (the header bytes are read; only that message is decoded)."""
    facts = LogFacts()
    codec = Codec(255, 190)
    try:
        for k, rec in enumerate(read_records(path)):
            if facts.flight_time is None:
                facts.flight_time = _time_of(rec.t_recv_us)
            if k >= UID_SCAN_RECORDS:
                break
            if _message_id(rec.packet) == AUTOPILOT_VERSION_ID:
                for msg in codec.parse(rec.packet):
                    uid = _uid_of(msg)
                    if uid:
                        facts.uids[int(msg.get_srcSystem())] = uid
    except (TlogError, OSError):
        pass  # the replay says what is wrong with the file
    return facts


def _message_id(packet: bytes) -> int:
    if len(packet) > 9 and packet[0] == 0xFD:
        return packet[7] | packet[8] << 8 | packet[9] << 16
    if len(packet) > 5 and packet[0] == 0xFE:
        return packet[5]
    return -1


def _uid_of(msg: Any) -> str:
    """The autopilot's unique id as hex: uid2 (18 bytes) where set, else uid (64 bits)."""
    uid2 = bytes(getattr(msg, "uid2", b"") or b"")
    if any(uid2):
        return uid2.hex()
    uid = int(getattr(msg, "uid", 0) or 0)
    return f"{uid:016x}" if uid else ""


class _TimedSource:
    """A source whose frames' reading and decoding is timed (decode_s)."""

    def __init__(self, source: Source) -> None:
        self.source = source
        self.seconds = 0.0

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        it = iter(self.source.frames(stop))
        while True:
            t0 = time.perf_counter()
            try:
                frame = next(it)
            except StopIteration:
                self.seconds += time.perf_counter() - t0
                return
            self.seconds += time.perf_counter() - t0
            yield frame

    def link_stats(self) -> dict[str, Any] | None:
        return self.source.link_stats()

    def close(self) -> None:
        self.source.close()

    @property
    def errors(self) -> list[str]:
        return list(getattr(self.source, "errors", []))

    @property
    def plan(self) -> Plan | None:
        """The recording's segments (a data file's), for its results."""
        plan: Plan | None = getattr(self.source, "plan", None)
        return plan


class _TimedSink:
    """The results writer, timed (write_s)."""

    def __init__(self, sink: ResultsSink) -> None:
        self.sink = sink
        self.seconds = 0.0

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        t0 = time.perf_counter()
        self.sink.on_frame(frame, outs)
        self.seconds += time.perf_counter() - t0

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        t0 = time.perf_counter()
        self.sink.finish(results, link)
        self.seconds += time.perf_counter() - t0


def _tlog_reader(path: Path, config: AircraftConfig, log: io.StringIO) -> tuple[Source, LogFacts]:
    """A .tlog's link as `replay` decodes it (link_of; the config checked as `replay`
    checks it, link_config)."""
    link = link_of(link_config(config))
    facts = tlog_facts(path)
    facts.link = True
    return tlog_source_class()([path], link, log=log), facts


def _data_reader(path: Path, config: AircraftConfig, log: io.StringIO) -> tuple[Source, LogFacts]:
    """An autopilot's log (DataFlash, ULog), a CSV or the HFB-320 record, as `offline`
    reads it (ingest.logs.reader.load_flight: by content), only its segments' frames
    (a NoSegmentError, a failed row, where it has none)."""
    file, rec, account = load_flight(path, config)
    if account:
        print(account, file=log)
    for note in rec.notes:
        print(f"note: {note}", file=log)
    want = config.propulsion.input_name
    if rec.power != want:
        raise LogError(
            f"{config.source}: [propulsion] model: {config.propulsion.model!r} needs {want} "
            f"in the data, but {file} has {rec.power}"
        )
    mtime = datetime.fromtimestamp(file.stat().st_mtime, UTC)
    source = source_of([rec], [file.name], limits_of(config))
    assert source.plan is not None
    print(source.plan.summary(), file=log)
    return source, LogFacts(mtime, compatibility=rec.compatibility or None)


Reader = Callable[[Path, AircraftConfig, io.StringIO], tuple[Source, LogFacts]]

READERS: dict[str, Reader] = {
    "tlog": _tlog_reader,
    "dataflash": _data_reader,
    "dataflash-text": _data_reader,
    "ulog": _data_reader,
    "csv": _data_reader,
    "hfb320": _data_reader,
}
"""The reader of each log format (ingest.logs.detect.kind: the file's content says which)."""


def reader_of(path: Path) -> Reader:
    """The reader of a log, by its content (detect.kind)."""
    return READERS[detect.kind(path)]


LOG_SUFFIXES = (".tlog", ".bin", ".log", ".ulg", ".csv", ".asc")
"""What a folder's files must end with to be taken as logs (a file named on the
command line is read whatever its name)."""


def estimate_file(
    path: str | Path,
    config: AircraftConfig,
    out_dir: str | Path | None,
    base: Mapping[str, Any] | None = None,
    timeout_s: float | None = None,
    history_format: str = "parquet",
    stop: Stop | None = None,
) -> LogOutcome:
    """Both filters over one log, as `replay` (a .tlog) or `offline` (a data file) runs
    them, its result files written into out_dir (None: none); its rows of the batch
    tables, each with `base`'s columns (log, hashes, version: the caller's) and the
    vehicle's identity. A log that cannot be estimated (unreadable, no usable frame, too
    long: timeout_s) gives a failed row and its reason, never an exception; anything
    else (a bug, memory) is raised."""
    p = Path(path)
    started = time.perf_counter()
    base = dict(base or {"log": str(p)})
    outcome = LogOutcome(str(p))
    log = io.StringIO()
    try:
        with contextlib.redirect_stderr(log):
            results, facts, times = _estimate(
                p, config, out_dir, timeout_s, history_format, stop, log
            )
    except (LogError, SourceError, FlightDataError, ConfigError, TlogError) as exc:
        text = str(exc)  # a row's error names its log, whichever reader failed
        outcome.error = text if str(p) in text else f"{p}: {text}"
        outcome.coefficients = [failed_row(base, outcome.error)]
        outcome.summaries = [failed_row(base, outcome.error)]
        outcome.seconds = time.perf_counter() - started
        return outcome
    finally:
        _keep_log(out_dir, log.getvalue())
    times["seconds"] = outcome.seconds = time.perf_counter() - started
    for sid, vehicle in sorted(results.items()):
        uid = facts.uids.get(sid)
        row = {
            **base,
            "flight_time_utc": facts.flight_time,
            "vehicle": base.get("vehicle") or (f"uid:{uid}" if uid else f"sys{sid}"),
            "system_id": sid,
            "autopilot_uid": uid,
            "status": "ok",
            "error": None,
        }
        outcome.coefficients += coefficient_rows(row, vehicle)
        warnings = len(trust_warnings(vehicle, None))
        outcome.summaries.append(summary_row(row, vehicle, warnings, times))
    return outcome


LOG_FILE = "estimate.log"
"""What the log's estimation said (its notes, the results' tables), in its folder."""


def _keep_log(out_dir: str | Path | None, text: str) -> None:
    if out_dir is not None and text:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / LOG_FILE).write_text(text, encoding="utf-8")


def _estimate(
    path: Path,
    config: AircraftConfig,
    out_dir: str | Path | None,
    timeout_s: float | None,
    history_format: str,
    stop: Stop | None,
    log: io.StringIO,
) -> tuple[dict[int, VehicleResult], LogFacts, dict[str, float]]:
    """The run of estimate_file: results by system id, the log's facts, the times."""
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    t0 = time.perf_counter()
    source, facts = reader_of(path)(path, config, log)
    read_s = time.perf_counter() - t0  # a data file read whole, a .tlog's uid looked for
    if facts.link:
        config = link_config(config)  # as replay estimates a link's frames
    timed = _TimedSource(source)
    session = Session(  # no view: blocks (decision 0065)
        config,
        block_frames=BATCH_BLOCK_FRAMES,
        gate=limits_of(config) if facts.link else None,  # a data file's plan chose its frames
        check_frames=facts.link,
    )
    writer = None
    if out_dir is not None:
        sink = ResultsSink(
            Path(out_dir),
            lambda v, s: f"vehicle {v.system_id}: {v.result.frames} frames in {s:.2f} s",
            results_stem,
            lambda: session.elapsed_s,
            out=log,
            estimators=lambda: session.estimators,
            history_format=history_format,
            run=lambda: _run_info(path, config, facts),
        )
        writer = _TimedSink(sink)
        session.add_sink(writer)
    deadline = Deadline(timeout_s, stop)
    t0 = time.perf_counter()
    results = session.run(timed, deadline)
    run_s = time.perf_counter() - t0
    if deadline.expired:
        raise TimedOutError(f"{path}: not done after {timeout_s:g} s (--timeout); nothing kept")
    if stop is not None and stop.requested:
        raise LogError(f"{path}: stopped before its end")
    if timed.errors:
        raise LogError("; ".join(timed.errors))
    if not results or all(v.result.frames == 0 for v in results.values()):
        raise LogError(f"{path}: no usable frame: nothing was estimated")
    if not any(v.any_update() for v in results.values()):
        raise LogError(
            f"{path}: no frame's observations could be used: check that the data match "
            "the config (its [link] mapping and [data] units)"
        )
    write_s = 0.0 if writer is None else writer.seconds
    times = {
        "decode_s": read_s + timed.seconds,
        "filter_s": max(run_s - timed.seconds - write_s, 0.0),  # the summaries' too
        "write_s": write_s,
    }
    return results, facts, times


def _run_info(path: Path, config: AircraftConfig, facts: LogFacts) -> dict[str, Any]:
    """The run's part of the results JSON: the log, the config, and the compatibility
    check its reader made (where one did)."""
    info: dict[str, Any] = {"source": str(path), "config": config.source}
    if facts.compatibility is not None:
        info["compatibility"] = facts.compatibility
    return info
