"""The demo's recording in a browser: how long Rerun's web viewer takes to show all of it.

    ./run bench webview [--seconds 60] [--screenshot docs/view.png]

Simulates the demo's flight into an .rrd (the view as `simulate --view save` writes it),
serves it with `rerun --serve-web`, opens it in headless Chromium (software rendering),
and takes a screenshot every second until two in a row are the same: the time that took
is the load time (target: within 20 s for a 60 s recording). A 2 s flight first gives
the viewer's own start-up. Prints each recording's size (per hour of flight:
`./run bench replay --view`), and writes the final screenshot (the README's picture). Needs Debian's
`chromium`.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import record  # benchmarks/record.py: the script's directory is on sys.path

sys.path.insert(0, str(record.ROOT))
from tests.view.browser import CHROMIUM, load_until_steady, served


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="flight length")
    ap.add_argument(
        "--screenshot", default=str(record.ROOT / "docs" / "view.png"), help="the picture's path"
    )
    record.add_argument(ap, "webview")
    args = ap.parse_args(argv)
    if CHROMIUM is None:
        print("webview: needs chromium (Debian: apt-get install chromium)", file=sys.stderr)
        return 2
    with record.recorded("webview", args.record, "The demo's recording in the web viewer"):
        return run(args)


def run(args: argparse.Namespace) -> int:
    png = b""
    for seconds in (BOOT_FLIGHT_S, args.seconds):
        size, shown, png = _load(seconds)
        print(
            f"{seconds:g} s flight: .rrd {size / 1e6:.2f} MB; the web viewer showed all of it "
            f"after {shown:.1f} s"
        )
    print(
        f"(the {BOOT_FLIGHT_S:g} s flight is the viewer's own start-up under software "
        "rendering; the difference is the recording's loading)"
    )
    Path(args.screenshot).write_bytes(png)
    print(f"screenshot of the {args.seconds:g} s flight: {args.screenshot}")
    return 0


BOOT_FLIGHT_S = 2.0


def _load(seconds: float) -> tuple[int, float, bytes]:
    """(.rrd bytes, seconds until the web viewer stood still, its screenshot) of a
    simulated flight this long."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        subprocess.run(
            [sys.executable, "-m", "gcs_estimator", "simulate", "--view", "save", "--out", str(out),
             "--set", f"simulation.manoeuvre.duration_s={seconds:g}"],
            check=True, capture_output=True,
        )  # fmt: skip
        rrd = out / "view.rrd"
        with served(rrd) as url:
            png, shown = load_until_steady(url, timeout_s=180.0)
        return rrd.stat().st_size, shown, png


if __name__ == "__main__":
    sys.exit(main())
