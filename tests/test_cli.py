"""The command line end to end: results files agree with the estimator's own values."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.cli import BACKEND_VARIABLE, backend_of, main
from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording, load_csv, load_hfb320, write_csv
from gcs_estimator.runtime.session import run_recording

ROOT = Path(__file__).resolve().parent.parent


def test_simulate_writes_table_json_and_csv(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status = main(
        [
            "simulate",
            "--config",
            str(ROOT / "configs/noc_uav.toml"),
            "--out",
            str(tmp_path),
            "--seed",
            "3",
            "--set",
            "simulation.manoeuvre.duration_s=20",
        ]
    )
    assert status == 0
    out = capsys.readouterr().out
    assert re.search(r"\| CLa +\|.* 6\.5858 \|", out)  # truth column, Table I layout
    data = json.loads((tmp_path / "results_sys1.json").read_text())
    assert data["coefficients"][4] == "CLa"

    # Same run by hand: the JSON holds exactly what the estimator returned.
    from sim.truth import simulate

    config = load_config(ROOT / "configs/noc_uav.toml", ["simulation.manoeuvre.duration_s=20"])
    flight = simulate(config, seed=3)
    res = run_recording(config, flight.t_s, flight.inputs, flight.measurements).result
    for kind, f in res.filters.items():
        for i, name in enumerate(res.names):
            got = data["filters"][kind]["estimates"][name]
            assert got["estimate"] == f.coefficients[i]
            assert got["sigma_parts"]["covariance"] == f.sigma[i]
    assert data["config"]["simulation"]["manoeuvre"]["duration_s"] == 20
    import pyarrow.parquet as pq

    history = pq.read_table(tmp_path / "results_sys1_history.parquet")  # the default format
    assert history.num_rows == len(flight.t_s)  # a row per frame, both filters in it
    assert history.column("IEKF_CLa")[-1].as_py() == np.float32(res.filters["IEKF"].coefficients[4])
    assert (tmp_path / "results_sys1.md").read_text().startswith("# NOC UAV")


def test_history_has_a_column_for_every_state_a_run_estimates(tmp_path: Path) -> None:
    """A rate-gyro bias state and gust states: the history CSV names a column for each
    element of the augmented state, and every row holds as many cells as the header."""
    over = [
        "simulation.manoeuvre.duration_s=12",
        "simulation.sensors.bias.q=0.003",
        'sensors.bias_states=["q"]',
        'filter.turbulence.model="states"',
    ]
    args = ["simulate", "--out", str(tmp_path), "--seed", "2", "--view", "off", "--history", "csv"]
    assert main(args + [a for o in over for a in ("--set", o)]) == 0
    lines = (tmp_path / "results_sys1_history.csv").read_text().splitlines()
    header = lines[0].split(",")
    for name in ("u_g", "w_g", "CLa", "q_bias", "sigma_q_bias", "sigma_w_g"):
        assert name in header
    assert len(lines) > 100
    assert {len(line.split(",")) for line in lines[1:]} == {len(header)}
    data = json.loads((tmp_path / "results_sys1.json").read_text())
    assert set(data["filters"]["IEKF"]["sensor_biases"]) == {"q_bias"}


def test_offline_csv_round_trip_matches_the_asc_record(tmp_path: Path, hfb_data_path: Path) -> None:
    rec = load_hfb320(hfb_data_path)
    csv_path = tmp_path / "hfb.csv"
    write_csv(csv_path, rec)
    back = load_csv(csv_path)
    np.testing.assert_array_equal(back.measurements, rec.measurements)
    np.testing.assert_array_equal(back.inputs, rec.inputs)
    # The three runs read the same frames: no structure check (decision 0066).
    quick = ["--set", "filter.structure_check=off"]
    csv_run = ["offline", str(csv_path), "--config", "hfb320", "--out", str(tmp_path / "a")]
    assert main([*csv_run, *quick]) == 0
    # The data's folder stands for its one data file (it also holds a README), and the
    # bundled record's name for its folder.
    assert main(["offline", str(hfb_data_path.parent), "--out", str(tmp_path / "b"), *quick]) == 0
    assert main(["offline", "hfb320", "--out", str(tmp_path / "c"), *quick]) == 0
    a = json.loads((tmp_path / "a/results_sys1.json").read_text())["filters"]
    b = json.loads((tmp_path / "b/results_sys1.json").read_text())["filters"]
    c = json.loads((tmp_path / "c/results_sys1.json").read_text())["filters"]
    assert a == b == c


def test_bad_inputs_give_one_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "x.csv"
    bad.write_text("time_s,airspeed_mps\n0,1\n")
    assert main(["offline", str(bad), "--config", "noc_uav", "--out", str(tmp_path)]) == 2
    assert "no column 'alpha_rad' for alpha" in capsys.readouterr().err
    assert main(["simulate", "--config", str(tmp_path / "none.toml")]) == 2
    assert "cannot read" in capsys.readouterr().err
    rec = Recording(np.array([0.0, 1.0]), np.zeros((2, 2)), np.zeros((2, 7)), "throttle")
    write_csv(tmp_path / "t.csv", rec)
    # A throttle record offered to an aircraft whose thrust is measured.
    hfb = ["--config", "hfb320"]
    assert main(["offline", str(tmp_path / "t.csv"), *hfb, "--out", str(tmp_path)]) == 2
    assert "[propulsion] model" in capsys.readouterr().err
    # A folder stands for a data file only when it holds exactly one.
    assert main(["offline", str(tmp_path), *hfb, "--out", str(tmp_path / "o")]) == 2
    assert "several flight-data files (t.csv, x.csv); give one" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["offline", str(tmp_path / "empty"), *hfb, "--out", str(tmp_path / "o")]) == 2
    assert "no flight data in it" in capsys.readouterr().err
    assert main(["offline", "hfb321", "--out", str(tmp_path / "o")]) == 2
    assert "bundled records: hfb320" in capsys.readouterr().err
    # A window the wrong way round is refused before any work, not after the filters ran.
    assert main(["refine", "hfb320", "--window", "10:5", "--out", str(tmp_path / "w")]) == 2
    assert "--window '10:5': FROM must come before TO" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


def test_the_backend_is_a_developers_environment_variable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The numpy reference backend is chosen by GCS_ESTIMATOR_BACKEND, read once at the
    edge; the user's command line has no --backend."""
    assert backend_of({}) == "fast"
    assert backend_of({BACKEND_VARIABLE: "reference"}) == "reference"
    with pytest.raises(SystemExit):
        main(["simulate", "--backend", "reference", "--out", str(tmp_path)])
    assert "unrecognized arguments: --backend" in capsys.readouterr().err
    monkeypatch.setenv(BACKEND_VARIABLE, "numpy")
    assert main(["simulate", "--out", str(tmp_path)]) == 2
    assert "GCS_ESTIMATOR_BACKEND='numpy': must be 'fast' or 'reference'" in (
        capsys.readouterr().err
    )


