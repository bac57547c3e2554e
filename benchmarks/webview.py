"""The demo's recording in a browser: how long Rerun's web viewer takes to show all of it.

    ./run bench webview [--seconds 60] [--runs 3] [--screenshot docs/view.png]

Simulates the demo's flight into an .rrd (the view as `simulate --view save` writes it),
serves it with `rerun --serve-web`, opens it in headless Chromium (software rendering),
and takes a screenshot every second until two in a row are the same: the time that took
is the load time (target: within 20 s for a 60 s recording). A recording of one scalar
gives the viewer's own start-up, this project's layout with no data what the layout
alone adds, and a 2 s flight what drawing the first data adds. Each is timed in a
browser opening the viewer for the first time (a fresh profile: the viewer's code
compiled on the spot), then the 60 s flight again in a browser that has opened the
viewer before, as a user's browser has after its first visit. Prints each recording's
size (per hour of flight: `./run bench replay --view`), and writes the final screenshot
(the README's picture). Needs Debian's `chromium`.
"""

from __future__ import annotations

import argparse
import contextlib
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import record  # benchmarks/record.py: the script's directory is on sys.path

sys.path.insert(0, str(record.ROOT))
from tests.view.browser import CHROMIUM, load_until_steady, served


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="flight length")
    ap.add_argument("--runs", type=int, default=3, help="loads timed of each case")
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
    assert CHROMIUM is not None
    browser = subprocess.run([CHROMIUM, "--version"], capture_output=True, text=True)
    print(f"browser: {browser.stdout.strip()} (headless, software rendering)")
    with tempfile.TemporaryDirectory() as tmp:
        _, times = _loads(_bare(Path(tmp) / "bare.rrd"), args.runs)
        print(f"a recording of one scalar (the web viewer alone): shown after {_spread(times)}")
        _, times = _loads(_layout_only(Path(tmp) / "layout.rrd"), args.runs)
        print(f"this project's layout and no data: shown after {_spread(times)}")
        boot = _flight(BOOT_FLIGHT_S, Path(tmp) / "boot")
        rrd = _flight(args.seconds, Path(tmp) / "flight")
        for path, seconds in ((boot, BOOT_FLIGHT_S), (rrd, args.seconds)):
            _, times = _loads(path, args.runs)
            print(
                f"{seconds:g} s flight: .rrd {path.stat().st_size / 1e6:.2f} MB; a browser "
                f"opening the web viewer for the first time showed all of it after "
                f"{_spread(times)}"
            )
        png, times = _loads(rrd, args.runs, visited=boot)
        print(
            f"{args.seconds:g} s flight in a browser that has opened the web viewer before "
            f"(its code compiled and cached; the page on a server of its own): all of it "
            f"after {_spread(times)}"
        )
    print(
        f"(target: within 20 s for the {args.seconds:g} s flight, under software rendering; "
        f"the {BOOT_FLIGHT_S:g} s flight against the layout with no data: what drawing "
        "the panels' first data costs; the longer flight against it: the recording's "
        "loading)"
    )
    Path(args.screenshot).write_bytes(png)
    print(f"screenshot of the {args.seconds:g} s flight: {args.screenshot}")
    return 0


def _loads(path: Path, runs: int, visited: Path | None = None) -> tuple[bytes, list[float]]:
    """Time `runs` loads of a recording in a fresh browser (one that has first opened
    `visited`, served on its own, when given); the last screenshot and the times."""
    times = []
    png = b""
    for _ in range(runs):
        with contextlib.ExitStack() as stack:
            before = None if visited is None else stack.enter_context(served(visited))
            url = stack.enter_context(served(path))
            png, shown = load_until_steady(url, timeout_s=180.0, visited=before)
        times.append(shown)
    return png, times


def _spread(times: list[float]) -> str:
    """min / median / max of a few timings (the machine is noisy)."""
    t = sorted(times)
    return f"{t[0]:.1f} / {t[len(t) // 2]:.1f} / {t[-1]:.1f} s (min / median / max of {len(t)})"


BOOT_FLIGHT_S = 2.0


def _bare(path: Path) -> Path:
    """A recording of ten values of one scalar and no layout: what the viewer takes to
    start whatever it shows."""
    import rerun as rr

    rec = rr.RecordingStream("webview-bare")
    rec.save(str(path))
    for i in range(10):
        rec.set_time("t", duration=0.1 * i)
        rec.log("x", rr.Scalars(float(i)))
    rec.flush()
    return path


def _layout_only(path: Path) -> Path:
    """A recording of the demo's layout (its blueprint) and no data at all."""
    import rerun as rr

    from gcs_estimator.config import load_config
    from gcs_estimator.outputs.view.layout import build_blueprint

    config = load_config("noc_uav")
    rec = rr.RecordingStream("webview-layout")
    rec.save(str(path))
    blueprint: Any = build_blueprint(
        [1], config.coefficient_names, config.structure.axes, "throttle"
    )  # the layout's builder keeps rerun's types out of its signature
    rec.send_blueprint(blueprint)
    rec.flush()
    return path


def _flight(seconds: float, out: Path) -> Path:
    """The .rrd of a simulated flight this long, as `simulate --view save` writes it."""
    subprocess.run(
        [sys.executable, "-m", "gcs_estimator", "simulate", "--view", "save", "--out", str(out),
         "--set", f"simulation.manoeuvre.duration_s={seconds:g}"],
        check=True, capture_output=True,
    )  # fmt: skip
    return out / "view.rrd"


if __name__ == "__main__":
    sys.exit(main())
