"""The independent validation set: aircraft bundled with JSBSim flown through a paper-like
elevator manoeuvre, written as noisy CSVs with an airframe file each.

    ./run bench jsbsim_flights [--out out/realdata]

JSBSim (the `jsbsim` package) is a six-degree-of-freedom simulator with its own
aerodynamic tables, on a round rotating Earth; nothing here was tuned on it. Each
aircraft is trimmed in level flight, flies 3-2-1-1 multisteps and two pulses on the
elevator (throttle fixed) with the wings held level by aileron (as a test pilot does: a
longitudinal manoeuvre flown in a bank is not longitudinal), calm and in light Dryden
turbulence, and is sampled at 50 Hz. The CSVs carry sensor noise, an angle-of-attack vane
ahead of the CG, a rate-gyro bias and the air density of each sample; the airframe files
state the vane position, estimate the bias and give the wing span (so the filters model
turbulence's pitch gust, which JSBSim flies: docs/decisions/0016), and carry no filter
tuning at all (the project's defaults).

Reference coefficients: JSBSim's own aerodynamic force and moment coefficients over the
flown samples, linearised by least squares on the estimator's coefficient structure
(regressors 1, alpha, q c / (2 V), elevator): the structure's best fit to JSBSim's
aerodynamics over the flown envelope. JSBSim also has alpha-dot terms (CLadot, Cmadot),
which the structure lacks; the fit takes their contribution as it comes (mostly into
the q terms), and the airframe file notes their size next to the references.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from best_fit import best_fit, reproduction, spread  # benchmarks/: the script's dir is on sys.path

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import REGRESSOR_SUFFIX, load_config
from gcs_estimator.ingest.flightdata import Recording, write_csv
from gcs_estimator.units import FOOT, POUND_FORCE, SLUG

ROOT = Path(__file__).resolve().parent.parent
INCH = 0.0254
MODEL_OUTPUT = ROOT / "out" / "jsbsim_output"
PLACES = {"cg": "inertia/cg", "eye": "metrics/eyepoint", "aerorp": "metrics/aero-rp"}
RATE_HZ = 50.0
STEPS_PER_SAMPLE = 4  # JSBSim at 200 Hz
DURATION_S = 60.0
NOISE = (0.3, math.radians(0.3), math.radians(0.2), math.radians(0.1), 0.05, 0.2, 0.2)
"""Sensor noise 1 sigma (V, alpha, theta, q, qdot, a_x, a_z): the project's defaults."""
GYRO_BIAS = 0.003
CLEAN = ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z")
"""The noise-free observations at the CG, in channel order."""
STRUCTURE = {"CD": ["1", "alpha"], "CL": ["1", "alpha", "qhat", "elevator"]}
STRUCTURE["Cm"] = ["1", "alpha", "qhat", "elevator"]
ALPHA_DOT_STRUCTURE = {
    axis: [*regs, "adhat"] if axis != "CD" else regs for axis, regs in STRUCTURE.items()
}
"""The structure with JSBSim's alpha-dot terms (CLadot, Cmadot) as well: `--alpha-dot`."""


def structure(alpha_dot: bool) -> dict[str, list[str]]:
    """The coefficient structure the airframe files give: the paper's, or with the
    alpha-dot terms the JSBSim aircraft carry."""
    return ALPHA_DOT_STRUCTURE if alpha_dot else STRUCTURE


@dataclass(frozen=True)
class Aircraft:
    model: str
    label: str
    altitude_ft: float
    """MIL-F-8785C light turbulence fades out above about 8,000 ft: both fly below."""
    speed_kts: float
    amplitude_deg: float
    """Elevator multistep amplitude."""
    vane_x_m: float
    """Angle-of-attack vane ahead of the CG (the validation set's: the model's eyepoint)."""
    kind: str = ""
    """The aircraft's class (light single, trainer, twin, glider, jet, ...)."""
    gamma_deg: float = 0.0
    """Flight-path angle at trim: a glider glides."""
    throttle: bool = True
    """False: no engine (a glider), no thrust input."""


