"""How much of turbulence's pitch gust JSBSim's aerodynamics take, against the structure's.

    ./run bench pitch_gust_share [--seeds 3] [--record NAME|none]

The structure's aerodynamics take the pitch rate less the pitch gust, q - q_g, in all of
their q terms (docs/decisions/0016). JSBSim's take it in CLq and Cmq, but its alpha-dot
terms (CLadot, Cmadot) take the rate of the angle of attack of the motion over the ground,
not of the air: a gust reaches them through neither q_g nor the gust angle's rate. The
structure's best fit folds the alpha-dot terms into its q terms (the calm best fit's Cmq
is about JSBSim's Cmq + Cmadot), so in turbulence it may credit the pitch gust to the
whole of its q terms where JSBSim credits it to a part.

For each aircraft of the validation set (benchmarks/jsbsim_flights.py) and seed, this
flies the calm and the light-turbulence flight and prints:
- the vertical gust's standard deviation and correlation time (where its autocorrelation
  falls below 1/e), and the pitch gust's standard deviation;
- how JSBSim's alpha-dot follows the rate of alpha over the ground and through the air
  (correlation);
- the share of the pitch gust each of the structure's equations (CL, Cm) would have to
  take to match JSBSim's coefficients sample by sample (equation error of the calm best
  fit, regressed on q_g c / (2 V) with the gust angle and its rate beside it): 1 is what
  the structure assumes, 0 no pitch gust;
- how closely the calm best fit, flown through the flight's gusts (benchmarks/best_fit.py,
  `reproduction`), reproduces the turbulent flight when its aerodynamics take no, half or
  all of the pitch gust (largest residual over the channels, in sensor sigmas).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from best_fit import best_fit, reproduction  # benchmarks/: the script's dir is on sys.path
from jsbsim_flights import AIRCRAFT, CLEAN, alpha_dot_terms, fly, write_record
from record import add_argument, recorded

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import load_config

SHARES = (0.0, 0.5, 1.0)
"""Pitch-gust shares the reproduction flies."""


def _correlation(a: FloatArray, b: FloatArray) -> float:
    return float(np.corrcoef(a, b)[0, 1])


def _correlation_time(x: FloatArray, t: FloatArray) -> float:
    """Where x's autocorrelation first falls below 1/e [s]."""
    c = x - x.mean()
    acf = np.correlate(c, c, "full")[c.shape[0] - 1 :] / float(c @ c)
    return float(t[int(np.argmax(acf < np.exp(-1.0)))] - t[0])


def _gust_share(
    f: dict[str, FloatArray], coefficients: dict[str, float], axis: str
) -> tuple[float, float, float]:
    """(share of q_g the axis takes, equation-error RMS of the structure as it is, and with
    that share) for JSBSim's coefficient `axis` (CL or Cm) against the structure with
    `coefficients`, its q term on q - q_g."""
    chord = float(f["chord"][0])
    qg_hat = f["gust_q"] * chord / (2.0 * f["V"])
    q_hat = f["q"] * chord / (2.0 * f["V"]) - qg_hat
    c = coefficients
    model = (
        c[axis + "0"]
        + c[axis + "a"] * f["alpha"]
        + c[axis + "q"] * q_hat
        + c[axis + "de"] * f["de"]
    )
    error = f[axis] - model
    gust_angle = f["gust_w"] / f["V"]
    X = np.column_stack(
        [
            np.ones_like(error),
            qg_hat,
            gust_angle,
            np.gradient(gust_angle, f["t"]) * chord / 2.0 / f["V"],
        ]
    )
    beta, *_ = np.linalg.lstsq(X, error, rcond=None)
    share = 1.0 - float(beta[1]) / c[axis + "q"]
    rest = error - beta[1] * qg_hat
    return share, float(np.sqrt(np.mean(error**2))), float(np.sqrt(np.mean(rest**2)))


def run(seeds: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for ac in AIRCRAFT:
            calm = fly(ac, False, 1)
            config_path, _ = write_record(Path(tmp) / ac.model, ac, calm, 1)
            config = load_config(config_path, ["sensors.vane_x_m=0", "sensors.bias_states=[]"])

            def columns(f: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
                inputs = np.column_stack([f["de"], f["thrust"], f["rho"]])
                return inputs, np.column_stack([f[k] for k in CLEAN])

            inputs, clean = columns(calm)
            best, _ = best_fit(config, calm["t"], inputs, clean, np.array(config.truth))
            fit = dict(zip(config.coefficient_names, best.tolist(), strict=True))
            print(f"\n## {ac.label}\n")
            print(
                "calm best fit: "
                + ", ".join(f"{k} {fit[k]:.4g}" for k in ("CLq", "Cmq"))
                + "; JSBSim's alpha-dot terms (per alpha-dot c / (2 V)): "
                + ", ".join(f"{k} {v:.4g}" for k, v in alpha_dot_terms(calm).items())
                + "\n"
            )
            head = ["seed", "σ(w_g) m/s", "w_g correlation time s", "σ(q_g) rad/s"]
            head += ["alpha-dot ~ ground rate", "alpha-dot ~ air rate"]
            for axis in ("CL", "Cm"):
                head += [f"{axis} share of q_g", f"{axis} eq. error RMS (share 1 / fitted)"]
            head += [f"reproduction, share {s:g}" for s in SHARES]
            print("| " + " | ".join(head) + " |")
            print("|" + "---|" * len(head))
            _, calm_cm, _ = _gust_share({**calm, "gust_q": 0 * calm["q"]}, fit, "Cm")
            for seed in range(1, seeds + 1):
                f = fly(ac, True, seed)
                alpha_dot = f["adhat"] * 2.0 * f["V"] / f["chord"]
                ground_alpha = f["alpha"] - f["gust_w"] / (f["V"] - f["gust_u"])
                row = [
                    str(seed),
                    f"{float(np.std(f['gust_w'])):.3f}",
                    f"{_correlation_time(f['gust_w'], f['t']):.1f}",
                    f"{float(np.std(f['gust_q'])):.4f}",
                    f"{_correlation(alpha_dot, np.gradient(ground_alpha, f['t'])):.4f}",
                    f"{_correlation(alpha_dot, np.gradient(f['alpha'], f['t'])):.2f}",
                ]
                for axis in ("CL", "Cm"):
                    share, rms, rest = _gust_share(f, fit, axis)
                    row += [f"{share:.2f}", f"{rms:.2e} / {rest:.2e}"]
                inputs, clean = columns(f)
                for s in SHARES:
                    gust = np.column_stack([f["gust_u"], f["gust_w"], s * f["gust_q"]])
                    rms_ch = reproduction(config, f["t"], inputs, clean, best, gust)
                    row.append(f"{float(rms_ch.max()):.2f}")
                print("| " + " | ".join(row) + " |")
            print(f"\ncalm flight: Cm equation error RMS {calm_cm:.2e}")
            sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="turbulence seeds (default %(default)s)")
    add_argument(ap, "pitch_gust_share")
    args = ap.parse_args(argv)
    with recorded(
        "pitch_gust_share", args.record, "Pitch gust: the share JSBSim's aerodynamics take"
    ):
        run(args.seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
