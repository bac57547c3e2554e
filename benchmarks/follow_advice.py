"""Whether following the warnings' advice keeps the marks honest where the answer is known
(decisions 0085, 0087, 0088).

    ./run bench follow_advice [--seeds 5] [--cases missed-gusts gusts calm]

The simulated NOC UAV flies its paper flight (60 s, 3-2-1-1 multisteps) as a MAVLink
vehicle into a .tlog, and the tlog is replayed with `--follow-advice` (cli.follow_advice):
as given, then again with what each run's warnings advise, until nothing new is advised.
The cases:

- missed-gusts: light turbulence, the filters told the air is calm
  (`filter.turbulence.adaptive=false`): a model that misses random motion, which the
  advice (the filter-error fit's process noise) is for;
- gusts: light turbulence with the defaults (the filters' own gust level);
- calm: calm air with the defaults, where nothing should be advised.

Per case and round, over the seeds that reached it: each filter's mean NIS over its
channels (1 expected), the coefficients within 3 of the sigma shown of the truth, the
largest |error| in sigmas, the coefficients marked identified and those beyond 3 sigma.
"Last" is each seed's last round, the run a user reads.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path
from slow_inputs import quiet

from gcs_estimator.cli import ADVICE_FILE
from gcs_estimator.cli import main as gcs_main
from gcs_estimator.config import load_truths
from gcs_estimator.outputs.diagnosis import set_argv
from gcs_estimator.uncertainty.metrics import IDENTIFIED
from sim.cli import main as sim_main
from sim.formats import truth_path

FLIGHT_S = 60.0
"""Each flight's length [s]: the paper's manoeuvres."""
CASES: dict[str, tuple[list[str], list[str]]] = {
    "missed-gusts": (
        ['simulation.turbulence.preset="light"'],
        ["filter.turbulence.adaptive=false"],
    ),
    "gusts": (['simulation.turbulence.preset="light"'], []),
    "calm": ([], []),
}
"""Per case: the simulator's --set overrides, then the replay's."""


@dataclass
class Round:
    """One round's figures, pooled over the seeds that reached it."""

    seeds: int = 0
    nis: dict[str, list[float]] = field(default_factory=lambda: {"EKF": [], "IEKF": []})
    z: list[float] = field(default_factory=list)
    marked: int = 0
    wrong: int = 0
    beyond: list[str] = field(default_factory=list)
    """Each coefficient marked identified beyond 3 sigma: seed, filter, name, z."""

    def add(self, res: dict[str, Any], truth: np.ndarray, seed: int = 0) -> None:
        self.seeds += 1
        names = res["coefficients"]
        for kind in ("EKF", "IEKF"):
            f = res["filters"][kind]
            self.nis[kind].append(f["mean_nis"] / f["mean_channels"])
            for i, name in enumerate(names):
                e = f["estimates"][name]
                z = (e["estimate"] - truth[i]) / e["sigma"]
                self.z.append(z)
                self.marked += e["identifiability"] == IDENTIFIED
                if e["identifiability"] == IDENTIFIED and abs(z) > 3.0:
                    self.wrong += 1
                    self.beyond.append(f"seed {seed} {kind} {name} {z:+.1f}")

    def row(self, label: str) -> str:
        z = np.abs(np.array(self.z))
        return (
            f"| {label} | {self.seeds} | {np.mean(self.nis['EKF']):.2f} "
            f"| {np.mean(self.nis['IEKF']):.2f} | {100 * np.mean(z <= 3.0):.0f} % "
            f"| {z.max():.1f} | {self.marked} of {z.size} | {self.wrong} |"
        )


def case(name: str, seeds: int, folder: Path) -> None:
    flown, told = CASES[name]
    print(f"## {name}\n")
    print(f"- simulator: {' '.join(flown) or 'defaults'}; replays: {' '.join(told) or 'defaults'}")
    rounds: dict[str, Round] = {}
    stops: list[str] = []
    advised: list[str] = []
    applied: list[str] = []
    for seed in range(1, seeds + 1):
        stem = folder / f"{name}_s{seed}"
        argv = ["--speed", "0", "--seed", str(seed), "--tlog", str(stem)]
        argv += ["--set", f"simulation.manoeuvre.duration_s={FLIGHT_S:g}"]
        for s in flown:
            argv += ["--set", s]
        if quiet(sim_main, argv) != 0:
            raise SystemExit(f"the simulator failed: {name}, seed {seed}")
        tlog = stem.parent / f"{stem.name}_1.tlog"
        out = stem.parent / f"{stem.name}_out"
        replay = ["replay", str(tlog), "--view", "off", "--out", str(out), "--follow-advice"]
        for s in told:
            replay += ["--set", s]
        status = quiet(gcs_main, replay)
        if status != 0:
            raise SystemExit(f"the replay of {name}, seed {seed} exited {status}")
        account = json.loads((out / ADVICE_FILE).read_text(encoding="utf-8"))
        for entry in account["rounds"]:
            (path,) = sorted((out / entry["folder"]).glob("results_sys*.json"))
            res = json.loads(path.read_text(encoding="utf-8"))
            truth = np.array(load_truths(truth_path(tlog), res["coefficients"])[1])
            rounds.setdefault(f"round {entry['round']}", Round()).add(res, truth, seed)
            if entry is account["rounds"][-1]:
                rounds.setdefault("last", Round()).add(res, truth, seed)
                applied.append(f"seed {seed}: {_shown(entry)}")
            advised += [k for k in entry.get("advised", {}) if k not in advised]
        stops.append(f"{len(account['rounds'])} ({account['rounds'][-1]['stopped']})")
    print(f"- rounds per seed: {'; '.join(stops)}")
    print(f"- settings advised in some round: {', '.join(advised) or 'none'}\n")
    print(
        "| round | seeds | EKF NIS / channels | IEKF NIS / channels | within 3σ | max abs z "
        "| identified | identified beyond 3σ |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label in sorted(rounds, key=lambda r: (r == "last", r)):
        print(rounds[label].row(label))
    print()
    print("Each seed's last round ran with:\n")
    for line in applied:
        print(f"- {line}")
    print(
        f"\nIdentified beyond 3σ in the last round: {'; '.join(rounds['last'].beyond) or 'none'}\n"
    )


def _shown(entry: dict[str, Any]) -> str:
    """What a round applied, as the command line takes it."""
    parts = set_argv(entry["applied"])[1::2]
    if entry["refine"] is not None:
        parts.append(f"--refine {entry['refine']}")
    return " ".join(parts) or "as given"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    record.add_argument(ap, "follow_advice")
    args = ap.parse_args()
    with (
        record.recorded("follow_advice", args.record, "Following the warnings' advice"),
        tempfile.TemporaryDirectory() as tmp,
    ):
        for name in args.cases:
            case(name, args.seeds, Path(tmp))
        print(
            f"{args.seeds} seed(s) of {FLIGHT_S:g} s each; NIS over channels: 1 expected; "
            "within 3σ and max abs z over both filters' coefficients against the truth, "
            "with the σ shown."
        )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
