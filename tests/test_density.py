"""Air density per sample: the standard atmosphere, the CSV columns it comes from, and
the filters flying with it in place of the airframe's constant."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording, load_csv, write_csv
from gcs_estimator.model import atmosphere
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.units import FOOT
from sim.truth import simulate


def test_standard_atmosphere_matches_the_published_table() -> None:
    # ISO 2533: sea level 1.2250 kg/m^3; 11 km: 22,632 Pa, 216.65 K; 3,000 m: 0.9093 kg/m^3;
    # 15 km: 0.19367 kg/m^3.
    assert atmosphere.density(atmosphere.pressure(0.0)) == pytest.approx(1.2250, abs=1e-4)
    assert atmosphere.pressure(11000.0) == pytest.approx(22632.0, rel=1e-4)
    assert atmosphere.temperature(atmosphere.pressure(11000.0)) == pytest.approx(216.65)
    assert atmosphere.density(atmosphere.pressure(3000.0)) == pytest.approx(0.9093, rel=5e-4)
    assert atmosphere.density(atmosphere.pressure(15000.0)) == pytest.approx(0.19367, rel=1e-3)
    # A known outside air temperature replaces the standard one: 15 K warmer, 5 % thinner.
    p = atmosphere.pressure(0.0)
    assert atmosphere.density(p, np.array(303.15)) == pytest.approx(p / (287.05287 * 303.15))


def _csv(path: Path, extra: dict[str, list[float]]) -> Path:
    head = "time_s,airspeed_mps,alpha_rad,theta_rad,q_radps,qdot_radps2,ax_mps2,az_mps2,"
    head += "elevator_rad,thrust_n"
    rows = [[0.0, 20, 0.05, 0.05, 0, 0, 0.5, -9.8, -0.02, 10.0]]
    rows.append([0.02, 20.1, 0.05, 0.05, 0, 0, 0.5, -9.8, -0.02, 10.0])
    lines = [",".join([head, *extra])]
    for i, r in enumerate(rows):
        lines.append(",".join([*(str(v) for v in r), *(str(v[i]) for v in extra.values())]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_density_from_each_kind_of_atmosphere_column(tmp_path: Path) -> None:
    none = load_csv(_csv(tmp_path / "none.csv", {}))
    assert none.inputs.shape == (2, 2)  # no atmosphere columns: the airframe's constant

    direct = load_csv(_csv(tmp_path / "rho.csv", {"air_density_kgpm3": [1.1, 1.0]}))
    np.testing.assert_array_equal(direct.inputs[:, 2], [1.1, 1.0])

    # Static pressure in hPa and outside air temperature in degC, one row without it.
    config = load_config(
        "noc_uav",
        [
            'data.columns.static_pressure="ps"',
            'data.units.static_pressure="hPa"',
            'data.columns.air_temperature="oat"',
            'data.units.air_temperature="degC"',
        ],
    )
    data = config.data
    path = tmp_path / "ps.csv"
    _csv(path, {"ps": [900.0, 899.0], "oat": [10.0, math.nan]})
    text = path.read_text(encoding="utf-8").replace(",nan", ",")
    path.write_text(text, encoding="utf-8")
    rho = load_csv(path, data).inputs[:, 2]
    assert rho[0] == pytest.approx(90000.0 / (atmosphere.R_AIR * 283.15))
    assert rho[1] == pytest.approx(float(atmosphere.density(np.array(89900.0))))

    # Pressure altitude in feet, standard temperature.
    alt = load_config(
        "noc_uav", ['data.columns.pressure_altitude="alt"', 'data.units.pressure_altitude="ft"']
    ).data
    rho = load_csv(_csv(tmp_path / "alt.csv", {"alt": [3000.0 / FOOT, 0.0]}), alt).inputs[:, 2]
    np.testing.assert_allclose(rho, [0.9093, 1.2250], rtol=5e-4)


def test_density_column_survives_a_round_trip(tmp_path: Path) -> None:
    t = np.array([0.0, 0.02, 0.04])
    inputs = np.array([[0.01, 5.0, 1.2], [0.02, 5.0, 1.19], [0.03, 5.0, math.nan]])
    rec = Recording(t, inputs, np.full((3, 7), 0.5), "thrust")
    write_csv(tmp_path / "r.csv", rec)
    back = load_csv(tmp_path / "r.csv")
    np.testing.assert_array_equal(back.inputs[:2], inputs[:2])
    assert math.isnan(back.inputs[2, 2])


def test_filters_fly_the_density_the_data_give_not_the_airframe_constant() -> None:
    """A flight at 1.225 kg/m^3 read with an airframe file that says 10 % less: given the
    density per sample, both filters end exactly where the right constant takes them;
    without it, the force coefficients come out about 10 % high. The estimates alone: no
    structure check, which widens only the sigmas (decision 0066)."""
    right = load_config("noc_uav", ["filter.structure_check=off"])
    flight = simulate(right, seed=1)
    rho = right.airframe.air_density_kgpm3
    wrong = load_config(
        "noc_uav", [f"airframe.air_density_kgpm3={0.9 * rho}", "filter.structure_check=off"]
    )
    with_rho = np.column_stack([flight.inputs, np.full(len(flight.t_s), rho)])
    runs = {
        "right constant": run_recording(right, flight.t_s, flight.inputs, flight.measurements),
        "per sample": run_recording(wrong, flight.t_s, with_rho, flight.measurements),
        "wrong constant": run_recording(wrong, flight.t_s, flight.inputs, flight.measurements),
    }
    res = {k: v.result for k, v in runs.items()}
    names = res["right constant"].names
    for kind in ("EKF", "IEKF"):
        good = res["right constant"].filters[kind].coefficients
        np.testing.assert_allclose(res["per sample"].filters[kind].coefficients, good, rtol=1e-9)
        bad = res["wrong constant"].filters[kind].coefficients
        i = names.index("Cma")
        assert bad[i] / good[i] == pytest.approx(1 / 0.9, rel=0.03)
