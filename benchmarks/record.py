"""Benchmarks keep what they print: docs/results/NAME.md, with the command, date and machine.

The docs link these files rather than copying figures into prose, so a figure always sits
next to the command and the revision that produced it. `./run bench all` (benchmarks/all.py)
writes every record at one revision; `--record none` writes nothing. Paths under the
project are written relative to it: a record holds nothing of the machine's folders.
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


OUTPUTS = ("docs/results/", "docs/view.png")
"""What the benchmarks write (their records, the README's picture) is not what they
measure: changes there do not make a tree "with local changes"."""


def git(*args: str) -> str:
    """A git command's output in the project, "" if git fails."""
    try:
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
    except OSError:
        return ""
    return out.stdout.rstrip() if out.returncode == 0 else ""  # porcelain lines start with " "


def tree_revision() -> tuple[str, list[str]]:
    """The commit checked out ("unknown" outside git) and the paths changed or added on top
    of it, the benchmarks' outputs aside."""
    changed = [
        line[3:]
        for line in git("status", "--porcelain", "--untracked-files=normal").splitlines()
        if not line[3:].startswith(OUTPUTS)
    ]
    return git("rev-parse", "--short", "HEAD") or "unknown", changed


def revision() -> str:
    """The commit measured, and whether the tree had changes on top of it."""
    head, changed = tree_revision()
    return f"{head}{' with local changes' if changed else ''}"


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
    text = buffer.getvalue().replace(f"{ROOT}{os.sep}", "").strip()
    path.write_text(head + text + "\n", encoding="utf-8")
    shown = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    print(f"(written to {shown})", file=sys.stderr)
