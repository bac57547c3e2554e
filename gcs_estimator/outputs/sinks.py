"""Sinks of a session besides the view: the results writer, the live status line and the
progress bar (session.Sink); RunEnd, the end of a run every command's vehicles get."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from gcs_estimator.estimation.estimator import Estimator, FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.telemetry.channel_sources import rates_line
from gcs_estimator.outputs.checks import Checks
from gcs_estimator.outputs.history_csv import HistoryCsv
from gcs_estimator.outputs.report import open_history, write_results
from gcs_estimator.outputs.table import terminal_text
from gcs_estimator.outputs.tables import HistoryParquet
from gcs_estimator.outputs.text import TERMINAL_WIDTH, wrap
from gcs_estimator.uncertainty.result import VehicleResult

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined, RefineProgress


HISTORY_BLOCK_FRAMES = 1024
"""Frames of a vehicle's history written to its file at a time during the run (20 s at
the NOC UAV's 50 Hz): what a stop has left to write."""


class ResultsSink:
    """Each vehicle's history (Parquet, or CSV where asked) as the run goes (given the
    session's estimators); at the end, its Table I on stdout (table.terminal_text: within
    TERMINAL_WIDTH columns), its JSON and Markdown (the full table), and the rest of the
    history."""

    def __init__(
        self,
        out_dir: Path,
        heading: Callable[[VehicleResult, float], str],
        stem: Callable[[int], str],
        elapsed: Callable[[], float],
        out: TextIO | None = None,
        refine: Callable[[VehicleResult], Refined | None] | None = None,
        run: Callable[[], dict[str, Any]] | None = None,
        estimators: Callable[[], Mapping[int, Estimator]] | None = None,
        history_block_frames: int = HISTORY_BLOCK_FRAMES,
        history_format: str = "parquet",
        checks: Callable[[VehicleResult, Refined | None], tuple[VehicleResult, Refined | None]]
        | None = None,
    ) -> None:
        self.checks = checks
        """The held-out check and the advice (outputs.checks.Checks); None: neither."""
        self.history_format = history_format
        """"csv" or "parquet" (tables.HISTORY_FORMATS)."""
        self.estimators = estimators
        """The session's estimators by system id, whose histories go to the CSV as the
        run goes; None: the whole CSV at the end."""
        self.history_block_frames = history_block_frames
        self.histories: dict[int, HistoryCsv | HistoryParquet] = {}
        self.refine = refine
        self.run = run
        """What the JSON says of the run (version, command line, source, times)."""
        self.out_dir = out_dir
        self.heading = heading
        self.stem = stem
        self.elapsed = elapsed
        self.out = sys.stdout if out is None else out

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        if self.estimators is None or not outs:
            return
        est = self.estimators().get(frame.system_id)
        if est is None:
            return
        csv = self.histories.get(frame.system_id)
        if csv is None:  # the vehicle's first frame: the file and its header
            power = est.config.propulsion.input_name
            names = list(est.model.layout.names)
            stem = self.stem(frame.system_id)
            csv = open_history(self.out_dir, stem, self.history_format, names, power)
            self.histories[frame.system_id] = csv
        # Every row but the newest is final (Estimator.tracks).
        final = est.history_rows - 1
        if final - csv.rows >= self.history_block_frames:
            csv.append(est.tracks(), final)

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        if not results:
            print("no vehicle data received", file=sys.stderr)
        for vehicle in results.values():
            self.vehicle(vehicle, link, self.out)
        for csv in self.histories.values():  # vehicles without a result (none so far)
            csv.close()
        if link is not None:
            print(link_line(link), file=self.out)

    def vehicle(
        self, vehicle: VehicleResult, link: Mapping[str, Any] | None, out: TextIO
    ) -> VehicleResult:
        """One vehicle's end: its whole-record fit where one was asked for, its checks
        (the held-out check, the advice), its table on `out`, its files (the rest of its
        history); the vehicle as checked."""
        sid = vehicle.system_id
        heading = self.heading(vehicle, self.elapsed())
        refined = None if self.refine is None else self.refine(vehicle)
        if self.checks is not None:
            vehicle, refined = self.checks(vehicle, refined)
        print(f"\n{heading}\n", file=out)
        print(terminal_text(vehicle, refined), file=out)
        extra: dict[str, Any] = {"system_id": sid}
        if link is not None:
            extra["link"] = dict(link)
        if self.run is not None:
            extra["run"] = self.run()
        history = self.histories.pop(sid, None)
        paths = write_results(
            self.out_dir, vehicle, extra, self.stem(sid), refined, history, self.history_format
        )
        written = "results: " + ", ".join(str(p) for p in paths.values())
        print(wrap(written), file=out)
        return vehicle