AIRCRAFT = (
    Aircraft("c172p", "Cessna 172 (light single)", 3000.0, 95.0, 2.0, 1.5),
    Aircraft("737", "Boeing 737 (jet transport)", 5000.0, 250.0, 1.0, 13.0),
)


def elevator_offset_deg(t: float, amplitude: float) -> float:
    """3-2-1-1 multisteps at 2 s and 8 s (unit 0.3 s), pulses at 16 s and 34 s (2 s)."""
    for start in (2.0, 8.0):
        s = (t - start) / 0.3
        for a, b, step in ((0, 3, 1.0), (3, 5, -1.0), (5, 6, 1.0), (6, 7, -1.0)):
            if a <= s < b:
                return step * amplitude
    for start, pulse in ((16.0, -1.0), (34.0, 1.0)):
        if start <= t < start + 2.0:
            return pulse * amplitude
    return 0.0


TIMINGS = ("fcs", "step")
"""How the elevator moves: "fcs", the multisteps commanded at sample instants and the
surface as the model's flight control system moves it; "step", the same commands at
STEP_OFFSET_STEPS integration steps after a sample instant, so the surface steps between
two logged samples (where the model's FCS has no actuator lag: see the flight's
`lag` figure)."""
STEP_OFFSET_STEPS = 3
"""Integration steps (of STEPS_PER_SAMPLE) after a sample instant at which a "step"
flight's elevator command changes: 15 ms into a 20 ms sample interval."""


def fly(
    ac: Aircraft, turbulence: bool, seed: int, timing: str = "fcs", fine: bool = False
) -> dict[str, FloatArray]:
    """One flight, sampled at RATE_HZ (at every integration step when `fine`): noise-free
    signals and JSBSim's aerodynamics. JSBSim's banner and its notes on the models' input
    sockets (printed when the model loads and when its initial conditions run) go to
    stderr: the benchmark's output, and its record, hold what the benchmark measured."""
    with contextlib.redirect_stdout(sys.stderr):
        return _fly(ac, turbulence, seed, timing, fine)


def _trimmed(ac: Aircraft, turbulence: bool, seed: int) -> tuple[Any, FloatArray | None]:
    import jsbsim

    fdm = jsbsim.FGFDMExec(None)
    fdm.set_debug_level(0)
    # Some models (the global5000) write a CSV of their own: into out/, not the cwd.
    MODEL_OUTPUT.mkdir(parents=True, exist_ok=True)
    fdm.set_output_path(str(MODEL_OUTPUT))
    fdm.load_model(ac.model)
    fdm.set_dt(1.0 / (RATE_HZ * STEPS_PER_SAMPLE))
    glide = _trim(fdm, ac)
    if turbulence:  # MIL-F-8785C Dryden, light (W20 = 15 kt)
        fdm["atmosphere/turb-type"] = 3
        fdm["atmosphere/turbulence/milspec/windspeed_at_20ft_ft_sec"] = 15 * 1.6878
        fdm["atmosphere/turbulence/milspec/severity"] = 1
        fdm["atmosphere/randomseed"] = seed
    return fdm, glide


def _trim(fdm: Any, ac: Aircraft, glide: FloatArray | None = None) -> FloatArray | None:
    """Level flight by JSBSim's own trim (throttle, elevator, pitch); a glider, which has
    no throttle to trim with, glides: alpha, elevator and flight-path angle solved for
    zero accelerations in calm air (returned; `glide`: a solution found before, set
    again)."""
    fdm["ic/h-sl-ft"] = ac.altitude_ft
    fdm["ic/vc-kts"] = ac.speed_kts
    fdm["ic/gamma-deg"] = ac.gamma_deg
    if ac.throttle:
        fdm.run_ic()
        fdm["propulsion/set-running"] = -1
        fdm["simulation/do_simple_trim"] = 1
        return None
    from scipy.optimize import least_squares

    def residual(z: FloatArray) -> list[float]:
        fdm["ic/h-sl-ft"] = ac.altitude_ft
        fdm["ic/vc-kts"] = ac.speed_kts
        fdm["ic/alpha-deg"], fdm["ic/gamma-deg"] = z[0], z[2]
        fdm["fcs/elevator-cmd-norm"] = z[1]
        fdm.run_ic()
        fdm.run()
        return [fdm[f"accelerations/{a}"] for a in ("udot-ft_sec2", "wdot-ft_sec2")] + [
            10.0 * fdm["accelerations/qdot-rad_sec2"]
        ]

    if glide is not None:
        residual(glide)
        return glide
    sol = least_squares(residual, [3.0, 0.0, ac.gamma_deg], diff_step=1e-4)
    if np.max(np.abs(residual(sol.x))) > 1e-3:
        raise RuntimeError(f"{ac.model}: no steady glide at {ac.speed_kts} kt")
    return np.asarray(sol.x, float)


