"""Configuration errors name the file, the key and what is allowed."""

from __future__ import annotations

from pathlib import Path

import pytest

from gcs_estimator.config import ConfigError, load_config, load_config_with

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("mass_kg = 13.5", "mass_kg = -3", r"\[airframe\] mass_kg: must be a number > 0, got -3"),
        (
            'model = "propeller"',
            'model = "jet"',
            r"\[propulsion\] model: must be one of 'propeller', 'measured', got 'jet'",
        ),
        (
            'CD = ["1", "alpha", "elevator"]',
            'CD = ["1", "beta"]',
            r"\[coefficients\] CD: unknown regressor 'beta'; allowed",
        ),
        ("Cmde = -3.7891", "", r"\[truth\] Cmde: missing"),
        ("iterations = 7", "iterations = 0", r"\[filter\] iterations: must be >= 1, got 0"),
        (
            "mass_kg = 13.5",
            "mass_kg = 13.5\nmass = 2",
            r"\[airframe\] mass: unknown key; known keys here",
        ),
        (
            "restart_times_s = [5.0, 10.0]",
            "restart_times_s = [10.0, 5.0]",
            r"restart_times_s: must be strictly increasing",
        ),
        (
            'preset = "none"',
            'preset = "stormy"',
            r"\[simulation.turbulence\] preset: must be one of",
        ),
        (
            'outputs = ["auto"]',
            'outputs = ["save", "screen"]',
            r"\[view\] outputs: unknown output 'screen'; allowed: \['auto', 'save'",
        ),
        (
            'connect_url = "rerun+http://127.0.0.1:9876/proxy"',
            'connect_url = "127.0.0.1:9876"',
            r"\[view\] connect_url: must look like rerun\+http://HOST:PORT/proxy",
        ),
        (
            "adaptive = true",
            'adaptive = "yes"',
            r"\[filter.turbulence\] adaptive: must be true or false, got 'yes'",
        ),
        (
            "relinearise_sigma = 1.0",
            "relinearise_sigma = -1",
            r"\[filter\] relinearise_sigma: must be a number >= 0, got -1",
        ),
        (
            "detection_sigma = 3.0",
            "detection_sigma = -3.0",
            r"\[filter.turbulence\] detection_sigma: must be a number >= 0, got -3.0",
        ),
        (
            "display_rate_hz = 25.0",
            "display_rate_hz = 0",
            r"\[view\] display_rate_hz: must be a number > 0, got 0",
        ),
    ],
)
def test_errors_name_file_key_and_allowed(tmp_path: Path, old: str, new: str, message: str) -> None:
    base = (ROOT / "configs" / "noc_uav.toml").read_text()
    assert old in base
    p = tmp_path / "plane.toml"
    p.write_text(base.replace(old, new, 1))
    with pytest.raises(ConfigError, match=message) as info:
        load_config(p)
    assert str(p) in str(info.value)


def test_not_toml_and_missing_file(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text("[airframe\nmass_kg = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.toml")


def test_both_shipped_configs_load_with_their_structures() -> None:
    noc = load_config(ROOT / "configs" / "noc_uav.toml")
    hfb = load_config(ROOT / "configs" / "hfb320.toml")
    assert noc.coefficient_names == (
        "CD0",
        "CDa",
        "CDde",
        "CL0",
        "CLa",
        "CLq",
        "CLde",
        "Cm0",
        "Cma",
        "Cmq",
        "Cmde",
    )
    assert hfb.coefficient_names == (
        "CD0",
        "CDV",
        "CDa",
        "CL0",
        "CLV",
        "CLa",
        "Cm0",
        "CmV",
        "Cma",
        "Cmq",
        "Cmde",
    )
    assert noc.propulsion.model == "propeller" and hfb.propulsion.model == "measured"
    assert noc.filter.initial_coefficients == (0.0,) * 11  # the paper's zero start


def test_overrides_apply_and_are_validated() -> None:
    path = ROOT / "configs" / "noc_uav.toml"
    c = load_config_with(path, ["filter.iterations=3", 'simulation.turbulence.preset="light"'])
    assert c.filter.iterations == 3
    assert c.simulation.turbulence.sigma_w_mps > 0
    with pytest.raises(ConfigError, match=r"\[filter\] iterations: must be >= 1"):
        load_config_with(path, ["filter.iterations=0"])
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        load_config_with(path, ["filter.iterations"])