def test_the_json_says_which_run_made_it(tmp_path: Path) -> None:
    data_file = ROOT / "gcs_estimator/data/hfb320/hfb320_1_10.asc"
    argv = ["offline", str(data_file), "--config", "hfb320", "--out", str(tmp_path)]
    assert main([*argv, "--view", "off"]) == 0
    run = json.loads((tmp_path / "results_sys1.json").read_text())["run"]
    import hashlib

    assert run["command"] == "offline" and run["command_line"][1:] == [*argv, "--view", "off"]
    assert run["source"] == str(data_file)
    assert run["source_sha256"] == hashlib.sha256(data_file.read_bytes()).hexdigest()
    assert len(run["config_sha256"]) == 64 and run["config"].endswith("hfb320.toml")
    assert run["started_utc"] <= run["ended_utc"]
    check = run["compatibility"]  # the data compatibility check's findings (decision 0056)
    assert check["mode"] == "report" and not check["corrected"]
    found = {(f["channel"], f["kind"]) for f in check["findings"]}
    assert found >= {("q", "bias"), ("a_x", "bias")}


def test_observations_that_never_match_the_config_exit_1_with_the_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fl = load_hfb320(ROOT / "gcs_estimator/data/hfb320/hfb320_1_10.asc")
    blank = Recording(fl.t_s, fl.inputs, np.full_like(fl.measurements, np.nan), fl.power)
    path = tmp_path / "blank.csv"
    write_csv(path, blank)
    status = main(["offline", str(path), "--config", "hfb320", "--out", str(tmp_path / "o")])
    assert status == 1
    assert "no frame's observations could be used" in capsys.readouterr().err


