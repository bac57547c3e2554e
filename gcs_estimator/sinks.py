"""Sinks of a session besides the view: the results writer, the live status line and the
progress bar (session.Sink)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from gcs_estimator.estimator import FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.report import final_table, write_results
from gcs_estimator.session import VehicleResult

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined


class ResultsSink:
    """At the end: each vehicle's Table I on stdout and its JSON, Markdown and CSV files."""

    def __init__(
        self,
        out_dir: Path,
        heading: Callable[[VehicleResult, float], str],
        stem: Callable[[int], str],
        elapsed: Callable[[], float],
        out: TextIO | None = None,
        refine: Callable[[VehicleResult], Refined | None] | None = None,
        run: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        self.refine = refine
        self.run = run
        """What the JSON says of the run (version, command line, source, times)."""
        self.out_dir = out_dir
        self.heading = heading
        self.stem = stem
        self.elapsed = elapsed
        self.out = sys.stdout if out is None else out

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        if not results:
            print("no vehicle data received", file=sys.stderr)
        for sid, vehicle in results.items():
            heading = self.heading(vehicle, self.elapsed())
            refined = None if self.refine is None else self.refine(vehicle)
            print(f"\n{heading}\n", file=self.out)
            print(final_table(vehicle, refined), file=self.out)
            extra: dict[str, Any] = {"system_id": sid}
            if link is not None:
                extra["link"] = dict(link)
            if self.run is not None:
                extra["run"] = self.run()
            paths = write_results(self.out_dir, vehicle, extra, self.stem(sid), refined)
            print("results: " + ", ".join(str(p) for p in paths.values()), file=self.out)
        if link is not None:
            counts = ", ".join(f"{k} {v}" for k, v in link.items() if k != "vehicles")
            print("link: " + counts, file=self.out)


class StatusSink:
    """A status line every `every_s` seconds: in place on a terminal, else one line each
    ten times as rarely."""

    def __init__(
        self, line: Callable[[float], str], out: TextIO | None = None, every_s: float = 1.0
    ) -> None:
        self.line = line
        self.out = sys.stderr if out is None else out
        self.tty = self.out.isatty()
        self.every_s = every_s if self.tty else 10 * every_s
        self.start = time.time()
        self.last = 0.0

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def tick(self) -> None:
        now = time.time()
        if now - self.last < self.every_s:
            return
        self.last = now
        text = self.line(now - self.start)
        if self.tty:
            print("\r\033[K" + text, end="", file=self.out, flush=True)
        else:
            print(text, file=self.out, flush=True)

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        if self.tty:
            print(file=self.out)


class ProgressSink:
    """A progress bar over a source that knows its length (a recording, a tlog)."""

    def __init__(
        self, progress: Callable[[], tuple[int, int]], label: str, out: TextIO | None = None
    ) -> None:
        self.progress = progress
        self.label = label
        self.out = sys.stderr if out is None else out
        self.shown = -1

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def tick(self) -> None:
        done, total = self.progress()
        pct = int(100 * done / total) if total else 0
        if pct == self.shown:
            return
        self.shown = pct
        bar = "#" * (pct // 4)
        print(
            f"\r{self.label} [{bar:<25}] {pct:3d} % ({done}/{total})",
            end="",
            file=self.out,
            flush=True,
        )

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        if self.shown >= 0:
            print(file=self.out)