def _fly(
    ac: Aircraft, turbulence: bool, seed: int, timing: str, fine: bool
) -> dict[str, FloatArray]:
    fdm, glide = _trimmed(ac, turbulence, seed)
    trim_cmd = fdm["fcs/elevator-cmd-norm"]
    # Normalised command per degree of elevator, from the surface's mapping at trim.
    de0 = fdm["fcs/elevator-pos-rad"]
    per_norm = 0.0
    # A surface with hysteresis (the c172x's actuator: 0.05 rad) ignores the small step;
    # the larger one is taken only there, so the other models' flights are as before.
    for probe in (0.05, 0.25):
        fdm["fcs/elevator-cmd-norm"] = trim_cmd + probe
        for _ in range(STEPS_PER_SAMPLE * 25):
            fdm.run()
        per_norm = (fdm["fcs/elevator-pos-rad"] - de0) / probe
        if per_norm != 0.0:
            break
    # Back to the trimmed command before trimming again: a model that trims with its
    # pitch trim (the c172p) would otherwise trim against the calibration's offset.
    fdm["fcs/elevator-cmd-norm"] = trim_cmd
    _trim(fdm, ac, glide)
    # JSBSim's trim leaves the surfaces' output properties as the calibration left them:
    # one step from the trim brings them to the trimmed commands before the first sample.
    fdm.run()
    aileron0 = fdm["fcs/aileron-cmd-norm"]
    out: dict[str, list[float]] = {}
    n = int(DURATION_S * RATE_HZ) * STEPS_PER_SAMPLE + 1
    shift = STEP_OFFSET_STEPS if timing == "step" else 0
    dt = 1.0 / (RATE_HZ * STEPS_PER_SAMPLE)
    for i in range(n):
        t = i * dt
        # The command of the sample interval this step lies in ("step": shifted).
        k = (i - shift) // STEPS_PER_SAMPLE
        cmd = math.radians(elevator_offset_deg(k / RATE_HZ, ac.amplitude_deg)) / per_norm
        fdm["fcs/elevator-cmd-norm"] = trim_cmd + cmd
        if i % STEPS_PER_SAMPLE == 0:
            # Wings level: bank and roll rate fed back to the aileron.
            fdm["fcs/aileron-cmd-norm"] = aileron0 - (
                2.0 * fdm["attitude/phi-rad"] + 0.5 * fdm["velocities/p-rad_sec"]
            )
        if fine or i % STEPS_PER_SAMPLE == 0:
            _sample(fdm, t, out)
        if i + 1 < n:
            fdm.run()
    return {k: np.array(v) for k, v in out.items()}


