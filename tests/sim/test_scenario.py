"""The simulator's [simulation] table: its own schema, read and checked by the simulator,
listed apart from the airframe's keys."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from gcs_estimator.config import ConfigError, load_config
from gcs_estimator.schema import Spec, leaves
from sim.cli import main as sim_main
from sim.scenario import Simulation, scenario_of, scenario_reference
from tests.test_config import _bad_values

ROOT = Path(__file__).resolve().parent.parent.parent
KEYS = list(leaves(Simulation, {}, "simulation"))


@pytest.mark.parametrize(
    ("table", "key", "spec", "tp"), [k[:4] for k in KEYS], ids=[f"{k.table}.{k.name}" for k in KEYS]
)
def test_every_simulator_key_refuses_a_bad_value_and_names_itself(
    table: str, key: str, spec: Spec, tp: Any
) -> None:
    where = re.escape(f"[{table}] {key}: ")
    for value in _bad_values(tp, spec):
        config = load_config("noc_uav", [f"{table}.{key}={json.dumps(value)}"])
        with pytest.raises(ConfigError, match=where) as info:
            scenario_of(config)
        assert "got" in str(info.value) or "unknown value" in str(info.value), str(info.value)


def test_a_file_without_the_table_flies_the_defaults() -> None:
    assert scenario_of(load_config("hfb320")) == Simulation()
    with pytest.raises(ConfigError, match=r"simulation: must be a table"):
        scenario_of(load_config("noc_uav", ["simulation=3"]))


def test_the_simulator_reference_is_generated_from_its_schema(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """docs/simulation.md is what `gcs-sim --keys` prints: regenerate it with
    `.venv/bin/gcs-sim --keys > docs/simulation.md` after changing a key."""
    assert sim_main(["--keys"]) == 0
    printed = capsys.readouterr().out
    assert printed == scenario_reference()
    assert (ROOT / "docs" / "simulation.md").read_text() == printed
    assert "## [simulation.turbulence]" in printed and "`preset`" in printed