def test_airframe_writes_a_starter_that_names_what_to_fill_in(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The starter file is TOML the estimator reads; until a FILL IN value is given the
    error names that key; filled in, it loads. An existing file is kept unless --force."""
    from gcs_estimator.config import ConfigError

    path = tmp_path / "my_plane.toml"
    assert main(["airframe", str(path)]) == 0
    text = path.read_text()
    assert "FILL IN" in text and "[propulsion]" in text and "[coefficients]" in text
    with pytest.raises(ConfigError, match=r"\[airframe\] mass_kg: must be a number > 0"):
        load_config(path)
    filled = {
        "mass_kg": 4.2,
        "wing_area_m2": 0.45,
        "mean_chord_m": 0.22,
        "inertia_yy_kgm2": 0.35,
        "trim_airspeed_mps": 18.0,
        "prop_diameter_m": 0.3556,
        "max_power_w": 600.0,
    }
    for key, value in filled.items():
        text = re.sub(rf"^{key} = 0\.0 ", f"{key} = {value} ", text, flags=re.MULTILINE)
    path.write_text(text)
    config = load_config(path)
    assert config.airframe.mass_kg == 4.2 and config.propulsion.max_power_w == 600.0
    assert config.propulsion.constants(1.225).scale_sigma > 0.0  # a spec sheet's guess
    assert config.truth is None
    assert main(["airframe", str(path)]) == 2
    assert "the file exists" in capsys.readouterr().err
    assert path.read_text() == text
    assert main(["airframe", str(path), "--force"]) == 0 and "FILL IN" in path.read_text()


def test_a_data_file_without_an_airframe_file_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A CSV is some aircraft's: without --config the run would borrow another's mass and
    reference values. The bundled record needs none (its airframe ships with it)."""
    rec = Recording(np.array([0.0, 0.02]), np.zeros((2, 2)), np.zeros((2, 7)), "throttle")
    write_csv(tmp_path / "mine.csv", rec)
    assert main(["offline", str(tmp_path / "mine.csv"), "--out", str(tmp_path / "o")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "mine.csv: no airframe file: give --config FILE" in line
    assert main(["refine", str(tmp_path / "gone.csv"), "--out", str(tmp_path / "o")]) == 2
    assert "gone.csv: no such file" in capsys.readouterr().err


def test_filters_that_diverge_on_most_frames_exit_1_saying_so(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """NaN inputs (what empty CSV cells were before they were held) diverge the filters on
    most frames: the run says its numbers are not estimates, and exits 1."""
    from gcs_estimator.cli import EXIT_NOTHING_ESTIMATED, _run
    from gcs_estimator.runtime.session import RecordingSource, Session
    from gcs_estimator.stop import Stop
    from sim.truth import simulate

    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=4"])
    flight = simulate(config, seed=1)
    inputs = flight.inputs.copy()
    inputs[np.arange(len(inputs)) % 8 != 0, 0] = np.nan  # the elevator in every 8th row
    session = Session(config, keep_history=False)
    source = RecordingSource(flight.t_s, inputs, flight.measurements)
    assert _run(session, source, Stop()) == EXIT_NOTHING_ESTIMATED
    assert "the filters diverged on most frames of vehicle(s) [1]" in capsys.readouterr().err
    good = RecordingSource(flight.t_s, flight.inputs, flight.measurements)
    assert _run(Session(config, keep_history=False), good, Stop()) == 0


def test_a_vehicle_that_never_flew_exits_1_saying_so(capsys: pytest.CaptureFixture[str]) -> None:
    """On the ground (airspeed 1 m/s, the trim 24): nothing to identify, and the run says
    why rather than print coefficients."""
    from gcs_estimator.cli import EXIT_NOTHING_ESTIMATED, _run
    from gcs_estimator.runtime.session import RecordingSource, Session
    from gcs_estimator.stop import Stop
    from sim.truth import simulate

    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=4"])
    flight = simulate(config, seed=1)
    ground = flight.measurements.copy()
    ground[:, 0] = 1.0
    source = RecordingSource(flight.t_s, flight.inputs, ground)
    assert _run(Session(config), source, Stop()) == EXIT_NOTHING_ESTIMATED
    err = capsys.readouterr().err
    assert "vehicle 1 never flew: its airspeed never reached 0.5 x" in err and "(12 m/s)" in err


def test_the_throttle_servo_rule_is_a_links_not_a_data_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Measured thrust comes over MAVLink as NAMED_VALUE_FLOAT, so a link or log needs
    [link] throttle_servo = 0 with it; a data file's thrust column needs no such setting."""
    measured = ["--config", "noc_uav", "--set", 'propulsion.model="measured"']
    argv = ["replay", str(tmp_path / "x.tlog"), *measured, "--out", str(tmp_path / "r")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "[link] throttle_servo: must be 0 (thrust comes as NAMED_VALUE_FLOAT" in err
    config = load_config("noc_uav", ['propulsion.model="measured"'])
    assert config.link.throttle_servo == 3 and config.link_problem() is not None