def link_line(link: Mapping[str, Any]) -> str:
    """The link's final counts (after the tables): each vehicle's channel sources and
    rates (sources_lines), then what it received and lost, and the other counts that
    are not zero (the JSON's `link` has them all, and each link's), wrapped to
    TERMINAL_WIDTH columns."""
    shown = [
        f"{k} {v}"
        for k, v in link.items()
        if k not in ("vehicles", "sources")
        and (k in LINK_ALWAYS or (isinstance(v, int | float) and v != 0))
    ]
    lines = sources_lines(link.get("sources") or {})
    return "\n".join([*lines, wrap("link: " + ", ".join(shown))])


def sources_lines(sources: Mapping[str, Any]) -> list[str]:
    """Per vehicle: which message each channel came from at what mean rate ("!": too
    slow, channel_sources.MIN_RATE_HZ), the warnings, how the servo outputs were read,
    and what alpha is where it is ArduPilot's AHRS estimate."""
    out: list[str] = []
    for sid, entry in sources.items():
        channels = entry.get("channels") or {}
        line = rates_line(channels)
        if line:
            out.append(wrap(f"channels of system id {sid}: {line}"))
        for key, ch in channels.items():
            if "warning" in ch:
                out.append(wrap(f"warning: {key} from {ch['message']}: {ch['warning']}"))
        if "servos" in entry:
            out.append(wrap(f"servos of system id {sid}: {entry['servos']}"))
        if "alpha_note" in entry:
            out.append(wrap(f"note: {entry['alpha_note']}"))
    return out


LINK_ALWAYS = ("received", "lost")
"""The link's counts shown even at zero."""


def results_stem(system_id: int) -> str:
    """The stem of a link session's result files of one vehicle."""
    return f"results_sys{system_id}"


def vehicle_heading(vehicle: VehicleResult, elapsed_s: float) -> str:
    """A link session's heading of a vehicle's table."""
    return f"vehicle {vehicle.system_id}: {vehicle.result.frames} frames in {elapsed_s:.2f} s"


STATUS_WIDTH = TERMINAL_WIDTH
"""Columns a status line may take."""


class StatusSink:
    """Status lines every `every_s` seconds (a header, then a line per vehicle, each at
    most STATUS_WIDTH columns): redrawn in place on a terminal, else printed ten times
    as rarely."""

    def __init__(
        self,
        lines: Callable[[float], list[str]],
        out: TextIO | None = None,
        every_s: float = 1.0,
    ) -> None:
        self.lines = lines
        self.out = sys.stderr if out is None else out
        self.tty = self.out.isatty()
        self.every_s = every_s if self.tty else 10 * every_s
        self.start = time.time()
        self.last = 0.0
        self._drawn = 0
        """Lines on the terminal from the last draw."""

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def tick(self) -> None:
        now = time.time()
        if now - self.last < self.every_s:
            return
        self.last = now
        lines = [line[:STATUS_WIDTH] for line in self.lines(now - self.start)]
        if not self.tty:
            print("\n".join(lines), file=self.out, flush=True)
            return
        # Back to the start of the last draw, write the lines over it, clear what is
        # left of a longer one, and stay at the end of the last line.
        text = "\r" + (f"\033[{self._drawn - 1}A" if self._drawn > 1 else "")
        text += "\n".join("\033[K" + line for line in lines)
        extra = self._drawn - len(lines)
        if extra > 0:
            text += "\n\033[K" * extra + f"\033[{extra}A"
        print(text, end="", file=self.out, flush=True)
        self._drawn = len(lines)

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        if self.tty and self._drawn:
            print(file=self.out)


def _size(n: float, unit: str) -> str:
    if unit == "bytes":
        return f"{n / 1e6:.1f}"
    return f"{n:,.0f}"


