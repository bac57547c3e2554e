"""A link whose servo outputs come slower than its sensors, and what a link's frames say of
its sensors (decision 0084).

    ./run bench slow_inputs [--seeds 3] [--rates 50 25 12.5 6.25] [--alfa FOLDER]

The simulated NOC UAV (its paper flight: 3-2-1-1 multisteps, elevator steps that land
between servo samples) flies as ArduPlane at the asked rates with SERVO_OUTPUT_RAW at each
--rates value, written as a tlog and replayed with no config (the truth file beside it).
Per rate, over the seeds: the frames whose input counted as a guess (a lost sample while
the input changed: its measurements dropped, its flight states restarted), each filter's
mean NIS over its channels, the coefficients within 3 of the sigma shown, the largest
|error| in sigmas, the coefficients marked identified, and those beyond 3 sigma.

With --alfa FOLDER (the public ALFA Carbon-Z T-28 ArduPlane flight: its .tlog and
carbonz_t28.toml, ../shared/data/real/alfa_carbonz_t28 beside the repository; nothing of it
is in the repository), the real flight is replayed as a user would, with its airframe file
and `--follow-advice`: as given, then again with what each run's warnings advise (its
JSON's diagnostics.advised_settings: the biases the frames' compatibility check finds
estimated, each channel's measurement sigma set to the noise the run read where it read
it clearly higher than configured; the whole-record filter-error fit where they ask for
it, then the process noise it finds where its residuals are white, decisions 0085 and
0087; the input delay), until nothing new is advised. Per round: each filter's mean NIS and its
channels' innovations' mean square over the predicted (1 expected), the frames counted as
guesses, what the compatibility check found beyond the noise, and the marks.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path

from gcs_estimator.cli import ADVICE_FILE
from gcs_estimator.cli import main as gcs_main
from gcs_estimator.config import load_truths
from gcs_estimator.outputs.diagnosis import set_argv
from gcs_estimator.uncertainty.metrics import IDENTIFIED
from sim.cli import main as sim_main
from sim.formats import truth_path

FLIGHT_S = 60.0
"""Each simulated flight's length [s]: the paper's manoeuvres."""


def quiet(call: Any, argv: list[str]) -> int:
    """A command's main, its output swallowed: its exit status."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return int(call(argv))


def _results(out: Path) -> dict[str, Any]:
    (path,) = sorted(out.glob("results_sys*.json"))
    data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return data


def _replay(tlog: Path, out: Path, extra: list[str]) -> None:
    status = quiet(gcs_main, ["replay", str(tlog), "--view", "off", "--out", str(out), *extra])
    if status != 0:
        raise SystemExit(f"replay of {tlog.name} exited {status}")


