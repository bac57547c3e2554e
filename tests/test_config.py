"""Configuration: every key declared once; errors name the file, table, key and what is allowed."""

from __future__ import annotations

import json
import re
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any, get_args, get_origin

import pytest

from gcs_estimator.config import (
    COEFFICIENT,
    AircraftConfig,
    ConfigError,
    config_reference,
    load_config,
    parse_config,
)
from gcs_estimator.schema import Spec, leaves
from sim.scenario import scenario_of

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
            r"\[coefficients\] CD: unknown value 'beta'; allowed",
        ),
        ("Cmde = -3.7891", "", r"\[truth\] Cmde: missing"),
        (
            "iterations = 7",
            "iterations = 0",
            r"\[filter\] iterations: must be a whole number >= 1, got 0",
        ),
        (
            "mass_kg = 13.5",
            "mass_kg = 13.5\nmass = 2",
            r"\[airframe\] mass: unknown key \(did you mean 'mass_kg'\?\); known keys here",
        ),
        (
            "iterations = 7",
            "iterations = 7\niteration = 3",
            r"\[filter\] iteration: unknown key \(did you mean 'iterations'\?\)",
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
            r"\[view\] outputs: unknown value 'screen'; allowed: \['auto', 'save'",
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
            "serve_port = 9877",
            "serve_port = 0",
            r"\[view\] serve_port: must be a whole number >= 1 and <= 65535, got 0",
        ),
    ],
)
def test_errors_name_file_key_and_allowed(tmp_path: Path, old: str, new: str, message: str) -> None:
    """The airframe's keys are checked as the file is read, the [simulation] table's as
    the simulator reads it (scenario_of), with the same kind of message."""
    base = (ROOT / "configs" / "noc_uav.toml").read_text()
    assert old in base
    p = tmp_path / "plane.toml"
    p.write_text(base.replace(old, new, 1))
    with pytest.raises(ConfigError, match=message) as info:
        scenario_of(load_config(p))
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


def test_overrides_apply_and_are_validated() -> None:
    path = ROOT / "configs" / "noc_uav.toml"
    c = load_config(path, ["filter.iterations=3", 'simulation.turbulence.preset="light"'])
    assert c.filter.iterations == 3
    assert scenario_of(c).turbulence.sigma_w > 0
    with pytest.raises(ConfigError, match=r"\[filter\] iterations: must be a whole number >= 1"):
        load_config(path, ["filter.iterations=0"])
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        load_config(path, ["filter.iterations"])


def _bad_values(tp: Any, spec: Spec) -> list[Any]:
    """Values the schema must refuse for a key: the wrong type, and out of its bounds."""
    if tp is str:
        return [5] + (["nonsense"] if spec.choices else [])
    if tp is bool:
        return ["yes"]
    if get_origin(tp) is tuple:
        return ["x", ["nonsense"] if get_args(tp)[0] is str else ["x"]]
    bad: list[Any] = ["x", True]
    bad += [b - 1 for b in (spec.gt, spec.ge) if b is not None]
    bad += [spec.le + 1] if spec.le is not None else []
    return bad


NOC_NAMES = load_config("noc_uav").coefficient_names
KEYS = list(leaves(AircraftConfig, {COEFFICIENT: NOC_NAMES}))