def _sample(fdm: Any, t: float, out: dict[str, list[float]]) -> None:
    g: Callable[[str], float] = fdm.__getitem__
    mass = g("inertia/mass-slugs")
    px, pz = _term(g, "forces/fbx-prop-lbs"), _term(g, "forces/fbz-prop-lbs")  # 0: a glider
    fx = g("forces/fbx-aero-lbs") + px
    fz = g("forces/fbz-aero-lbs") + pz
    thrust = math.hypot(px, pz)
    qs = g("aero/qbar-psf") * g("metrics/Sw-sqft")
    u, v, w = g("velocities/u-fps"), g("velocities/v-fps"), g("velocities/w-fps")
    ground_speed = math.sqrt(u * u + v * v + w * w)
    ground_alpha = math.atan2(w, u)
    values = {
        "t": t,
        "V": g("velocities/vt-fps") * FOOT,
        "alpha": g("aero/alpha-rad"),
        "theta": g("attitude/theta-rad"),
        "q": g("velocities/q-rad_sec"),
        "qdot": g("accelerations/qdot-rad_sec2"),
        "a_x": fx / mass * FOOT,
        "a_z": fz / mass * FOOT,
        "de": g("fcs/elevator-pos-rad"),
        "thrust": thrust * POUND_FORCE,
        "CL": g("forces/fwz-aero-lbs") / qs,
        "CD": g("forces/fwx-aero-lbs") / qs,
        "Cm": g("moments/m-aero-lbsft") / (qs * g("metrics/cbarw-ft")),
        "qbar": g("aero/qbar-psf"),
        # The propeller's induced dynamic pressure where the model has one (0 where not).
        "qbar_induced": _term(g, "aero/function/qbar-induced-psf"),
        "rho": g("atmosphere/rho-slugs_ft3") * SLUG / FOOT**3,
        "arm": _term(g, "moments/m-prop-lbsft") / thrust * FOOT if thrust > 0 else 0.0,
        "phi": g("attitude/phi-rad"),
        "mass": mass * SLUG,
        "area": g("metrics/Sw-sqft") * FOOT**2,
        "chord": g("metrics/cbarw-ft") * FOOT,
        "span": g("metrics/bw-ft") * FOOT,
        "iyy": g("inertia/iyy-slugs_ft2") * SLUG * FOOT**2,
        # Where the model places its CG, eyepoint and aerodynamic reference point
        # (structural frame: x aft, z up [m]).
        **{
            f"{name}_{axis}": g(f"{prop}-{axis}-in") * INCH
            for name, prop in PLACES.items()
            for axis in "xz"
        },
        "incl": math.atan2(-pz, px) if thrust > 0 else 0.0,
        # The alpha-dot terms' contributions (coefficients), and alpha-dot c / (2 V).
        "CLadot": _term(g, "aero/coefficient/CLadot") / qs,
        "Cmadot": _term(g, "aero/coefficient/Cmadot") / (qs * g("metrics/cbarw-ft")),
        "adhat": g("aero/alphadot-rad_sec") * g("metrics/cbarw-ft") / (2 * g("velocities/vt-fps")),
        # The gust: air-relative V and alpha against the motion over the ground.
        "gust_u": (g("velocities/vt-fps") - ground_speed) * FOOT,
        "gust_w": (g("aero/alpha-rad") - ground_alpha) * ground_speed * FOOT,
        # The pitch gust (MIL-F-8785C's q_g): the aerodynamics see q less it.
        "gust_q": g("velocities/q-rad_sec") - g("velocities/q-aero-rad_sec"),
    }
    for k, v in values.items():
        out.setdefault(k, []).append(float(v))


def _term(g: Callable[[str], float], prop: str) -> float:
    """A JSBSim aerodynamic term's value (0 where the model has no such term)."""
    try:
        return float(g(prop))
    except Exception:
        return 0.0


def reference(
    f: dict[str, FloatArray], chord_m: float, alpha_dot: bool = False
) -> dict[str, tuple[float, float]]:
    """JSBSim's aerodynamic coefficients over the flown samples, linearised by least
    squares on the structure's regressors (structure(alpha_dot)): name -> (value, fit
    residual RMS)."""
    regressors = {
        "1": np.ones_like(f["t"]),
        "alpha": f["alpha"],
        "qhat": f["q"] * chord_m / (2.0 * f["V"]),
        "elevator": f["de"],
        "adhat": f["adhat"],
    }
    suffix = REGRESSOR_SUFFIX
    out: dict[str, tuple[float, float]] = {}
    for axis, regs in structure(alpha_dot).items():
        X = np.column_stack([regressors[r] for r in regs])
        beta, *_ = np.linalg.lstsq(X, f[axis], rcond=None)
        rms = float(np.sqrt(np.mean((f[axis] - X @ beta) ** 2)))
        for r, b in zip(regs, beta, strict=True):
            out[axis + suffix[r]] = (float(b), rms)
    return out


