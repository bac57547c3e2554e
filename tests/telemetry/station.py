"""Start `gcs-estimator listen` as a process of its own, as a user would, and wait for it
to say it listens (its kernels compiled, its handlers installed)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def start_listen(*args: str, own_group: bool = False) -> tuple[subprocess.Popen[str], str]:
    """`listen` with args; (the process, its listening line). Its stdout and the rest of
    its stderr are left for communicate(). own_group: in a process group of its own, with
    the processes it starts (a terminal's Ctrl-C goes to all of them)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "gcs_estimator", "listen", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        process_group=0 if own_group else None,
    )
    assert proc.stderr is not None
    for line in proc.stderr:
        if line.startswith("listening on"):
            return proc, line
    _out, err = proc.communicate(timeout=60)
    raise AssertionError(f"listen never said it listens: {err}")


def bound_port(line: str) -> int:
    """The port a listening line names (udpin:HOST:0 binds any free one)."""
    found = re.search(r":(\d+)\b", line)
    assert found, line
    return int(found.group(1))