@pytest.mark.parametrize(
    ("table", "key", "spec", "tp"), [k[:4] for k in KEYS], ids=[f"{k.table}.{k.name}" for k in KEYS]
)
def test_every_key_refuses_a_bad_value_and_names_itself(
    table: str, key: str, spec: Spec, tp: Any
) -> None:
    """Each key of the schema, given each kind of bad value on the command line, is named
    in the error with its table, and the value is quoted."""
    dotted = f"{table}.{key}" if table else key
    where = re.escape(f"[{table}] {key}: " if table else f"{key}: ")
    for value in _bad_values(tp, spec):
        with pytest.raises(ConfigError, match=where) as info:
            load_config("noc_uav", [f"{dotted}={json.dumps(value)}"])
        assert "got" in str(info.value) or "unknown value" in str(info.value), str(info.value)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("propulsion.prop_area_m2=0", r"\[propulsion\] prop_area_m2: set all of prop_area_m2"),
        ("simulation.manoeuvre.pulse_durations_s=[1.0]", r"pulse_durations_s: must have 2 values"),
        ("link.elevator_us_per_rad=0", r"\[link\] elevator_us_per_rad: must not be 0"),
        ("link.throttle_pwm_max_us=900", r"\[link\] throttle_pwm_max_us: must be greater"),
        ('link.thrust_name="ELEVENCHARS"', r"\[link\] thrust_name: NAMED_VALUE_FLOAT names are"),
        ("filter.measurement_sigma.q=0", r"\[filter.measurement_sigma\] q: must be a number > 0"),
        (
            "filter.initial_sigma.coefficients.Cxx=1",
            r"\[filter.initial_sigma.coefficients\] Cxx: unknown key",
        ),
        ("coefficients.CD=[]", r"\[truth\] CD0: unknown key; known keys here: \[.CL0."),
        ('coefficients.Cm=["1", "1"]', r"\[coefficients\] Cm: lists a value twice"),
    ],
)
def test_rules_between_keys_name_the_key_to_fix(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        scenario_of(load_config("noc_uav", [override]))


def test_defaults_are_declared_once_and_match_the_complete_example() -> None:
    """A minimal airframe file (required keys only) gets the same tuning as the complete
    example writes out: the defaults and the documented values are one set of numbers."""
    data = tomllib.loads((ROOT / "configs" / "noc_uav.toml").read_text())
    minimal = {k: data[k] for k in ("airframe", "propulsion", "coefficients", "truth")}
    small = parse_config(minimal)
    full = load_config("noc_uav")
    # The one per-aircraft choice the example makes: wider priors on the qhat derivatives.
    sigma = replace(full.filter.initial_sigma, coefficients=small.filter.initial_sigma.coefficients)
    assert small.filter == replace(full.filter, initial_sigma=sigma)
    assert scenario_of(small) == scenario_of(full)
    # And its simulated vehicle's AOA_SSA is a vane's (ArduPlane's, the default, is its
    # AHRS estimate: decision 0038).
    assert small.link == replace(full.link, aoa_ssa="ahrs") and full.link.aoa_ssa == "vane"
    assert small.view == full.view


def test_shipped_configs_are_found_by_name_from_anywhere(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert load_config("hfb320").airframe.name == "HFB-320"
    with pytest.raises(
        ConfigError,
        match=r"nosuch: no such file, nor a shipped config; shipped: "
        r"\['hfb320', 'hfb320_book_noise', 'noc_uav'\]",
    ):
        load_config("nosuch")


def test_a_config_extends_another_and_sets_only_what_differs(tmp_path: Path) -> None:
    """`extends` takes a shipped name or a path beside the file; tables merge key by key
    (a key set here wins, the base's other keys stay), chains work, and a loop or a base
    that is not there is refused naming the file and the key."""
    base = load_config("hfb320")
    book = load_config("hfb320_book_noise")
    assert book.airframe == base.airframe and book.truth == base.truth
    assert book.filter.measurement_noise == "config" != base.filter.measurement_noise
    assert book.filter.process_noise.states[0] == 1.2856
    # Keys of a table the file does not touch keep the base's value.
    assert book.filter.process_noise.coefficients == base.filter.process_noise.coefficients
    assert "extends" in book.source and book.source.endswith("hfb320.toml)")

    (tmp_path / "plane.toml").write_text(
        (ROOT / "configs" / "noc_uav.toml").read_text(), encoding="utf-8"
    )
    (tmp_path / "heavier.toml").write_text(
        'extends = "plane.toml"\n[airframe]\nmass_kg = 20.0\n', encoding="utf-8"
    )
    (tmp_path / "windy.toml").write_text(
        'extends = "heavier.toml"\n[filter.turbulence]\nsigma_w_mps = 1.0\n', encoding="utf-8"
    )
    windy = load_config(tmp_path / "windy.toml", ["airframe.mass_kg=21.0"])
    plane = load_config(tmp_path / "plane.toml")
    assert windy.airframe.mass_kg == 21.0
    assert windy.airframe.wing_area_m2 == plane.airframe.wing_area_m2
    assert windy.filter.turbulence.sigma_w_mps == 1.0
    assert windy.filter.turbulence.length_w_m == plane.filter.turbulence.length_w_m
    assert windy.raw["airframe"]["mass_kg"] == 21.0 and "extends" not in windy.raw

    (tmp_path / "a.toml").write_text('extends = "b.toml"\n', encoding="utf-8")
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"b.toml: extends: 'a.toml' leads back to this file"):
        load_config(tmp_path / "a.toml")
    (tmp_path / "c.toml").write_text('extends = "nosuch"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"c.toml: extends: 'nosuch' is neither a file beside"):
        load_config(tmp_path / "c.toml")
    (tmp_path / "d.toml").write_text("extends = 3\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"d.toml: extends: must be a shipped config's name"):
        load_config(tmp_path / "d.toml")


def test_the_configuration_reference_is_generated_from_the_schema() -> None:
    """docs/configuration.md is what `gcs-estimator keys` prints: regenerate it with
    `./run gcs keys > docs/configuration.md` after changing a key. Each table comes once,
    with all its keys (a table whose dataclass lists a key after a sub-table too)."""
    text = (ROOT / "docs" / "configuration.md").read_text()
    assert text == config_reference(NOC_NAMES)
    headings = [line for line in text.splitlines() if line.startswith("## [")]
    assert len(headings) == len(set(headings)) and "## [link]" in headings
    link = text.split("## [link]")[1].split("\n## ")[0]
    assert "`signing_key_file`" in link and "`elevator_servo`" in link


def test_the_simulator_table_is_not_the_estimators() -> None:
    """The airframe's schema leaves [simulation] to the simulator: none of its keys is
    listed by `keys`, a mistake in it does not stop the estimator reading the file, and
    the simulator's reading of it names the file and key."""
    assert not any(k.table.startswith("simulation") for k in KEYS)
    config = load_config("noc_uav", ["simulation.sample_rate_hz=0"])
    assert config.raw["simulation"]["sample_rate_hz"] == 0
    with pytest.raises(ConfigError, match=r"\[simulation\] sample_rate_hz: must be a number > 0"):
        scenario_of(config)


@pytest.mark.parametrize("bind", ["0.0.0.0:9877", "bad host", ""])
def test_a_serve_bind_that_is_no_address_names_the_key(bind: str) -> None:
    with pytest.raises(ConfigError, match=r"\[view\] serve_bind: .* is no address to listen on"):
        load_config("noc_uav", [f'view.serve_bind="{bind}"'])