def alpha_dot_terms(f: dict[str, FloatArray]) -> dict[str, float]:
    """JSBSim's alpha-dot derivatives (CLadot, Cmadot per alpha-dot c / (2 V)), which the
    structure lacks: their contributions divided by alpha-dot c / (2 V) where it moves."""
    moving = np.abs(f["adhat"]) > 0.1 * np.max(np.abs(f["adhat"]))
    return {
        name: float(np.median(f[name][moving] / f["adhat"][moving])) if moving.any() else 0.0
        for name in ("CLadot", "Cmadot")
    }


def measurements(f: dict[str, FloatArray], ac: Aircraft, rng: np.random.Generator) -> FloatArray:
    """What the sensors read: the vane ahead of the CG, the gyro bias, noise."""
    V, alpha, q = f["V"], f["alpha"], f["q"]
    vane = np.arctan2(V * np.sin(alpha) - q * ac.vane_x_m, V * np.cos(alpha))
    clean = np.column_stack([V, vane, f["theta"], q + GYRO_BIAS, f["qdot"], f["a_x"], f["a_z"]])
    return clean + np.array(NOISE) * rng.standard_normal(clean.shape)


def airframe_lines(
    label: str, f: dict[str, FloatArray], regressors: dict[str, list[str]]
) -> list[str]:
    """An airframe file's [airframe], [propulsion] and [coefficients] tables from what the
    model flew (geometry, mass, inertia, thrust line): what a user would write."""
    return [
        "[airframe]",
        f'name = "{label}"',
        f"mass_kg = {float(np.mean(f['mass'])):.6g}",
        f"wing_area_m2 = {float(f['area'][0]):.6g}",
        f"mean_chord_m = {float(f['chord'][0]):.6g}",
        f"wing_span_m = {float(f['span'][0]):.6g}",
        f"inertia_yy_kgm2 = {float(np.mean(f['iyy'])):.6g}",
        f"air_density_kgpm3 = {float(np.mean(f['rho'])):.6g}  # the CSV has it per sample",
        f"trim_airspeed_mps = {float(f['V'][0]):.6g}",
        f"thrust_inclination_rad = {float(np.median(f['incl'])):.6g}",
        f"thrust_moment_arm_m = {float(np.median(f['arm'])):.6g}",
        "",
        "[propulsion]",
        'model = "measured"',
        "",
        "[coefficients]",
        *(f"{axis} = {regs}".replace("'", '"') for axis, regs in regressors.items()),
    ]


def airframe_toml(
    ac: Aircraft,
    f: dict[str, FloatArray],
    ref: dict[str, tuple[float, float]],
    adot: dict[str, float],
    alpha_dot: bool = False,
) -> str:
    """The airframe file a user would write: geometry, structure (with the alpha-dot
    terms when alpha_dot), sensors; no tuning."""
    note = (
        "# (fit residual RMS per axis in the comments), the alpha-dot terms with the rest."
        if alpha_dot
        else "# (fit residual RMS per axis in the comments). JSBSim's alpha-dot terms, which the\n"
        "# structure lacks and the fit takes in as they come: "
        + ", ".join(f"{n} = {v:.4g}" for n, v in adot.items())
        + "."
    )
    lines = [
        f"# {ac.label}: JSBSim '{ac.model}', written by benchmarks/jsbsim_flights.py.",
        "",
        *airframe_lines(ac.label, f, structure(alpha_dot)),
        "",
        "[sensors]",
        f"vane_x_m = {ac.vane_x_m}",
        'bias_states = ["q"]',
        "",
        "[link]",
        "throttle_servo = 0",
        "",
        "# JSBSim's own aerodynamics over the flown samples, linearised on the structure above",
        note,
        "[truth]",
        'label = "JSBSim"',
        *(f"{n} = {v:.6g}  # residual {r:.2g}" for n, (v, r) in ref.items()),
        "",
    ]
    return "\n".join(lines)