def _duration(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 3600:
        return f"{seconds // 60:.0f} min {seconds % 60:02.0f} s"
    return f"{seconds // 3600:.0f} h {seconds % 3600 // 60:02.0f} min"


class ProgressSink:
    """A progress bar over a source that knows its length (a recording, a tlog), with
    its rate and the time left."""

    def __init__(
        self,
        progress: Callable[[], tuple[int, int]],
        label: str,
        out: TextIO | None = None,
        unit: str = "bytes",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.progress = progress
        self.label = label
        self.out = sys.stderr if out is None else out
        self.unit = unit
        """What progress() counts: "bytes" (shown in MB) or a name such as "frames"."""
        self.clock = clock
        self.start = clock()
        self.shown = -1
        self._last_draw = -math.inf

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def line(self) -> str:
        """The bar, the amount done, the rate and the time left."""
        done, total = self.progress()
        pct = int(100 * done / total) if total else 0
        bar = "#" * (pct // 4)
        unit = "MB" if self.unit == "bytes" else self.unit
        amount = f"{_size(done, self.unit)}/{_size(total, self.unit)} {unit}"
        text = f"{self.label} [{bar:<25}] {pct:3d} % {amount}"
        elapsed = self.clock() - self.start
        if done > 0 and elapsed > 0:
            rate = done / elapsed
            text += f", {_size(rate, self.unit)} {unit}/s"
            if total > done:
                text += f", {_duration((total - done) / rate)} left"
        return text[:STATUS_WIDTH]

    def tick(self) -> None:
        done, total = self.progress()
        pct = int(100 * done / total) if total else 0
        now = self.clock()
        if pct == self.shown and now - self._last_draw < 1.0:
            return
        self.shown, self._last_draw = pct, now
        print("\r\033[K" + self.line(), end="", file=self.out, flush=True)

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        if self.shown >= 0:
            print(file=self.out)


@dataclass(frozen=True)
class RefineAsk:
    """A whole-record fit asked for on the command line, as a results sink's `refine`
    (a value, so a filter worker can be given it)."""

    method: str
    window_s: tuple[float | None, float | None]
    hold_noise: bool
    failures: list[str] = field(default_factory=list, compare=False, repr=False)
    """Why the fit failed, a line per vehicle where it did (the run's exit status)."""

    def __call__(self, vehicle: VehicleResult) -> Refined | None:
        from gcs_estimator.refine import RefineError, choose_method, refine_run

        status = RefineStatus()
        try:
            method = self.method
            if method == "auto":
                method, why = choose_method(vehicle.result)
                method += f" ({why})"
            print(
                f"refining: {method} over {vehicle.result.frames} frames of vehicle "
                f"{vehicle.system_id} ...",
                file=sys.stderr,
                flush=True,
            )
            return refine_run(
                vehicle,
                self.method,
                window_s=self.window_s,
                progress=status,
                hold_noise=self.hold_noise,
            )
        except RefineError as exc:
            print(f"refine: {exc}", file=sys.stderr)
            self.failures.append(f"vehicle {vehicle.system_id}: {exc}")
            return None
        finally:
            status.end()


@dataclass(frozen=True)
class RunEnd:
    """The end of a run, the same for every command and every vehicle (decision 0063):
    the whole-record fit where asked (refine), the held-out check and the advice
    (checks), then the table, the JSON and Markdown and the rest of the history
    (ResultsSink.vehicle, in this order). A value: the command line makes one
    (cli.run_end), and a filter worker is given the same one for its vehicles."""

    refine: RefineAsk | None = None
    checks: Checks = field(default_factory=Checks)
    history_format: str = "parquet"
    """Each vehicle's history file: "parquet" or "csv" (tables.HISTORY_FORMATS)."""

    def sink(
        self,
        out_dir: Path,
        heading: Callable[[VehicleResult, float], str],
        elapsed: Callable[[], float],
        run: Callable[[], dict[str, Any]] | None,
        estimators: Callable[[], Mapping[int, Estimator]] | None,
        stem: Callable[[int], str] = results_stem,
    ) -> ResultsSink:
        """The results writer that ends the run so (stdout for the tables)."""
        return ResultsSink(
            out_dir,
            heading,
            stem,
            elapsed,
            refine=self.refine,
            run=run,
            estimators=estimators,
            history_format=self.history_format,
            checks=self.checks,
        )

    def failures(self) -> list[str]:
        """Why the whole-record fit failed, a line per vehicle where it did (the run's
        exit status)."""
        return [] if self.refine is None else list(self.refine.failures)


class RefineStatus:
    """Where a whole-record fit stands (refine's progress callback): redrawn in place on
    a terminal at most every `every_s`, else a line at most every ten times that; a
    final line when it is done (end)."""

    def __init__(
        self,
        out: TextIO | None = None,
        every_s: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.out = sys.stderr if out is None else out
        self.tty = self.out.isatty()
        self.every_s = every_s if self.tty else 10 * every_s
        self.clock = clock
        self.start = clock()
        self.last = -math.inf
        self.latest: RefineProgress | None = None

    def line(self, p: RefineProgress) -> str:
        step = f"last step {p.step_sigma:.2g} σ" if p.step_sigma > 0 else "no step taken"
        return (
            f"refining: iteration {p.iterations}, cost {p.cost:.6g}, {step}, "
            f"{p.runs} filter runs, {_duration(self.clock() - self.start)}"
        )[:STATUS_WIDTH]

    def __call__(self, p: RefineProgress) -> None:
        self.latest = p
        now = self.clock()
        if now - self.last < self.every_s:
            return
        self.last = now
        self._draw(p)

    def _draw(self, p: RefineProgress) -> None:
        if self.tty:
            print("\r\033[K" + self.line(p), end="", file=self.out, flush=True)
        else:
            print(self.line(p), file=self.out, flush=True)

    def end(self) -> None:
        """The fit is over: its last state drawn, and the line ended on a terminal."""
        if self.latest is not None:
            self._draw(self.latest)
            if self.tty:
                print(file=self.out, flush=True)
