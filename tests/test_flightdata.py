"""Any CSV: columns named and units given in the config, errors that name the key."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import FlightDataError, Recording, load_csv, write_csv
from gcs_estimator.model.channels import Channel
from gcs_estimator.units import FOOT, G0, KNOT
from sim.truth import simulate
from tests.logs.ulog_files import quaternion

# A logger's own layout: its names, knots, degrees, g, percent throttle, milliseconds.
FOREIGN = {
    "time": ("t_ms", "ms", 1e3),
    "airspeed": ("TAS", "kt", 1.0 / KNOT),
    "alpha": ("AoA", "deg", 180.0 / math.pi),
    "theta": ("Pitch", "deg", 180.0 / math.pi),
    "q": ("GyrY", "deg/s", 180.0 / math.pi),
    "qdot": ("dGyrY", "deg/s^2", 180.0 / math.pi),
    "a_x": ("AccX", "g", 1.0 / G0),
    "a_z": ("AccZ", "ft/s^2", 1.0 / FOOT),
    "elevator": ("Elev", "deg", 180.0 / math.pi),
    "throttle": ("Thr", "%", 100.0),
}
OVERRIDES = [f"data.columns.{q}={col}" for q, (col, _, _) in FOREIGN.items()] + [
    f'data.units.{q}="{unit}"' for q, (_, unit, _) in FOREIGN.items()
]


def _write_foreign(path: Path, rec: Recording, drop: str = "") -> None:
    values = {
        "time": rec.t_s,
        **{q: rec.measurements[:, i - 1] for i, q in enumerate(FOREIGN) if 0 < i < 8},
        "elevator": rec.inputs[:, 0],
        "throttle": rec.inputs[:, 1],
    }
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        names = [q for q in FOREIGN if q != drop]
        w.writerow(["Extra", *(FOREIGN[q][0] for q in names)])
        for i in range(len(rec)):
            w.writerow(["x", *(repr(float(values[q][i] * FOREIGN[q][2])) for q in names)])


@pytest.fixture(scope="module")
def flight() -> Recording:
    fl = simulate(load_config("noc_uav", ["simulation.manoeuvre.duration_s=5"]), seed=3)
    # The seven channels the CSV layout has (no climb-rate column): h_dot missing.
    return Recording(fl.t_s, fl.inputs, fl.measurements[:, :7], "throttle")


def test_a_foreign_csv_reads_back_in_si(tmp_path: Path, flight: Recording) -> None:
    path = tmp_path / "log.csv"
    _write_foreign(path, flight)
    rec = load_csv(path, load_config("noc_uav", OVERRIDES).data)
    assert rec.power == "throttle"
    np.testing.assert_allclose(rec.t_s, flight.t_s, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rec.measurements, flight.measurements, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rec.inputs, flight.inputs, rtol=1e-12, atol=1e-12)


def test_a_climb_rate_column_is_read_in_its_unit_and_written_back(tmp_path: Path) -> None:
    """The optional climb-rate column ([data.columns] climb_rate): h_dot where the file
    has it, in its configured unit; write_csv writes it where the recording has one."""
    fl = simulate(
        load_config("noc_uav", ["simulation.manoeuvre.duration_s=5", "simulation.climb_rate=true"]),
        seed=3,
    )
    rec = Recording(fl.t_s, fl.inputs[:, :2], fl.measurements, "throttle")
    assert np.isfinite(rec.measurements[:, Channel.HDOT]).all()
    path = tmp_path / "with.csv"
    write_csv(path, rec)
    back = load_csv(path)
    np.testing.assert_array_equal(back.measurements, rec.measurements)
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    col = rows[0].index("climb_rate_mps")
    for row in rows[1:]:
        row[col] = repr(float(row[col]) / FOOT)
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    data = load_config("noc_uav", ['data.units.climb_rate="ft/s"']).data
    np.testing.assert_allclose(load_csv(path, data).measurements, rec.measurements, rtol=1e-12)


def test_a_csv_carries_the_turns_as_columns_or_as_the_attitude_quaternion(tmp_path: Path) -> None:
    """A mission's turns in a CSV: the bank angle, roll and yaw rates as their own columns
    (write_csv writes them) read back as the model's turn inputs and the segments' bank;
    or the attitude as PX4's quaternion, with a down-positive vertical speed: theta and
    phi from it, the climb rate from the speed with [data.scale] climb_rate = -1. A bank
    column in degrees read as radians is refused naming the unit."""
    from sim.scenario import mission

    fl = simulate(load_config("noc_uav", mission("none", 20.0)), seed=2)
    phi = fl.inputs[:, Channel.PHI - Channel.ELEVATOR]
    assert np.abs(phi).max() > math.radians(20)
    assert np.isfinite(fl.measurements).all()  # the climb rate too
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    path = tmp_path / "turns.csv"
    write_csv(path, rec)
    back = load_csv(path)
    np.testing.assert_array_equal(back.inputs[:, 3:6], fl.inputs[:, 3:6])
    np.testing.assert_array_equal(back.aux["phi"], phi)
    np.testing.assert_array_equal(back.measurements, rec.measurements)

    theta = fl.measurements[:, Channel.THETA]
    psi = np.linspace(-3.0, 3.0, len(theta))  # any heading: it must not leak into them
    columns = {
        "time": fl.t_s,
        "airspeed": fl.measurements[:, Channel.V],
        "q": fl.measurements[:, Channel.Q],
        "a_x": fl.measurements[:, Channel.AX],
        "a_z": fl.measurements[:, Channel.AZ],
        "elevator": fl.inputs[:, 0],
        "throttle": fl.inputs[:, 1],
        "vz": -fl.measurements[:, Channel.HDOT],
        "p": fl.inputs[:, 4],
        "r": fl.inputs[:, 5],
    }
    # Its norm a little off 1, as a logger's rounding leaves it; one row's cells empty.
    parts = [1.02 * c for c in quaternion(phi, theta, psi)]
    quat = dict(zip(("q0", "q1", "q2", "q3"), parts, strict=True))
    lost = 100
    px4 = tmp_path / "px4.csv"
    with open(px4, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*columns, *quat])
        for i in range(len(fl.t_s)):
            cells = [repr(float(v[i])) for v in (*columns.values(), *quat.values())]
            w.writerow(cells[: len(columns)] + [""] * 4 if i == lost else cells)
    sets = [
        'data.columns.alpha=""',
        'data.columns.qdot=""',
        'data.columns.theta=""',
        "data.columns.climb_rate=vz",
        "data.scale.climb_rate=-1",
        *(f"data.columns.{q}={q}" for q in ("time", "airspeed", "q", "a_x", "a_z", "p", "r")),
        *(f"data.columns.{q}={q}" for q in ("elevator", "throttle")),
        *(f"data.columns.quat_{a}=q{i}" for i, a in enumerate("wxyz")),
    ]
    read = load_csv(px4, load_config("noc_uav", sets).data)
    kept = np.arange(len(theta)) != lost
    assert np.isnan(read.measurements[lost, Channel.THETA])  # missing, as its cells
    np.testing.assert_allclose(read.measurements[kept, Channel.THETA], theta[kept], atol=1e-12)
    np.testing.assert_allclose(read.inputs[kept, 3], phi[kept], atol=1e-12)
    # The bank between its neighbours, as a link's is between its samples.
    assert read.inputs[lost, 3] == pytest.approx((phi[lost - 1] + phi[lost + 1]) / 2, abs=1e-12)
    np.testing.assert_allclose(read.inputs[:, 4:6], fl.inputs[:, 4:6], atol=0)
    np.testing.assert_allclose(
        read.measurements[:, Channel.HDOT], fl.measurements[:, Channel.HDOT], atol=1e-15
    )
    assert any("the bank angle from the attitude quaternion" in n for n in read.notes)
    assert any("the pitch angle from the attitude quaternion" in n for n in read.notes)
    assert not any("no theta column" in n for n in read.notes)

    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    col = rows[0].index("phi_rad")
    for row in rows[1:]:
        row[col] = repr(math.degrees(float(row[col])))
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    with pytest.raises(FlightDataError, match=r'phi = "deg"'):
        load_csv(path)
    in_degrees = load_csv(path, load_config("noc_uav", ['data.units.phi="deg"']).data)
    np.testing.assert_allclose(in_degrees.inputs[:, 3], phi, rtol=1e-12, atol=1e-15)

    # Rows before the first elevator sample are dropped, the turns' and climb rate's too.
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    lead = 3
    elevator, roll = rows[0].index("elevator_rad"), rows[0].index("p_radps")
    for row in rows[1 : 1 + lead]:
        row[elevator] = ""
    for row in rows[1:]:
        row[roll] = repr(math.degrees(float(row[roll])))
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    units = ['data.units.phi="deg"', 'data.units.p="deg/s"']
    late = load_csv(path, load_config("noc_uav", units).data)
    assert len(late.t_s) == len(fl.t_s) - lead
    np.testing.assert_allclose(late.inputs[:, 3:5], fl.inputs[lead:, 3:5], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(late.aux["phi"], late.inputs[:, 3])
    np.testing.assert_array_equal(late.measurements, rec.measurements[lead:])
    with pytest.raises(FlightDataError, match=r'p = "deg/s"'):  # a roll rate in deg/s
        load_csv(path, load_config("noc_uav", units[:1]).data)


def test_offline_flies_a_csvs_turns(tmp_path: Path) -> None:
    """`offline` on a mission's CSV: with the turn columns the filters' innovations are
    as large as they predict and every coefficient lies within 3 of its sigmas of the
    truth; the same file without them flies the turns wings level, and its innovations
    are many times the prediction."""
    import json

    from gcs_estimator.cli import main
    from sim.scenario import mission

    fl = simulate(load_config("noc_uav", mission("none", 40.0)), seed=4)
    nis = {}
    for name, inputs in (("turns", fl.inputs), ("level", fl.inputs[:, :2])):
        path = tmp_path / f"{name}.csv"
        write_csv(path, Recording(fl.t_s, inputs, fl.measurements, "throttle"))
        out = tmp_path / name
        argv = ["offline", str(path), "--config", "noc_uav", "--view", "off", "--out", str(out)]
        assert main(argv) == 0
        iekf = json.loads((out / "results_sys1.json").read_text())["filters"]["IEKF"]
        nis[name] = iekf["mean_nis"] / iekf["mean_channels"]
        if name == "turns":
            for (n, e), truth in zip(iekf["estimates"].items(), fl.truth, strict=True):
                assert abs(e["estimate"] - truth) < 3.0 * e["sigma"], n
    assert nis["turns"] < 1.5 and nis["level"] > 10.0, nis


def test_a_missing_column_names_the_key_to_set(tmp_path: Path, flight: Recording) -> None:
    path = tmp_path / "log.csv"
    _write_foreign(path, flight, drop="q")
    with pytest.raises(FlightDataError, match=r"no column 'GyrY' for q; .*\[data.columns\] q"):
        load_csv(path, load_config("noc_uav", OVERRIDES).data)
    with pytest.raises(FlightDataError, match=r"no column 'time_s' for time"):
        load_csv(path)  # the project's own layout expected


def test_a_log_without_pitch_acceleration_runs_without_that_channel(
    tmp_path: Path, flight: Recording, capsys: pytest.CaptureFixture[str]
) -> None:
    """Most loggers record no pitch acceleration: `qdot = ""` says the data have none, the
    channel reads as missing throughout, the run says so and goes on with the others
    (the warm start differentiates q). Without it the error says how."""
    import json

    from gcs_estimator.cli import main

    path = tmp_path / "log.csv"
    _write_foreign(path, flight, drop="qdot")
    with pytest.raises(FlightDataError, match=r'if the data have no qdot, qdot = ""'):
        load_csv(path, load_config("noc_uav", OVERRIDES).data)
    without = [o for o in OVERRIDES if not o.startswith("data.columns.qdot=")]
    rec = load_csv(path, load_config("noc_uav", [*without, 'data.columns.qdot=""']).data)
    assert np.all(np.isnan(rec.measurements[:, 4]))
    kept = [0, 1, 2, 3, 5, 6]
    np.testing.assert_allclose(rec.measurements[:, kept], flight.measurements[:, kept], rtol=1e-12)
    np.testing.assert_allclose(rec.inputs, flight.inputs, rtol=1e-12, atol=1e-12)
    assert any('no qdot column ([data.columns] qdot = "")' in n for n in rec.notes)
    sets = [a for o in [*without, 'data.columns.qdot=""'] for a in ("--set", o)]
    out = tmp_path / "run"
    assert (
        main(
            ["offline", str(path), "--config", "noc_uav", "--view", "off", "--out", str(out), *sets]
        )
        == 0
    )
    said = capsys.readouterr()
    assert "no qdot column" in said.out + said.err
    res = json.loads((out / "results_sys1.json").read_text())
    ekf = res["filters"]["EKF"]
    assert ekf["mean_channels"] == pytest.approx(6.0)
    assert ekf["innovation_mean_square"]["qdot"] is None
    assert all(math.isfinite(e["estimate"]) for e in ekf["estimates"].values())


def test_an_unknown_unit_is_refused_with_the_allowed_ones() -> None:
    from gcs_estimator.config import ConfigError

    with pytest.raises(ConfigError, match=r"\[data.units\] airspeed: must be one of 'm/s', 'kt'"):
        load_config("noc_uav", ['data.units.airspeed="mph"'])


def _overrides_without(quantity: str) -> list[str]:
    """The foreign layout's overrides but for one quantity's unit (left at SI)."""
    return [o for o in OVERRIDES if not o.startswith(f"data.units.{quantity}=")]


@pytest.mark.parametrize(
    ("quantity", "unit"),
    [("alpha", "deg"), ("theta", "deg"), ("q", "deg/s"), ("elevator", "deg"), ("time", "ms")],
)
def test_a_column_in_the_wrong_unit_is_refused_naming_the_likely_one(
    tmp_path: Path, flight: Recording, quantity: str, unit: str
) -> None:
    path = tmp_path / "log.csv"
    _write_foreign(path, flight)
    with pytest.raises(FlightDataError, match=rf"data\.units\.{quantity}={unit}\b"):
        load_csv(path, load_config("noc_uav", _overrides_without(quantity)).data)


def test_absurd_values_are_refused_naming_the_limit(tmp_path: Path, flight: Recording) -> None:
    """Alpha in degrees read as radians: beyond what a fixed-wing aircraft's alpha can
    reach (config.PLAUSIBLE_MAX), and the message says the limit."""
    path = tmp_path / "log.csv"
    _write_foreign(path, flight)
    with pytest.raises(
        FlightDataError, match=r"alpha reaches .*beyond the 0\.8 a fixed-wing aircraft's can reach"
    ):
        load_csv(path, load_config("noc_uav", _overrides_without("alpha")).data)


def test_a_bom_a_latin1_byte_and_an_oversized_field(tmp_path: Path, flight: Recording) -> None:
    path = tmp_path / "log.csv"
    _write_foreign(path, flight)
    text = path.read_bytes().replace(b"Extra", "Temp \u00b0C".encode("latin-1"), 1)
    (tmp_path / "latin1.csv").write_bytes(text)
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    data = load_config("noc_uav", OVERRIDES).data
    for name in ("latin1.csv", "bom.csv"):
        rec = load_csv(tmp_path / name, data)
        np.testing.assert_allclose(rec.measurements, flight.measurements, rtol=1e-12)
    lines = path.read_text().splitlines()
    lines[5] = "x" * 200_000 + lines[5]
    (tmp_path / "huge.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(FlightDataError, match=r"huge\.csv:6: not a CSV row"):
        load_csv(tmp_path / "huge.csv", data)


def test_a_config_that_is_not_utf8_names_the_line(tmp_path: Path) -> None:
    from gcs_estimator.config import ConfigError

    path = tmp_path / "plane.toml"
    path.write_bytes(b'base = "noc_uav"\n[airframe]\nname = "Caf\xe9"\n')
    with pytest.raises(ConfigError, match=r"plane\.toml:3: not UTF-8 text \(byte 0xe9\)"):
        load_config(path)


def test_a_loggers_slips_are_mended_and_said(
    tmp_path: Path, flight: Recording, capsys: pytest.CaptureFixture[str]
) -> None:
    """What loggers write now and then: two rows swapped, a row written twice, a row
    without its time, a cell that is not a number, and a last line cut while it was
    written (no line end: its last cell would read as another number). Each is mended
    or skipped and said in a note; every other sample reads back as written."""
    from gcs_estimator.ingest.flightdata import write_csv

    path = tmp_path / "clean.csv"
    write_csv(path, flight)
    header, *rows = path.read_text().splitlines()
    rows[10], rows[11] = rows[11], rows[10]
    rows.insert(20, rows[20])
    rows[30] = "," + rows[30].split(",", 1)[1]  # its time cell empty
    cells = rows[40].split(",")
    cells[2] = "n/a"  # alpha
    rows[40] = ",".join(cells)
    slipped = tmp_path / "slipped.csv"
    slipped.write_text("\n".join([header, *rows])[:-3])  # the last line cut, no line end
    rec = load_csv(slipped)
    # Kept: every sample but the one without a time (row 29 of the flight) and the last.
    keep = np.r_[0:29, 30 : len(flight) - 1]
    np.testing.assert_array_equal(rec.t_s, flight.t_s[keep])
    expect = flight.measurements[keep].copy()
    expect[38, 1] = np.nan  # sample 39 of the flight: its alpha was "n/a"
    np.testing.assert_array_equal(rec.measurements, expect)
    np.testing.assert_array_equal(rec.inputs, flight.inputs[keep])
    text = "\n".join(rec.notes)
    assert "2 row(s) out of time order put back in order" in text
    assert "1 row(s) repeating an earlier row's time skipped (the first at line 23)" in text
    assert "1 row(s) without a time skipped (the first at line 32)" in text
    assert "1 cell(s) of 'alpha_rad' not a number (the first at line 42: 'n/a')" in text
    assert f"the last line (line {len(rows) + 1}) has no line end" in text
    assert len(rec.notes) == 5
    # The run says them too, and estimates from what was kept.
    from gcs_estimator.cli import main

    out = tmp_path / "out"
    args = ["offline", str(slipped), "--config", "noc_uav", "--out", str(out), "--view", "off"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert all(f"note: {note}" in err for note in rec.notes)
    assert (out / "results_sys1.json").exists()


def test_two_recordings_in_one_csv_are_refused_naming_the_line(
    tmp_path: Path, flight: Recording
) -> None:
    """A time that goes back by more than a logger's slip (a second recording appended,
    its clock from zero): refused with the line, not read as one flight."""
    from gcs_estimator.ingest.flightdata import write_csv

    path = tmp_path / "two.csv"
    write_csv(path, flight)
    header, *rows = path.read_text().splitlines()
    path.write_text("\n".join([header, *rows, *rows]) + "\n")
    with pytest.raises(FlightDataError, match=rf"two.csv:{len(rows) + 2}: .*goes back .*Split it"):
        load_csv(path)


def test_an_hfb320_record_cut_while_written_reads_every_whole_line(tmp_path: Path) -> None:
    """The HFB-320 ASCII format as a recorder cut off would leave it: a line missing its
    last columns where a second piece was joined on, a value that is not a number, and a
    last line without its line end (its last number may be cut: 11603.15 read as 1 once
    doubled a run's NIS). The whole lines are read as the bundled record has them."""
    from gcs_estimator.ingest.flightdata import bundled, load_hfb320

    whole = load_hfb320(bundled("hfb320") / "hfb320_1_10.asc")
    assert whole.notes == ()  # the bundled record is whole
    lines = (bundled("hfb320") / "hfb320_1_10.asc").read_text().splitlines()[:60]
    lines[20] = lines[20][:40]  # the first columns only
    cells = lines[30].split()
    cells[5] = "x?"  # alpha
    lines[30] = "   ".join(cells)
    path = tmp_path / "cut.asc"
    path.write_text("\n".join(lines)[:-3])
    rec = load_hfb320(path)
    keep = np.r_[0:20, 21:59]
    np.testing.assert_array_equal(rec.t_s, whole.t_s[keep])
    expect = whole.measurements[keep].copy()
    expect[29, 1] = np.nan  # line 31: alpha was "x?"
    np.testing.assert_array_equal(rec.measurements, expect)
    np.testing.assert_array_equal(rec.inputs, whole.inputs[keep])
    text = "\n".join(rec.notes)
    assert "1 line(s) with fewer than" in text and "the first at line 21" in text
    assert "1 value(s) not a number read as missing (the first at line 31)" in text
    assert "the last line (line 60) has no line end" in text


@pytest.mark.parametrize("separator", [";", "\t"])
def test_a_csv_with_semicolons_or_tabs_reads_as_with_commas(
    tmp_path: Path, flight: Recording, separator: str
) -> None:
    """A spreadsheet in a locale whose decimal mark is a comma writes semicolons between
    columns and commas in numbers; some loggers write tabs. Either reads as the
    comma-separated file does, with a note; it used to be refused as having no column
    'time_s' (the whole header read as one column's name)."""
    from gcs_estimator.ingest.flightdata import write_csv

    path = tmp_path / "commas.csv"
    write_csv(path, flight)
    text = path.read_text()
    other = tmp_path / "other.csv"
    mark = "," if separator == ";" else "."
    other.write_text(text.replace(",", "\0").replace(".", mark).replace("\0", separator))
    a, b = load_csv(path), load_csv(other)
    np.testing.assert_array_equal(b.t_s, a.t_s)
    np.testing.assert_array_equal(b.measurements, a.measurements)
    np.testing.assert_array_equal(b.inputs, a.inputs)
    assert len(b.notes) == 1 and "columns separated by" in b.notes[0]


@pytest.mark.parametrize("read_as", ["s", "ms"])
def test_a_time_column_in_microseconds_is_named_as_such(
    tmp_path: Path, flight: Recording, read_as: str
) -> None:
    """Time in microseconds read as seconds, or as milliseconds after the first hint:
    each time the error names the unit whose steps are below a second (it once always
    said milliseconds, which for microseconds only moved the error)."""
    path = tmp_path / "us.csv"
    write = Recording(flight.t_s * 1e6, flight.inputs, flight.measurements, flight.power)
    from gcs_estimator.ingest.flightdata import write_csv

    write_csv(path, write)
    data = load_config("noc_uav", [f'data.units.time="{read_as}"']).data
    with pytest.raises(FlightDataError, match=rf"\(read as {read_as}\).*data\.units\.time=us\)"):
        load_csv(path, data)


# A ROS (or PX4) export: time in ns since the epoch, body axes x forward, y left, z up
# (FLU), the elevator as a command -1..1 of a 25 deg travel, the inputs logged at half
# the rate of the sensors (an empty cell between samples) and no thrust (a glide).
T0_NS = 1_531_929_211_000_000_000
TRAVEL_DEG = 25.0
ROS = [
    "data.columns.time=stamp_ns",
    "data.columns.airspeed=airspeed",
    'data.columns.alpha=""',
    "data.columns.theta=pitch",
    "data.columns.q=gyro_y",
    'data.columns.qdot=""',
    "data.columns.a_x=acc_x",
    "data.columns.a_z=acc_z",
    "data.columns.elevator=elevator_cmd",
    "data.columns.thrust=thrust",
    'data.units.time="ns"',
    'data.units.elevator="normalised"',
    "data.scale.q=-1",
    "data.scale.a_z=-1",
    f"airframe.elevator_travel_deg={TRAVEL_DEG}",
]


def _write_ros(path: Path, rec: Recording, every: int = 2) -> None:
    """The flight as a ROS export would hold it; the elevator in every `every`-th row."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["stamp_ns", "airspeed", "pitch", "gyro_y", "acc_x", "acc_z", "elevator_cmd",
                    "thrust"])  # fmt: skip
        for i in range(len(rec)):
            v, _, theta, q, _, a_x, a_z = rec.measurements[i, :7]
            cmd = rec.inputs[i, 0] / math.radians(TRAVEL_DEG)
            elevator = repr(float(cmd)) if i % every == 0 else ""
            t_ns = T0_NS + round(float(rec.t_s[i]) * 1e9)
            w.writerow([t_ns, v, theta, -q, a_x, -a_z, elevator, 0.0])


def test_a_ros_export_reads_in_si_and_the_estimators_axes(
    tmp_path: Path, flight: Recording
) -> None:
    """ns time, y and z flipped to x forward z down, a normalised elevator times its
    travel, empty input cells interpolated (input_hold = linear), zero thrust a glide."""
    path = tmp_path / "ros.csv"
    _write_ros(path, flight)
    config = load_config(
        "noc_uav", [*ROS, 'propulsion.model="measured"', 'data.input_hold="linear"']
    )
    rec = load_csv(path, config.data, config.airframe.elevator_travel_deg)
    assert rec.power == "thrust" and not np.any(rec.inputs[:, 1])
    np.testing.assert_allclose(rec.t_s - T0_NS * 1e-9, flight.t_s, atol=1e-6)
    kept = [0, 2, 3, 5, 6]
    np.testing.assert_allclose(rec.measurements[:, kept], flight.measurements[:, kept], rtol=1e-12)
    assert np.all(np.isnan(rec.measurements[:, [1, 4]]))
    assert np.all(np.isfinite(rec.inputs))
    sampled = flight.inputs[::2, 0]
    np.testing.assert_allclose(rec.inputs[::2, 0], sampled, rtol=1e-12, atol=1e-15)
    between = np.interp(flight.t_s[1::2], flight.t_s[::2], sampled)
    np.testing.assert_allclose(rec.inputs[1::2, 0], between, rtol=1e-6, atol=1e-9)
    empty = len(flight) // 2
    assert any(f"{empty} empty input cell(s) filled" in n for n in rec.notes), rec.notes
    assert any("a glide" in n for n in rec.notes)


def test_empty_input_cells_hold_the_earlier_sample_when_asked(
    tmp_path: Path, flight: Recording
) -> None:
    path = tmp_path / "ros.csv"
    _write_ros(path, flight, every=3)
    config = load_config("noc_uav", [*ROS, 'data.input_hold="previous"'])
    rec = load_csv(path, config.data, config.airframe.elevator_travel_deg)
    want = np.repeat(flight.inputs[::3, 0], 3)[: len(flight)]
    np.testing.assert_allclose(rec.inputs[:, 0], want, rtol=1e-12, atol=1e-15)
    held = len(flight) - len(flight.inputs[::3])
    assert any(f"{held} empty input cell(s) filled" in n and "earlier" in n for n in rec.notes)


def test_rows_before_the_first_input_are_skipped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "late.csv"
    path.write_text(
        "time_s,airspeed_mps,alpha_rad,theta_rad,q_radps,qdot_radps2,ax_mps2,az_mps2,"
        "elevator_rad,throttle\n"
        "0.00,20,0.05,0.05,0,0,0,-9.8,,\n"
        "0.02,20,0.05,0.05,0,0,0,-9.8,,0.5\n"
        "0.04,20,0.05,0.05,0,0,0,-9.8,0.01,\n"
        "0.06,20,0.05,0.05,0,0,0,-9.8,,0.7\n"
    )
    rec = load_csv(path)
    np.testing.assert_allclose(rec.t_s, [0.04, 0.06])
    np.testing.assert_allclose(rec.inputs, [[0.01, 0.6], [0.01, 0.7]])
    assert any("2 row(s) before the first sample of every input skipped" in n for n in rec.notes)
    assert any("2 empty input cell(s) filled" in n for n in rec.notes)
    path.write_text(path.read_text().replace("0.01,", ","))
    with pytest.raises(FlightDataError, match=r"'elevator_rad' \(an input\) holds no number"):
        load_csv(path)


def test_a_normalised_elevator_needs_the_travel_and_says_so(
    tmp_path: Path, flight: Recording
) -> None:
    path = tmp_path / "ros.csv"
    ramp = flight.inputs.copy()  # the command ramps from 1 to -0.3, as in a PX4 Gazebo glide
    ramp[:, 0] = np.linspace(1.0, -0.3, len(flight)) * math.radians(TRAVEL_DEG)
    _write_ros(path, Recording(flight.t_s, ramp, flight.measurements, "throttle"))
    config = load_config("noc_uav", ROS)
    with pytest.raises(FlightDataError, match=r"set \[airframe\] elevator_travel_deg"):
        load_csv(path, config.data)  # no travel given
    # Read as radians, a command reaching 1 is no deflection: the advice is the unit.
    as_rad = load_config("noc_uav", [o for o in ROS if "units.elevator" not in o])
    with pytest.raises(FlightDataError, match=r'elevator = "normalised" and \[airframe\]'):
        load_csv(path, as_rad.data, TRAVEL_DEG)


def test_every_missing_column_is_named_in_one_error(tmp_path: Path, flight: Recording) -> None:
    path = tmp_path / "ros.csv"
    _write_ros(path, flight)
    with pytest.raises(FlightDataError) as err:
        load_csv(path)
    text = str(err.value)
    for quantity in ("time", "airspeed", "alpha", "theta", "q", "qdot", "a_x", "a_z", "elevator"):
        assert f"for {quantity}" in text
    assert text.count("\n") == 0 and "[data.columns]" in text and "stamp_ns" in text


def test_ns_read_as_seconds_names_ns(tmp_path: Path, flight: Recording) -> None:
    path = tmp_path / "ros.csv"
    _write_ros(path, flight)
    config = load_config("noc_uav", [o for o in ROS if "units.time" not in o])
    with pytest.raises(FlightDataError, match=r"data\.units\.time=ns\b"):
        load_csv(path, config.data, TRAVEL_DEG)


def test_no_thrust_column_is_a_glide_and_a_zero_scale_is_refused(
    tmp_path: Path, flight: Recording
) -> None:
    from gcs_estimator.config import ConfigError

    path = tmp_path / "ros.csv"
    _write_ros(path, flight)
    text = path.read_text().splitlines()
    path.write_text("\n".join(",".join(r.split(",")[:-1]) for r in text) + "\n")
    config = load_config("noc_uav", [*ROS[:-6], 'data.columns.thrust=""', *ROS[-5:]])
    rec = load_csv(path, config.data, TRAVEL_DEG)
    assert rec.power == "thrust" and not np.any(rec.inputs[:, 1])
    assert any('thrust = ""): a glide' in n for n in rec.notes)
    with pytest.raises(FlightDataError, match=r'thrust = "" for a glide'):
        load_csv(path, load_config("noc_uav", ROS).data, TRAVEL_DEG)
    with pytest.raises(ConfigError, match=r"\[data.scale\] q: a factor must be"):
        load_config("noc_uav", ["data.scale.q=0"])


def test_a_lost_input_sample_where_the_input_changed_is_a_guess(tmp_path: Path) -> None:
    """An empty cell in a column logged every row is a lost sample: where the samples
    either side differ, the frame's input is a guess (Frame.inputs_known False), as the
    link marks it; where they agree, or the column is logged at a lower rate, it is not."""
    head = "time_s,airspeed_mps,alpha_rad,theta_rad,q_radps,qdot_radps2,ax_mps2,az_mps2,"
    rows = [f"{0.02 * k:.2f},20,0.05,0.05,0,0,0,-9.8,{e},0.5" for k, e in enumerate(
        ["0.0", "0.0", "", "0.0", "0.05", "", "0.1", "0.1"])]  # fmt: skip
    path = tmp_path / "lost.csv"
    path.write_text(head + "elevator_rad,throttle\n" + "\n".join(rows) + "\n")
    rec = load_csv(path)
    assert rec.inputs_known is not None
    np.testing.assert_array_equal(rec.inputs_known, [1, 1, 1, 1, 1, 0, 1, 1])
    assert any("1 of them in gaps over 2 x the column's usual" in n for n in rec.notes), rec.notes
    slow = [
        f"{0.02 * k:.2f},20,0.05,0.05,0,0,0,-9.8,{'' if k % 2 else 0.01 * k},0.5" for k in range(8)
    ]
    path.write_text(head + "elevator_rad,throttle\n" + "\n".join(slow) + "\n")
    assert load_csv(path).inputs_known is None  # every other row: a lower rate, held