def simulated(seeds: int, rates: list[float], folder: Path) -> None:
    print("## The NOC UAV as ArduPlane, SERVO_OUTPUT_RAW slower than the sensors (50 Hz)\n")
    print(
        "| servo Hz | frames | guessed | EKF NIS / channels | IEKF NIS / channels | within 3σ "
        "| max abs z | identified | identified beyond 3σ |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for hz in rates:
        frames = guessed = 0
        nis: dict[str, list[float]] = {"EKF": [], "IEKF": []}
        z_all: list[float] = []
        wrong = marked = 0
        for seed in range(1, seeds + 1):
            stem = folder / f"servo{hz:g}_s{seed}"
            argv = ["--speed", "0", "--seed", str(seed), "--autopilot", "arduplane", "--asked"]
            argv += ["--set", f"simulation.manoeuvre.duration_s={FLIGHT_S:g}"]
            argv += ["--msg-rate", f"SERVO_OUTPUT_RAW={hz:g}", "--tlog", str(stem)]
            if quiet(sim_main, argv) != 0:
                raise SystemExit(f"the simulator failed at {hz:g} Hz, seed {seed}")
            tlog = stem.parent / f"{stem.name}_1.tlog"
            out = stem.parent / f"{stem.name}_out"
            _replay(tlog, out, [])
            res = _results(out)
            vehicle = res["link"]["vehicles"]["1"]
            frames += vehicle["frames"]
            guessed += vehicle["inputs_guessed"]
            names = res["coefficients"]
            truth = load_truths(truth_path(tlog), names)[1]
            for kind in ("EKF", "IEKF"):
                f = res["filters"][kind]
                nis[kind].append(f["mean_nis"] / f["mean_channels"])
                for i, name in enumerate(names):
                    e = f["estimates"][name]
                    z = (e["estimate"] - truth[i]) / e["sigma"]
                    z_all.append(z)
                    marked += e["identifiability"] == IDENTIFIED
                    wrong += e["identifiability"] == IDENTIFIED and abs(z) > 3.0
        z = np.abs(np.array(z_all))
        print(
            f"| {hz:g} | {frames} | {guessed} | {np.mean(nis['EKF']):.2f} "
            f"| {np.mean(nis['IEKF']):.2f} | {100 * np.mean(z <= 3.0):.0f} % "
            f"| {z.max():.1f} | {marked} of {len(z_all)} | {wrong} |"
        )
    print(
        f"\n{seeds} seed(s) of {FLIGHT_S:g} s each; NIS over channels: 1 expected; within 3σ "
        "and max abs z over both filters' coefficients against the truth, with the σ shown."
    )


def _alfa_line(label: str, res: dict[str, Any]) -> None:
    vehicle = res["link"]["vehicles"]["1"]
    print(f"### {label}\n")
    print(f"- frames {vehicle['frames']}, guessed {vehicle['inputs_guessed']}")
    for kind in ("EKF", "IEKF"):
        f = res["filters"][kind]
        ims = ", ".join(
            f"{n} {v:.2f}"
            for n, v in f["innovation_mean_square"].items()
            if v is not None and math.isfinite(v)
        )
        marks = [n for n, e in f["estimates"].items() if e["identifiability"] == IDENTIFIED]
        biases = ", ".join(
            f"{n} {b['estimate']:+.4g} ± {b['sigma']:.2g}" for n, b in f["sensor_biases"].items()
        )
        print(
            f"- {kind}: mean NIS {f['mean_nis']:.2f} over {f['mean_channels']:.2f} channels; "
            f"per channel {ims}; identified: {', '.join(marks) or 'none'}"
            + (f"; biases {biases}" if biases else "")
        )
    found = res["diagnostics"].get("compatibility") or {"findings": []}
    beyond = [
        f"{f['channel']} {f['kind']} {f['value']:+.4g} ± {f['sigma']:.2g} ({f['z']:+.1f} σ)"
        for f in found["findings"]
        if f["significant"]
    ]
    print(f"- compatibility check of the frames, beyond the noise: {'; '.join(beyond) or 'none'}")
    print(f"- what to fly next (IEKF): {_advice_line(res.get('advice'))}")
    print()


def _advice_line(advice: dict[str, Any] | None) -> str:
    """The run's advice in one line: the channels to sample faster, then each manoeuvre
    advised with the coefficients it is advised for (or why none was)."""
    if not advice:
        return "none given"
    parts = [f"faster data: {n} {r:.1f} Hz" for n, r in advice.get("slow_channels_hz", {}).items()]
    if advice.get("note"):
        return "; ".join([*parts, advice["note"]])
    by: dict[str, list[str]] = {}
    for a in advice.get("not_identified", []):
        by.setdefault(a["manoeuvre"]["label"], []).append(a["name"])
    parts += [f"{label} (for {', '.join(names)})" for label, names in by.items()]
    return "; ".join(parts) or "nothing: every coefficient is identified"


def alfa(folder: Path, work: Path) -> None:
    tlogs = sorted(folder.glob("*.tlog"))
    airframe = folder / "carbonz_t28.toml"
    if len(tlogs) != 1 or not airframe.is_file():
        raise SystemExit(f"--alfa {folder}: expected one .tlog and carbonz_t28.toml there")
    print("## The ALFA Carbon-Z T-28 ArduPlane flight (tlog)\n")
    print(
        f"`gcs-estimator replay {tlogs[0].name} --config {airframe.name} --follow-advice`: "
        "its rounds, each with the settings the rounds before it were advised\n"
    )
    out = work / "alfa"
    argv = ["--config", str(airframe), "--follow-advice"]
    _replay(tlogs[0], out, argv)
    account = json.loads((out / ADVICE_FILE).read_text(encoding="utf-8"))
    for entry in account["rounds"]:
        added = set_argv(entry["applied"]) + (
            [] if entry["refine"] is None else ["--refine", entry["refine"]]
        )
        label = f"round {entry['round']}: " + (
            "its airframe file as given" if not added else f"with {_shown(added)}"
        )
        _alfa_line(label, _results(out / entry["folder"]))
    last = account["rounds"][-1]
    print(f"- the rounds stopped: {last['stopped']}; the run to read: round {last['round']}\n")


def _shown(argv: list[str]) -> str:
    return " ".join(a for a in argv if a != "--set")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--rates", type=float, nargs="+", default=[50.0, 25.0, 12.5, 6.25])
    ap.add_argument("--alfa", type=Path, default=None, metavar="FOLDER")
    record.add_argument(ap, "slow_inputs")
    args = ap.parse_args()
    with (
        record.recorded("slow_inputs", args.record, "Slow servo outputs on a link"),
        tempfile.TemporaryDirectory() as tmp,
    ):
        work = Path(tmp)
        simulated(args.seeds, args.rates, work)
        print()
        if args.alfa is None:
            print("(no --alfa FOLDER: the real flight not replayed)")
        elif not args.alfa.is_dir():
            print(f"({args.alfa} not found: the real flight not replayed)")
        else:
            alfa(args.alfa, work)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
