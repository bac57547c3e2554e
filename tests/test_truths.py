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
    config = load_config("noc_uav", [SHORT])
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
