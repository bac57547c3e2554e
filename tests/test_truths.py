"""Several vehicles, each scored against its own truth: gcs-sim writes every vehicle's
true coefficients to a side file; a session given the file scores each vehicle against
its own entry, and without one scores only the first vehicle heard (the config's
[truth] describes one aircraft)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.config import ConfigError, load_config, load_truths
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import TlogWriter, read_tlog
from gcs_estimator.runtime.session import Session
from sim.cli import build_parser, recordings
from sim.vehicle import SimulatedVehicle

SHORT = "simulation.manoeuvre.duration_s=30"


def _fleet(tmp_path: Path) -> tuple[Path, Path]:
    """Two simulated vehicles (the second 20 % off the config's values) interleaved in
    one tlog, and the truth file gcs-sim wrote for them."""
    truth = tmp_path / "truth.toml"
    args = build_parser().parse_args(
        ["--vehicles", "2", "--perturb", "0.2", "--truth", str(truth), "--set", SHORT]
    )
    recs = recordings(args)
    config = load_config("noc_uav", args.set)
    tlogs = []
    for k, rec in enumerate(recs):
        path = tmp_path / f"v{k + 1}.tlog"
        SimulatedVehicle(
            rec, config.link, ("127.0.0.1", 9), system_id=k + 1, speed=0.0, tlog=path
        ).run()
        tlogs.append(list(read_tlog(path)))
    both = tmp_path / "fleet.tlog"
    writer = TlogWriter(both)
    for r in sorted(tlogs[0] + tlogs[1], key=lambda r: r.t_recv_us):
        writer.write(r.t_recv_us, r.packet)
    writer.close()
    return both, truth


def test_each_vehicle_is_scored_against_its_own_truth(tmp_path: Path) -> None:
    tlog, truth = _fleet(tmp_path)
    # The estimates alone: no structure check, which widens only sigmas (decision 0066).
    config = load_config("noc_uav", [SHORT, "filter.structure_check=off"])
    names = config.coefficient_names
    truths = load_truths(truth, names)
    assert sorted(truths) == [1, 2]
    np.testing.assert_array_equal(truths[1], config.truth)
    ratio = np.array(truths[2]) / np.array(config.truth)
    np.testing.assert_allclose(np.abs(ratio - 1), 0.2, rtol=1e-12)

    session = Session(config, truths=truths)
    results = session.run(TlogSource([tlog], MavlinkLink(config.link)))
    cma = names.index("Cma")
    for sid in (1, 2):
        v = results[sid]
        np.testing.assert_array_equal(v.truth, truths[sid])
        est = v.result.filters["IEKF"].coefficients[cma]
        assert est == pytest.approx(truths[sid][cma], rel=0.05)  # scored against its own

    plain = Session(config).run(TlogSource([tlog], MavlinkLink(config.link)))
    first = next(iter(plain))
    assert plain[first].truth is not None
    assert all(plain[sid].truth is None for sid in plain if sid != first)


def test_a_bad_truth_file_names_the_key(tmp_path: Path) -> None:
    names = load_config("noc_uav").coefficient_names
    bad = tmp_path / "t.toml"
    bad.write_text("[vehicle.300]\nCD0 = 1\n")
    with pytest.raises(ConfigError, match=r"vehicle\] 300: a system id 1..255"):
        load_truths(bad, names)
    bad.write_text("[vehicle.1]\nCD0 = 1\n")
    with pytest.raises(ConfigError, match=rf"\[vehicle.1\] {names[1]}: missing"):
        load_truths(bad, names)
    full = "".join(f"{n} = 1.0\n" for n in names)
    bad.write_text(f"[vehicle.1]\n{full}CXX = 2\n")
    with pytest.raises(ConfigError, match="CXX"):
        load_truths(bad, names)
    bad.write_text("[vehicles.1]\nCD0 = 1\n")
    with pytest.raises(ConfigError, match="vehicles: unknown key"):
        load_truths(bad, names)


def test_a_reference_that_is_zero_up_to_rounding_gets_no_percent_error() -> None:
    """A reference linearised from aerodynamics that lack a term comes out near 1e-14,
    not 0: an error in percent of it would be a number of 17 digits. It is scored as
    the zero it is (no percent), and the others as before."""
    from gcs_estimator.runtime.session import run_recording
    from gcs_estimator.uncertainty.metrics import percent_error
    from sim.truth import simulate

    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=8"])
    flight = simulate(config, seed=2)
    tiny = load_config("noc_uav", ["simulation.manoeuvre.duration_s=8", "truth.CLq=-9.8e-15"])
    result = run_recording(tiny, flight.t_s, flight.inputs, flight.measurements)
    assert config.truth is not None
    for kind, summary in result.summaries.items():
        by_name = {c.name: c for c in summary.coefficients}
        assert by_name["CLq"].error_pct is None, kind
        assert by_name["CLa"].error_pct == percent_error(
            float(result.result.filters[kind].coefficients[result.result.names.index("CLa")]),
            config.truth[config.coefficient_names.index("CLa")],
        )
    assert percent_error(1.0, 1e-3) == 99900.0  # small, not zero: still in percent


def _one_vehicle_tlog(tmp_path: Path) -> Path:
    """A short simulated flight recorded as a tlog, with nothing beside it."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=8"])
    args = build_parser().parse_args(["--set", "simulation.manoeuvre.duration_s=8"])
    (rec,) = recordings(args)
    path = tmp_path / "flight.tlog"
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
    return path


