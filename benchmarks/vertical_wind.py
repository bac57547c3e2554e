"""Why the NOC mission in light turbulence without a vane is not identified: what the data
hold against what the filters' passes find (issue 53's NOC target, decision 0075).

    ./run bench vertical_wind [--seeds 3] [--minutes 8] [--record NAME|none]

Each seed flies noc_mission's light-turbulence mission with the vane's alpha left out
(alpha from the climb rate, decision 0049), runs it as the project does (both filters,
the restarts, the structure check off: it does not move the estimates), once with the
default white gust noise and once with the gust states (`[filter.turbulence] model =
"states"`), and then replays that run's final pass (Estimator.replay_final_pass: the same
frames, settings and gust start) from other coefficient starts:

- likelihood: the pass's -2 log likelihood with the coefficients held (prior sigma
  1e-7) at the run's final estimates and at the truth. A positive "held at truth is
  better by" says the data favour the truth: the filters have ended away from what the
  record holds, a matter of where the passes go, not of what the flight can tell.
- from truth: the pass started at the truth with a prior sigma of f |truth| (f = 0.3,
  1, 3): where CLa and Cma end (over truth) and the largest |error| in the filter's own
  sigma. Whether a pass that starts in the truth's basin stays there, and how far it
  drifts along the confound of alpha's scale with the vertical wind.
- equation error: the warm start's fit (warmstart.equation_error, the restarts' first
  start) over the whole record: CLa and Cma over truth. Alpha from the climb rate is the
  motion over the ground's; the aerodynamics see the air's, which the vertical wind
  moves by w_g / V, about 1.8 deg RMS in light turbulence against the mission's
  0.7 deg of alpha it flies.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections.abc import Mapping

import numpy as np
from record import add_argument, recorded

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import Estimator
from gcs_estimator.estimation.filters.core import FILTER_KINDS, FilterKind
from gcs_estimator.estimation.passes import Start
from gcs_estimator.estimation.warmstart import equation_error
from gcs_estimator.model.channels import Channel
from gcs_estimator.runtime.session import BATCH_BLOCK_FRAMES, RecordingSource, Session
from sim.scenario import mission
from sim.truth import simulate

MODELS = (("white", ()), ("states", ("filter.turbulence.model=states",)))
"""(label, overrides): the filters' two turbulence models."""
WIDTHS = (0.3, 1.0, 3.0)
"""Prior sigma of the starts from truth, as a share of |truth|."""
HELD = 1e-7
"""Prior sigma that holds the coefficients where they start."""
SHOWN = ("CLa", "Cma")


def _run(config: AircraftConfig, t: FloatArray, u: FloatArray, y: FloatArray) -> Estimator:
    """The recording through the project's session (no history kept beyond the run's)."""
    session = Session(config, keep_history=True, block_frames=BATCH_BLOCK_FRAMES)
    session.run(RecordingSource(t, u, y))
    return session.estimators[RecordingSource.SYSTEM_ID]


def _replay(
    est: Estimator, frames: tuple[FloatArray, ...], start: dict[FilterKind, Start]
) -> Estimator:
    """est's final pass replayed from `start` (per filter), its likelihood summed."""
    again = Estimator(est.config, backend=est.backend, keep_history=False)
    again.runner.likelihood = {}
    source = copy.copy(est)
    source.runner = copy.copy(est.runner)
    source.runner.starts = dict(start)
    again.replay_final_pass(source, *frames)
    return again


def _starts(
    est: Estimator,
    coefficients: Mapping[FilterKind, FloatArray],
    sigma: Mapping[FilterKind, FloatArray],
) -> dict[FilterKind, Start]:
    """Starts at these coefficients and sigmas with the run's gust start."""
    return {
        k: Start(coefficients[k], sigma[k], est.runner.starts[k].gust_var) for k in FILTER_KINDS
    }


