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
- whole-record fit (--fit EKF [IEKF]): from the run's final estimates, the coefficients
  that make that filter's held pass likeliest (-2 log L minimised by L-BFGS-B, its
  gradient by differences, about --fit-passes passes at most): where CLa and Cma end (over
  truth), its -2 log L less the pass held at truth (negative: likelier than the truth),
  and the passes it took. Decision 0075 named this fit as what would unblock the case if
  its least lay at the truth; decision 0080 has what it found.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections.abc import Mapping

import numpy as np
from record import add_argument, recorded
from scipy.optimize import minimize

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
    est: Estimator,
    frames: tuple[FloatArray, ...],
    start: dict[FilterKind, Start],
    kinds: tuple[FilterKind, ...] = FILTER_KINDS,
) -> Estimator:
    """est's final pass replayed from `start` (per filter; those in `kinds`), its
    likelihood summed."""
    again = Estimator(est.config, backend=est.backend, keep_history=False)
    again.runner.likelihood = {}
    source = copy.copy(est)
    source.runner = copy.copy(est.runner)
    source.runner.starts = dict(start)
    t, u, y = frames
    again.replay_final_pass(source, t, u, y, kinds=kinds)
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


FIT_SCALE_FLOOR = 1e-2
"""The fit's variables are the coefficients over max(|start|, this)."""
FIT_STEP = 1e-5
"""The fit's difference step, in those variables."""


def _whole_record_fit(
    est: Estimator, frames: tuple[FloatArray, ...], kind: FilterKind, passes: int
) -> tuple[FloatArray, float, int, bool]:
    """From filter `kind`'s final estimate, the coefficients whose held pass is likeliest
    (module docstring): (coefficients, -2 log L there, passes run, converged)."""
    coef = est.model.coefficients
    state = est.states[kind]
    assert state is not None
    x0 = state.x[coef].copy()
    scale = np.maximum(np.abs(x0), FIT_SCALE_FLOOR)
    held = dict.fromkeys(FILTER_KINDS, np.full(x0.shape, HELD))
    runs = [0]

    def cost(z: FloatArray) -> float:
        runs[0] += 1
        x = z * scale
        again = _replay(est, frames, _starts(est, dict.fromkeys(FILTER_KINDS, x), held), (kind,))
        return float((again.runner.likelihood or {})[kind]) / 1e3

    sol = minimize(cost, x0 / scale, method="L-BFGS-B", options={"maxfun": passes, "eps": FIT_STEP})
    return np.asarray(sol.x) * scale, 1e3 * float(sol.fun), runs[0], bool(sol.success)


def _seed(base: list[str], seed: int, fit: tuple[FilterKind, ...], passes: int) -> list[str]:
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
            if fit:
                if kind in fit:
                    xf, lf, runs, done = _whole_record_fit(est, frames, kind, passes)
                    cells.append(
                        f"{xf[ia] / truth[ia]:.2f} / {xf[ma] / truth[ma]:.2f} / "
                        f"{lf - like_truth[kind]:+,.0f} / {runs}{'' if done else ' (stopped)'}"
                    )
                else:
                    cells.append("")
            rows.append(f"| {seed} | {label} | {kind} | " + " | ".join(cells) + " |")
    t, u, yh = frames
    eq_fit = equation_error(
        est.model,
        t,
        est.model.inputs_of(u),
        yh,
        np.zeros(len(truth)),
        np.array(config.filter.initial_sigma.coefficients),
    )
    ia, ma = est.names.index(SHOWN[0]), est.names.index(SHOWN[1])
    rows.append(
        f"| {seed} | equation error, whole record | | {eq_fit.beta[ia] / truth[ia]:.2f} | "
        f"{eq_fit.beta[ma] / truth[ma]:.2f} | | | | | |" + (" |" if fit else "")
    )
    return rows


def run(seeds: int, minutes: float, fit: tuple[FilterKind, ...] = (), passes: int = 300) -> None:
    base = [*mission("light", 60.0 * minutes), 'filter.structure_check="off"']
    print(
        f"NOC mission of {minutes:g} min in light turbulence, no vane, {seeds} seed(s); "
        "ratios are estimate over truth\n"
    )
    head = [f"from truth, σ {f:g}|truth|: CLa / Cma / max z" for f in WIDTHS]
    if fit:
        head.append("whole-record fit: CLa / Cma / -2 log L less held at truth / passes")
    print(
        "| seed | gust model | filter | CLa | Cma | max \\|z\\| (own σ) | "
        "-2 log L held at the estimate less held at truth | " + " | ".join(head) + " |"
    )
    print("|---|---|---|---:|---:|---:|---:|" + "---:|" * len(head))
    start = time.perf_counter()
    for seed in range(1, seeds + 1):
        for row in _seed(base, seed, fit, passes):
            print(row, flush=True)
    print(f"\n({time.perf_counter() - start:.0f} s)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="seeds (default %(default)s)")
    ap.add_argument(
        "--minutes", type=float, default=8.0, help="mission length (default %(default)s)"
    )
    ap.add_argument(
        "--fit",
        nargs="+",
        choices=FILTER_KINDS,
        default=[],
        help="also the whole-record fit from these filters' ends (slow: hundreds of passes)",
    )
    ap.add_argument(
        "--fit-passes",
        type=int,
        default=300,
        help="function evaluations L-BFGS-B may take (its stop comes at the end of the "
        "iteration that passes them; default %(default)s)",
    )
    add_argument(ap, "vertical_wind")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.minutes <= 0:
        raise SystemExit("vertical_wind: --seeds must be 1 or more, --minutes positive")
    with recorded(
        "vertical_wind", args.record, "Light turbulence without a vane: what the data hold"
    ):
        run(args.seeds, args.minutes, tuple(args.fit), args.fit_passes)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