def _truths_in(out: Path) -> dict[str, float | None]:
    import json

    res = json.loads((out / "results_sys1.json").read_text())
    return {n: e["truth"] for n, e in res["filters"]["IEKF"]["estimates"].items()}


def test_a_log_is_scored_only_against_a_truth_given_for_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """No --config: a log is refused in one line saying what the airframe file holds.
    The truth file beside it may name the airframe (and, for a simulated flight, its
    truth); an explicit --config's [truth] is the user's own reference."""
    from gcs_estimator.cli import main, side_file
    from gcs_estimator.config import FlightAirframe, truths_text

    tlog = _one_vehicle_tlog(tmp_path)
    quick = ["--view", "off", "--set", "filter.structure_check=off"]
    assert main(["replay", str(tlog), "--out", str(tmp_path / "a"), *quick]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {tlog}: no airframe file: give --config")
    assert (
        "mass_kg" in err[0] and "inertia_yy_kgm2" in err[0] and "gcs-estimator airframe" in err[0]
    )

    config = load_config("noc_uav")
    names = config.coefficient_names
    side = side_file(tlog)
    side.write_text(truths_text({}, names, FlightAirframe("noc_uav", (), own_truth=False)))
    assert main(["replay", str(tlog), "--out", str(tmp_path / "b"), *quick]) == 0
    assert "note: the airframe is noc_uav" in capsys.readouterr().err
    assert set(_truths_in(tmp_path / "b").values()) == {None}

    other = tuple(2.0 * v for v in config.truth or ())
    side.write_text(truths_text({1: other}, names, FlightAirframe("noc_uav", (), False)))
    assert main(["replay", str(tlog), "--out", str(tmp_path / "c"), *quick]) == 0
    assert list(_truths_in(tmp_path / "c").values()) == list(other)

    # The user's own airframe file: its [truth] is theirs (the file beside the log unread).
    argv = ["replay", str(tlog), "--config", "noc_uav", "--out", str(tmp_path / "d"), *quick]
    assert main(argv) == 0
    assert list(_truths_in(tmp_path / "d").values()) == list(config.truth or ())


def test_a_demo_recording_replays_with_its_airframe_and_truth(tmp_path: Path) -> None:
    """The demo writes the truth file beside its recording: its airframe, the overrides,
    and that the airframe's [truth] is what the simulated vehicle flew."""
    from gcs_estimator.cli import main
    from gcs_estimator.config import flight_airframe

    sets = ["--set", "simulation.manoeuvre.duration_s=8", "--set", "filter.structure_check=off"]
    demo = tmp_path / "demo"
    assert main(["demo", "--speed", "0", "--view", "off", "--out", str(demo), *sets]) == 0
    named = flight_airframe(demo / "telemetry.truth.toml")
    assert named is not None and named.config == "noc_uav" and named.own_truth
    assert named.overrides == ("simulation.manoeuvre.duration_s=8", "filter.structure_check=off")
    again = tmp_path / "again"
    argv = ["replay", str(demo / "telemetry.tlog"), "--view", "off", "--out", str(again)]
    assert main(argv) == 0
    truth = load_config("noc_uav").truth
    assert list(_truths_in(again).values()) == list(truth or ())
    assert _truths_in(again) == _truths_in(demo)
