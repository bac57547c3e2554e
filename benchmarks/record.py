"""Benchmarks keep what they print: docs/results/NAME.md, with the command, date and machine.

The README links these files rather than copying figures into prose, so a figure always
sits next to the command that produced it. `--record none` writes nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Iterator
from importlib.metadata import version
from pathlib import Path
from typing import TextIO

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"


def add_argument(ap: argparse.ArgumentParser, default: str) -> None:
    ap.add_argument(
        "--record",
        default=default,
        metavar="NAME",
        help="write the output to docs/results/NAME.md (default: %(default)s; none: do not)",
    )


class _Tee(io.TextIOBase):
    def __init__(self, *streams: TextIO) -> None:
        self.streams = streams

    def write(self, s: str) -> int:
        for stream in self.streams:
            stream.write(s)
        return len(s)

    def flush(self) -> None:
        for stream in self.streams:
            stream.flush()


def machine() -> str:
    """CPU, cores, OS and the versions that decide the figures."""
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    libs = ", ".join(f"{m} {version(m)}" for m in ("numpy", "numba", "pymavlink", "rerun-sdk"))
    return (
        f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.release()}; "
        f"Python {platform.python_version()}, {libs}"
    )


def revision() -> str:
    """The commit measured, and whether the tree had changes on top of it (other than the
    benchmarks' own outputs)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        # What the benchmarks write (their records, the README's picture) is not what
        # they measure: changes there do not make a revision "with local changes".
        outputs = [":(exclude)docs/results", ":(exclude)docs/view.png"]
        dirty = (
            subprocess.run(
                ["git", "diff", "--quiet", "HEAD", "--", ".", *outputs], cwd=ROOT
            ).returncode
            != 0
        )
    except OSError:
        return "unknown"
    return f"{head}{' with local changes' if dirty else ''}" if head else "unknown"


@contextlib.contextmanager
def recorded(script: str, name: str, title: str) -> Iterator[None]:
    """Print as usual, and on success also write docs/results/NAME.md."""
    measured = revision()  # before the run: a benchmark may write tracked files (a picture)
    buffer = io.StringIO()
    stdout = sys.stdout
    sys.stdout = _Tee(stdout, buffer)
    try:
        yield
    finally:
        sys.stdout = stdout
    if name == "none":
        return
    command = " ".join(["./run bench", script, *map(shlex.quote, sys.argv[1:])])
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    head = (
        f"# {title}\n\n"
        f"- command: `{command}`\n- date: {now}\n- revision: {measured}\n"
        f"- machine: {machine()}\n\n"
    )
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.md"
    path.write_text(head + buffer.getvalue().strip() + "\n")
    print(f"(written to {path.relative_to(ROOT)})", file=sys.stderr)
