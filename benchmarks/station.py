"""Start `gcs-estimator listen` as its own process and learn the port it bound (for the
benchmarks that drive a real station over UDP)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent


def start_listen(*args: str) -> tuple[subprocess.Popen[str], int]:
    """listen on udpin:127.0.0.1:0 with args; (the process, the port it bound), read from
    its listening line (it exits the benchmark with listen's output if none comes)."""
    station = subprocess.Popen(
        [str(BIN / "gcs-estimator"), "listen", "udpin:127.0.0.1:0", *args],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert station.stderr is not None
    for line in station.stderr:
        if line.startswith("listening on"):
            return station, int(line.split()[3].rstrip(",").rsplit(":", 1)[1])
    raise SystemExit(f"listen did not start: {station.stderr.read()}")
