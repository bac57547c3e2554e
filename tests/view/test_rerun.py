"""The Rerun view: real .rrd recordings read back with Rerun's own reader, a real gRPC
server joined late by the real viewer binary, and viewers that are absent or hung."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from gcs_estimator.config import load_config
from gcs_estimator.estimation.estimator import FILTER_KINDS, Track
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import TlogWriter
from gcs_estimator.model.channels import FLIGHT_STATES as STATE_NAMES
from gcs_estimator.outputs.table import final_table, live_table
from gcs_estimator.outputs.view import layout as lay
from gcs_estimator.outputs.view import live
from gcs_estimator.outputs.view.live import RerunView, ViewSink
from gcs_estimator.outputs.view.outlets import LocalOutlet
from gcs_estimator.runtime.decode_worker import tlog_source
from gcs_estimator.runtime.session import RecordingSource, Session
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle

ROOT = Path(__file__).resolve().parents[2]
SHORT = ["simulation.manoeuvre.duration_s=12"]


def read_scalars(path: Path, entity: str, timeline: str = lay.TIMELINE) -> tuple[np.ndarray, ...]:
    """(times [s], values [N x k]) of a Scalars entity, sorted by the timeline."""
    chunks = (
        RrdReader(path)
        .stream()
        .filter(content=entity, is_static=False, components="Scalars:scalars")
        .to_chunks()
    )
    assert chunks, f"{entity}: no data in {path}"
    table = pa.Table.from_batches([c.to_record_batch() for c in chunks])
    t = table.column(timeline).cast(pa.int64()).to_numpy() * 1e-9
    values = np.array(table.column("Scalars:scalars").to_pylist(), float)
    order = np.argsort(t, kind="stable")
    return t[order], values[order]


def read_texts(path: Path, entity: str) -> list[str]:
    chunks = RrdReader(path).stream().filter(content=entity).to_chunks()
    texts: list[str] = []
    for c in chunks:
        batch = c.to_record_batch()
        if "TextDocument:text" in batch.schema.names:
            texts += [v[0] for v in batch.column("TextDocument:text").to_pylist() if v]
    return texts


Run = tuple[VehicleResult, Path, np.ndarray]

F32_EPS = float(np.finfo(np.float32).eps)


def kept(values: np.ndarray) -> np.ndarray:
    """What the history keeps of values the view logs: the filters' float64 outputs to
    float32 (estimator.HISTORY_DTYPE)."""
    return np.asarray(values, float).astype(np.float32).astype(float)


def path_of(run: VehicleResult, name: str, sid: int = 1) -> str:
    """The entity of coefficient `name` (its axis from the run's config)."""
    names = run.result.names
    return lay.coefficient_path(sid, name, run.result.config.structure.axes[names.index(name)])


def tracks(run: VehicleResult) -> dict[str, Track]:
    out = {k: f.track for k, f in run.result.filters.items()}
    assert all(t is not None for t in out.values())
    return out  # type: ignore[return-value]


@pytest.fixture(scope="module")
def short_run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    """A 12 s simulated flight (both restarts included) through the view into an .rrd."""
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    flight = simulate(config, seed=2)
    path = tmp_path_factory.mktemp("view") / "run.rrd"
    session = Session(config)
    clock = iter(np.arange(0.0, 1e6, 0.05))  # a flush every 10 frames: many blocks
    view = RerunView(
        [LocalOutlet("test", save=path)],
        config,
        table_source=lambda sid: live_table(session.estimator(sid)),
        clock=lambda: float(next(clock)),
    )
    session.add_sink(ViewSink(view))
    results = session.run(RecordingSource(flight.t_s, flight.inputs, flight.measurements))
    return results[1], path, flight.t_s


def test_coefficients_are_the_filter_outputs_at_the_estimate_rate(
    short_run: Run,
) -> None:
    run, path, t_s = short_run
    tr = tracks(run)
    truth = np.array(run.result.config.truth)
    axes = run.result.config.structure.axes
    rate, e_rate = live.DISPLAY_RATE_HZ, live.ESTIMATE_RATE_HZ
    assert 0 < e_rate < 1 / np.median(np.diff(t_s))  # the frames come faster: decimated
    for i, name in enumerate(run.result.names):
        t, v = read_scalars(path, path_of(run, name))
        frame = np.searchsorted(t_s, t - 1e-9)
        np.testing.assert_allclose(t, t_s[frame], atol=1e-9)  # ns resolution of the index
        for col, kind in enumerate(FILTER_KINDS):
            np.testing.assert_array_equal(kept(v[:, col]), tr[kind].coefficients[frame, i])
        # Every estimate interval has its row, the newest frame is shown, and a row
        # beyond one per interval is only ever a batch's newest.
        intervals = np.unique(np.floor(t_s * e_rate))
        np.testing.assert_array_equal(np.unique(np.floor(t_s[frame] * e_rate)), intervals)
        assert frame[-1] == len(t_s) - 1
        assert len(t) < len(t_s) and len(t) <= 2 * len(intervals)
        # The bands at the display rate, from the same outputs.
        tb, band = read_scalars(path, lay.band_path(1, name, axes[i]))
        assert len(tb) == len(np.unique(np.floor(t_s * rate)))
        idx = np.searchsorted(t_s, tb - 1e-9)
        for col, kind in enumerate(FILTER_KINDS):
            x = tr[kind].coefficients[idx, i].astype(float)
            s2 = 2 * tr[kind].coefficient_sigma[idx, i].astype(float)
            atol = F32_EPS * float(np.max(np.abs(x) + s2))
            np.testing.assert_allclose(band[:, 2 * col], x - s2, rtol=F32_EPS, atol=atol)
            np.testing.assert_allclose(band[:, 2 * col + 1], x + s2, rtol=F32_EPS, atol=atol)
        tt, tru = read_scalars(path, lay.truth_path(1, name, axes[i]))
        assert tt[0] == pytest.approx(t_s[0]) and tt[-1] == pytest.approx(t_s[-1])
        np.testing.assert_array_equal(tru[:, 0], truth[i])
        trecv, _ = read_scalars(path, path_of(run, name), lay.RECEIVE_TIMELINE)
        np.testing.assert_allclose(trecv, t_s[frame] - t_s[0], atol=1e-9)
    # The restart re-runs are in: what the view showed at 5 s is the history's value.
    assert run.result.restarts_done == 2


def test_display_series_are_decimated_samples_of_the_same_outputs(
    short_run: Run,
) -> None:
    run, path, t_s = short_run
    tr = tracks(run)
    rate = live.DISPLAY_RATE_HZ
    for j, state in enumerate(STATE_NAMES):
        t, v = read_scalars(path, lay.state_path(1, state))
        assert len(t) == len(np.unique(np.floor(t_s * rate)))  # one row per display interval
        idx = np.searchsorted(t_s, t - 1e-9)
        scale = 1.0 if state == "V" else 180 / math.pi
        np.testing.assert_allclose(v[:, 0], tr["EKF"].y[idx, j] * scale, rtol=1e-12)
        np.testing.assert_allclose(v[:, 1], tr["EKF"].x[idx, j] * scale, rtol=F32_EPS)
        np.testing.assert_allclose(v[:, 2], tr["IEKF"].x[idx, j] * scale, rtol=F32_EPS)
    t, nis = read_scalars(path, lay.nis_path(1))
    idx = np.searchsorted(t_s, t - 1e-9)
    np.testing.assert_array_equal(kept(nis[:, 1]), tr["IEKF"].nis[idx])
    used = tr["IEKF"].n_used[idx]
    np.testing.assert_array_equal(np.isfinite(nis[:, 2]), used > 0)  # no update, no bound
    assert np.all(nis[used > 0, 2] < nis[used > 0, 3])  # chi-square 95 % bounds
    _, gust = read_scalars(path, lay.turbulence_path(1))
    np.testing.assert_array_equal(kept(gust[:, 0]), tr["EKF"].gust_sigma[idx])
    np.testing.assert_array_equal(kept(gust[:, 1]), tr["IEKF"].gust_sigma[idx])
    np.testing.assert_array_equal(kept(gust[:, 2]), tr["EKF"].gust_pass_sigma[idx])
    np.testing.assert_array_equal(kept(gust[:, 3]), tr["IEKF"].gust_pass_sigma[idx])
    assert np.all(gust >= 0.0)
    t, el = read_scalars(path, lay.input_path(1, "elevator"))
    np.testing.assert_allclose(el[:, 0], np.degrees(tr["EKF"].u[idx, 0]))
    _, z = read_scalars(path, lay.innovation_path(1, "IEKF"))
    expect = tr["IEKF"].innovation[idx] / tr["IEKF"].innovation_sigma[idx]
    n = expect.shape[1]  # the observation channels (h_dot the last), then the bounds
    np.testing.assert_allclose(z[:, :n], expect, rtol=4 * F32_EPS, equal_nan=True)
    assert np.all(z[:, n] == -2) and np.all(z[:, n + 1] == 2)


def test_results_table_and_layout_are_in_the_recording(
    short_run: Run,
) -> None:
    run, path, _ = short_run
    texts = read_texts(path, lay.results_path(1))
    assert len(texts) >= 2  # live updates, then the final table
    assert texts[-1] == final_table(run)
    assert "| CLa |" in texts[0]
    # The series styles are static and name the filters and the truth line.
    styles = RrdReader(path).stream().filter(content=path_of(run, "Cma"), is_static=True)
    names = [
        c.to_record_batch().column("SeriesLines:names").to_pylist()
        for c in styles.to_chunks()
        if "SeriesLines:names" in c.to_record_batch().schema.names
    ]
    assert names and names[0][0] == ["EKF", "IEKF"]
    # The blueprint travels with the recording: a view for every coefficient and state.
    reader = RrdReader(path)
    origins: set[str] = set()
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        if "ViewBlueprint:space_origin" in batch.schema.names:
            origins.update(o[0] for o in batch.column("ViewBlueprint:space_origin").to_pylist())
    assert {path_of(run, n) for n in run.result.names} <= origins
    assert {lay.state_path(1, s) for s in STATE_NAMES} <= origins
    assert {lay.nis_path(1), lay.results_path(1), "/link"} <= origins


def short_tlog(path: Path, vehicles: int) -> None:
    """Several simulated vehicles' telemetry (each from its own tlog) merged into one."""
    from gcs_estimator.ingest.flightdata import Recording
    from gcs_estimator.ingest.telemetry.mavlink import read_tlog

    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    records: list[tuple[int, bytes]] = []
    for sid in range(1, vehicles + 1):
        fl = simulate(config, seed=sid)
        rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
        own = path.with_suffix(f".{sid}.tlog")
        SimulatedVehicle(
            rec, config.link, ("127.0.0.1", 9), system_id=sid, speed=0.0, tlog=own
        ).run()
        records += [(r.t_recv_us, r.packet) for r in read_tlog(own)]
    records.sort(key=lambda r: r[0])
    w = TlogWriter(path)
    for i, (_, p) in enumerate(records):
        w.write(1_000_000_000 + 1000 * i, p)  # 1 ms apart: inside every wait
    w.close()


def test_replay_of_two_vehicles_gives_one_subtree_each_and_link_health(tmp_path: Path) -> None:
    tlog = tmp_path / "two.tlog"
    short_tlog(tlog, 2)
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    rrd = tmp_path / "two.rrd"
    session = Session(config)
    link = MavlinkLink(config.link)
    view = RerunView(
        [LocalOutlet("two", save=rrd)],
        config,
        link_source=lambda: (link.session_time(), link.health.as_dict()),
    )
    session.add_sink(ViewSink(view, lambda: link.t_first_recv))
    results = session.run(tlog_source([tlog], link))
    for sid in (1, 2):
        run = results[sid]
        t, v = read_scalars(rrd, path_of(run, "Cmq", sid))
        track = tracks(run)["IEKF"]
        frame = np.searchsorted(track.t, t - 1e-9)
        np.testing.assert_allclose(t, track.t[frame], atol=1e-9)  # this vehicle's frames
        assert frame[-1] == run.result.frames - 1
        np.testing.assert_array_equal(
            kept(v[:, 1]), track.coefficients[frame, run.result.names.index("Cmq")]
        )
    t, counts = read_scalars(rrd, lay.LINK_COUNTS)
    assert counts[-1, 0] == link.health.total().lost
    _, rate = read_scalars(rrd, lay.LINK_RATE)
    assert np.all(rate >= 0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


RERUN_BIN = Path(rr.__file__).parent.parent / "rerun_cli" / "rerun"


def test_served_session_outlives_the_run_and_a_late_viewer_gets_it_all(tmp_path: Path) -> None:
    """A replay serving its view ends; the server stays up for serve_linger_s, saying so,
    and the real viewer binary, joining only then, still receives everything from the
    start, and leaves when the server goes."""
    tlog = tmp_path / "one.tlog"
    short_tlog(tlog, 1)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    session = subprocess.Popen(
        [
            sys.executable, "-m", "gcs_estimator", "replay", str(tlog),
            "--config", str(ROOT / "configs/noc_uav.toml"), "--set", SHORT[0],
            "--set", "view.serve_linger_s=8", "--out", str(tmp_path),
            "--view", "serve", "--serve-port", str(port), "--history", "csv",
        ],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    assert session.stderr is not None
    line = ""
    while "still serving" not in line:  # the run is over; the server is still up
        line = session.stderr.readline()
        assert line, "the session ended without lingering"
    uri = line.split("still serving ")[1].split()[0]
    joiner = subprocess.run(
        [str(RERUN_BIN), uri, "--save", str(tmp_path / "joined.rrd")],
        capture_output=True,
        timeout=120,  # hang guard: it leaves when the server goes
        env={**env, "RERUN_ANALYTICS": "0"},
    )
    assert session.wait(timeout=60) == 0
    assert joiner.returncode == 0
    t, v = read_scalars(tmp_path / "joined.rrd", lay.coefficient_path(1, "Cma", "Cm"))
    hist = np.genfromtxt(
        tmp_path / "results_sys1_history.csv",
        delimiter=",",
        names=True,
        dtype=None,
        encoding="utf-8",
    )
    iekf = hist[hist["filter"] == "IEKF"]
    frame = np.searchsorted(iekf["t_s"], t - 1e-9)
    np.testing.assert_allclose(t, iekf["t_s"][frame], atol=1e-9)
    assert frame[0] == 0 and frame[-1] == len(iekf) - 1  # from the first frame to the last
    # The history file holds each estimate as the float32 it keeps, in its shortest text.
    np.testing.assert_array_equal(kept(v[:, 1]), kept(iekf["Cma"][frame]))


class SilentPeer:
    """Accepts TCP connections and never answers: a hung viewer."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = int(self.sock.getsockname()[1])
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)

    def close(self) -> None:
        self.sock.close()
        for c in self.conns:
            c.close()


@pytest.fixture
def silent_peer() -> Iterator[SilentPeer]:
    peer = SilentPeer()
    yield peer
    peer.close()


@pytest.mark.parametrize("viewer", ["hung", "absent", "spawned without a display"])
def test_run_completes_normally_when_the_viewer_is_unreachable(
    tmp_path: Path, silent_peer: SilentPeer, viewer: str
) -> None:
    """Stream to a viewer that never answers, to a port nobody listens on, or to a viewer
    spawned where it cannot open a window: the run ends with exit 0, its results and its
    .rrd, and does not hang on exit."""
    cmd = [
        sys.executable,
        "-m",
        "gcs_estimator",
        "simulate",
        "--config",
        str(ROOT / "configs/noc_uav.toml"),
        "--set",
        SHORT[0],
        "--out",
        str(tmp_path),
    ]
    if viewer == "spawned without a display":
        cmd += ["--view", "save,spawn", "--set", f"view.viewer_port={free_port()}"]
        expect = "spawning a viewer on port"
    else:
        port = silent_peer.port if viewer == "hung" else free_port()
        cmd += ["--view", "save", "--connect", f"rerun+http://127.0.0.1:{port}/proxy"]
        expect = "streaming to rerun+http://127.0.0.1"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    # A hang guard only (the SDK alone would wait for ever on the hung viewer).
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr
    assert expect in proc.stderr
    data = json.loads((tmp_path / "results_sys1.json").read_text())
    assert set(data["filters"]) == set(FILTER_KINDS)
    t, _ = read_scalars(tmp_path / "view.rrd", lay.coefficient_path(1, "CLa", "CL"))
    # The whole 12 s flight is saved: an estimate in every 1/25 s interval, to the last.
    assert t[-1] == pytest.approx(12.0)
    assert len(np.unique(np.floor(t * 25.0 + 1e-6))) == 301


def test_reference_values_from_the_command_line_are_shown_and_compared(
    tmp_path: Path, hfb_data_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ref = tmp_path / "book.toml"
    names = load_config(ROOT / "configs/hfb320.toml").coefficient_names
    ref.write_text(
        '[truth]\nlabel = "book"\n' + "".join(f"{n} = {i + 1}.5\n" for i, n in enumerate(names))
    )
    from gcs_estimator.cli import main

    def offline(*view: str) -> int:
        cmd = ["offline", str(hfb_data_path), "--config", str(ROOT / "configs/hfb320.toml")]
        return main(
            [*cmd, "--reference", str(ref), "--out", str(tmp_path), "--force", "--view", *view]
        )

    assert offline("save") == 0
    data = json.loads((tmp_path / "results_sys1.json").read_text())
    assert data["truth_label"] == "book"
    assert data["filters"]["IEKF"]["estimates"]["Cma"]["truth"] == names.index("Cma") + 1.5
    _, v = read_scalars(tmp_path / "view.rrd", lay.truth_path(1, "Cma", "Cm"))
    assert np.all(v[:, 0] == names.index("Cma") + 1.5)
    # A reference that misses a coefficient names the file and the key.
    ref.write_text("[truth]\nCD0 = 1.0\n")
    capsys.readouterr()
    assert offline("off") == 2
    assert f"{ref}: [truth] CDV: missing" in capsys.readouterr().err


def test_serving_on_a_port_another_program_listens_on_is_refused_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A port taken by another program: the view's server thread would stop at once and
    the run would go on saying it serves (and wait 30 s at the end for viewers that can
    never join). The command refuses it before the run, naming the port and the option
    to change; the same port, freed, serves."""
    from gcs_estimator.cli import main

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        argv = ["simulate", "--set", "simulation.manoeuvre.duration_s=2", "--view", "serve"]
        argv += ["--serve-port", str(port), "--out", str(tmp_path / "held")]
        assert main(argv) == 2
    assert f"view.serve_port {port} on 127.0.0.1: cannot serve there" in capsys.readouterr().err
    from gcs_estimator.outputs.view.outlets import LocalOutlet

    outlet = LocalOutlet("free", serve=("127.0.0.1", port, "1MB"))
    assert outlet.server_uri is not None and str(port) in outlet.server_uri
    outlet.close()