def generate(
    out: Path, seeds: Sequence[int] = (1,), alpha_dot: bool = False
) -> list[tuple[Path, Path]]:
    """Fly every aircraft calm and in light turbulence; (config, csv) per record and seed
    (the first seed's records are NAME.csv, the others' NAME_sSEED.csv), the airframe
    files with structure(alpha_dot). Next to each,
    NAME.best_fit.json: the structure's best fit to the noise-free calm flight
    (benchmarks/best_fit.py), which serves the turbulent one too, how far it moves with
    the channels' weighting (its spread), and how closely it reproduces this flight
    (flown through its own gusts). The calm flight is the same for every seed (only its
    sensor noise differs), so it is flown and fitted once."""
    out.mkdir(parents=True, exist_ok=True)
    records = []
    for ac in AIRCRAFT:
        calm = fly(ac, False, seeds[0])
        target: tuple[FloatArray, FloatArray, FloatArray] | None = None
        for seed in seeds:
            for turbulent in (False, True):
                f = fly(ac, turbulent, seed) if turbulent else calm
                name = f"{ac.model}_{'light' if turbulent else 'calm'}"
                name += "" if seed == seeds[0] else f"_s{seed}"
                config_path, csv_path = write_record(out / name, ac, f, seed, alpha_dot)
                config = load_config(config_path, ["sensors.vane_x_m=0", "sensors.bias_states=[]"])
                inputs = np.column_stack([f["de"], f["thrust"], f["rho"]])
                clean = np.column_stack([f[k] for k in CLEAN])
                if target is None:  # the calm flight, flown first
                    best, rms = best_fit(config, f["t"], inputs, clean, np.array(config.truth))
                    target = best, spread(config, f["t"], inputs, clean, best), rms
                best, moves, rms = target
                if turbulent:
                    gust = np.column_stack([f["gust_u"], f["gust_w"], f["gust_q"]])
                    rms = reproduction(config, f["t"], inputs, clean, best, gust)
                names = config.coefficient_names
                fit = {
                    "coefficients": dict(zip(names, best.tolist(), strict=True)),
                    "residual_sigmas": dict(zip(CLEAN, rms.tolist(), strict=True)),
                    "spread_pct": dict(zip(names, moves.tolist(), strict=True)),
                }
                best_path = csv_path.with_suffix(".best_fit.json")
                best_path.write_text(json.dumps(fit), encoding="utf-8")
                records.append((config_path, csv_path))
                print(
                    f"{name}: {f['t'].shape[0]} samples, largest bank "
                    f"{np.degrees(np.abs(f['phi']).max()):.2f} deg -> {csv_path}",
                    file=sys.stderr,
                )
    return records


def write_record(
    stem: Path, ac: Aircraft, f: dict[str, FloatArray], seed: int, alpha_dot: bool = False
) -> tuple[Path, Path]:
    """A flight's noisy CSV (sensor noise drawn from `seed`) and its airframe file."""
    inputs = np.column_stack([f["de"], f["thrust"], f["rho"]])
    rng = np.random.default_rng(seed)
    rec = Recording(f["t"], inputs, measurements(f, ac, rng), "thrust")
    csv_path, toml_path = stem.with_suffix(".csv"), stem.with_suffix(".toml")
    write_csv(csv_path, rec)
    ref = reference(f, float(f["chord"][0]), alpha_dot)
    toml = airframe_toml(ac, f, ref, alpha_dot_terms(f), alpha_dot)
    toml_path.write_text(toml, encoding="utf-8")
    return toml_path, csv_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "out" / "realdata"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--alpha-dot",
        action="store_true",
        help="airframe files with JSBSim's alpha-dot terms (CLadot, Cmadot) in the structure",
    )
    args = ap.parse_args(argv)
    generate(Path(args.out), (args.seed,), args.alpha_dot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