def _seed(base: list[str], seed: int) -> list[str]:
    """One seed's rows for both turbulence models (base: the mission's overrides)."""
    config = load_config("noc_uav", base)
    flight = simulate(config, seed=seed)
    truth = flight.truth
    y = flight.measurements.copy()
    y[:, Channel.ALPHA] = np.nan
    rows: list[str] = []
    for label, extra in MODELS:
        cfg = load_config("noc_uav", [*base, *extra])
        est = _run(cfg, np.asarray(flight.t_s, float), flight.inputs, y)
        frames = est.frame_history.arrays()
        names = est.names
        coef = est.model.coefficients
        final = {k: est.states[k].x[coef].copy() for k in FILTER_KINDS}  # type: ignore[union-attr]
        held = {k: np.full(len(truth), HELD) for k in FILTER_KINDS}
        at_est = _replay(est, frames, _starts(est, final, held)).runner.likelihood or {}
        at_truth = _replay(est, frames, _starts(est, dict.fromkeys(FILTER_KINDS, truth), held))
        like_truth = at_truth.runner.likelihood or {}
        ia, ma = names.index(SHOWN[0]), names.index(SHOWN[1])
        for kind in FILTER_KINDS:
            x = final[kind]
            state = est.states[kind]
            assert state is not None
            own = np.sqrt(np.diag(state.P))[coef]
            cells = [
                f"{x[ia] / truth[ia]:.2f}",
                f"{x[ma] / truth[ma]:.2f}",
                f"{np.max(np.abs((x - truth) / own)):.0f}",
                f"{at_est[kind] - like_truth[kind]:+,.0f}",
            ]
            for f in WIDTHS:
                wide = {k: f * np.abs(truth) + 1e-3 for k in FILTER_KINDS}
                again = _replay(est, frames, _starts(est, dict.fromkeys(FILTER_KINDS, truth), wide))
                s = again.states[kind]
                assert s is not None
                xe, se = s.x[coef], np.sqrt(np.diag(s.P))[coef]
                cells.append(
                    f"{xe[ia] / truth[ia]:.2f} / {xe[ma] / truth[ma]:.2f} / "
                    f"{np.max(np.abs((xe - truth) / se)):.0f}"
                )
            rows.append(f"| {seed} | {label} | {kind} | " + " | ".join(cells) + " |")
    t, u, yh = frames
    fit = equation_error(
        est.model,
        t,
        est.model.inputs_of(u),
        yh,
        np.zeros(len(truth)),
        np.array(config.filter.initial_sigma.coefficients),
    )
    ia, ma = est.names.index(SHOWN[0]), est.names.index(SHOWN[1])
    rows.append(
        f"| {seed} | equation error, whole record | | {fit.beta[ia] / truth[ia]:.2f} | "
        f"{fit.beta[ma] / truth[ma]:.2f} | | | | | |"
    )
    return rows


def run(seeds: int, minutes: float) -> None:
    base = [*mission("light", 60.0 * minutes), 'filter.structure_check="off"']
    print(
        f"NOC mission of {minutes:g} min in light turbulence, no vane, {seeds} seed(s); "
        "ratios are estimate over truth\n"
    )
    head = [f"from truth, σ {f:g}|truth|: CLa / Cma / max z" for f in WIDTHS]
    print(
        "| seed | gust model | filter | CLa | Cma | max \\|z\\| (own σ) | "
        "-2 log L held at the estimate less held at truth | " + " | ".join(head) + " |"
    )
    print("|---|---|---|---:|---:|---:|---:|" + "---:|" * len(WIDTHS))
    start = time.perf_counter()
    for seed in range(1, seeds + 1):
        for row in _seed(base, seed):
            print(row, flush=True)
    print(f"\n({time.perf_counter() - start:.0f} s)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="seeds (default %(default)s)")
    ap.add_argument(
        "--minutes", type=float, default=8.0, help="mission length (default %(default)s)"
    )
    add_argument(ap, "vertical_wind")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.minutes <= 0:
        raise SystemExit("vertical_wind: --seeds must be 1 or more, --minutes positive")
    with recorded(
        "vertical_wind", args.record, "Light turbulence without a vane: what the data hold"
    ):
        run(args.seeds, args.minutes)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
