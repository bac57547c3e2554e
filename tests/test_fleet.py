"""`batch` on a real Dask cluster: a scheduler and two worker processes started here on
loopback. Each log's estimates equal its `replay` alone; a corrupt log is a failed row; a
worker killed mid-batch loses nothing; a stopped batch resumes where it stopped."""

from __future__ import annotations

import importlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from gcs_estimator import cli
from gcs_estimator.config import ConfigError, load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.telemetry.mavlink import Codec, tlog_record
from gcs_estimator.runtime.logs import estimate_file, tlog_facts
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle

distributed: Any = importlib.import_module("distributed")  # a dependency: no skip

ROOT = Path(__file__).resolve().parent.parent
SHORT = ["simulation.manoeuvre.duration_s=12"]
WAIT_S = 180.0
"""The longest a condition is waited for (a busy machine: workers importing the package
and loading the compiled kernels)."""
UID = 0x0123456789ABCDEF


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _tlog(path: Path, seed: int, uid: int | None = None) -> Path:
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=seed)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
    if uid is not None:  # the autopilot's AUTOPILOT_VERSION first, as a station asks for it
        codec = Codec(1, 1)
        msg = codec.mav.autopilot_version_encode(
            0, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, uid
        )
        first = int.from_bytes(path.read_bytes()[:8], "big")
        path.write_bytes(tlog_record(first, codec.pack(msg)) + path.read_bytes())
    return path


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    d = tmp_path_factory.mktemp("logs")
    return [
        _tlog(d / f"flight{seed}.tlog", seed, UID if seed == 3 else None) for seed in (3, 4, 5, 6)
    ]


class Cluster:
    """A Dask scheduler and two worker processes (each under its nanny) on loopback."""

    def __init__(self, folder: Path) -> None:
        self.file = folder / "scheduler.json"
        py = [sys.executable, "-m"]
        self.procs = [
            subprocess.Popen(
                [*py, "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                 "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(self.file)],
                env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
        ]  # fmt: skip
        _until(self.file.exists, "the scheduler file")
        for _ in range(2):
            self.procs.append(
                subprocess.Popen(
                    [*py, "distributed.cli.dask_worker", "--scheduler-file", str(self.file),
                     "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard"],
                    env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                )
            )  # fmt: skip
        self.client = distributed.Client(scheduler_file=str(self.file), timeout="60s")
        self.client.wait_for_workers(2, timeout=WAIT_S)

    def pids(self) -> dict[str, int]:
        """Each worker's process id by address."""
        pids: dict[str, int] = self.client.run(os.getpid)
        return pids

    def close(self) -> None:
        self.client.close()
        for p in reversed(self.procs):
            p.terminate()
        for p in self.procs:
            p.wait(timeout=60)


def _until(condition: Any, what: str) -> Any:
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"waited {WAIT_S:g} s for {what}")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = Cluster(tmp_path_factory.mktemp("dask"))
    try:
        yield c
    finally:
        c.close()


def _gcs(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gcs_estimator", *args],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=600,
    )  # fmt: skip


def _batch(cluster: Cluster, out: Path, *logs: Path, extra: tuple[str, ...] = ()) -> list[str]:
    return ["batch", *map(str, logs), "--config", "noc_uav", "--scheduler-file", str(cluster.file),
            "--out", str(out),
            "--view", "off", *extra]  # fmt: skip


def _rows(path: Path) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = pq.read_table(path).to_pylist()
    return rows


def test_each_log_as_its_replay_alone_and_a_corrupt_log_is_a_failed_row(
    tmp_path: Path, logs: list[Path], cluster: Cluster
) -> None:
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(os.urandom(4000))
    out = tmp_path / "batch"
    done = _gcs(*_batch(cluster, out, logs[0], logs[1], junk))
    assert done.returncode == 1, done.stderr  # some log failed
    assert "2 logs estimated, 1 failed, 0 not run" in done.stdout
    rows = _rows(out / "coefficients.parquet")
    (failed,) = [r for r in rows if r["status"] == "failed"]
    assert failed["log"] == str(junk) and str(junk) in failed["error"]
    assert failed["estimate"] is None
    for log in logs[:2]:
        alone = tmp_path / f"alone_{log.stem}"
        # The replay alone in this process (decision 0066): the batch's are in its workers.
        assert cli.main(["replay", str(log), "--config", "noc_uav", "--out", str(alone),
                         "--view", "off"]) == 0  # fmt: skip
        own = json.loads((alone / "results_sys1.json").read_text())
        expected = {
            (kind, name): (c["estimate"], c["sigma"], c["identifiability"])
            for kind, f in own["filters"].items()
            for name, c in f["estimates"].items()
        }
        mine = {
            (r["filter"], r["coefficient"]): (r["estimate"], r["sigma"], r["identifiability"])
            for r in rows
            if r["log"] == str(log)
        }
        assert mine == expected
    flights = _rows(out / "flights.parquet")
    assert sorted(f["status"] for f in flights) == ["failed", "ok", "ok"]
    first = next(f for f in flights if f["log"] == str(logs[0]))
    assert first["vehicle"] == f"uid:{UID:016x}" and first["autopilot_uid"] == f"{UID:016x}"
    assert first["frames"] == 601 and first["worker"] in cluster.pids()
    assert Path(first["folder"], "results_sys1_history.parquet").is_file()


def test_a_killed_worker_loses_nothing(tmp_path: Path, logs: list[Path], cluster: Cluster) -> None:
    out = tmp_path / "batch"
    pids = cluster.pids()
    proc = subprocess.Popen(
        [sys.executable, "-m", "gcs_estimator", *_batch(cluster, out, *logs)],
        cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip

    def busy() -> str | None:
        processing = cluster.client.processing()
        return next((w for w, keys in processing.items() if keys and w in pids), None)

    victim = _until(busy, "a worker with a log in hand")
    os.kill(pids[victim], signal.SIGKILL)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr
    assert "4 logs estimated, 0 failed, 0 not run" in stdout
    flights = _rows(out / "flights.parquet")
    assert [f["log"] for f in flights] == [str(p) for p in logs]
    assert all(f["status"] == "ok" for f in flights)
    assert victim not in {f["worker"] for f in flights}  # its log ran again elsewhere
    cluster.client.wait_for_workers(2, timeout=WAIT_S)  # its nanny started another


def test_a_stopped_batch_resumes_where_it_stopped(
    tmp_path: Path, logs: list[Path], cluster: Cluster
) -> None:
    out = tmp_path / "batch"
    proc = subprocess.Popen(
        [sys.executable, "-m", "gcs_estimator", *_batch(cluster, out, *logs)],
        cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stderr is not None
    for line in proc.stderr:
        if line.startswith("[1/4]"):
            proc.send_signal(signal.SIGINT)
            break
    _, rest = proc.communicate(timeout=600)
    assert proc.returncode == 2, rest
    assert "--resume" in rest
    first = [json.loads(x) for x in (out / "done.jsonl").read_text().splitlines()]
    assert 1 <= len(first) < 4
    again = _gcs(*_batch(cluster, out, *logs, extra=("--resume",)))
    assert again.returncode == 0, again.stderr
    assert f"resume: {len(first)} of 4 logs done already, {4 - len(first)} to run" in again.stderr
    flights = _rows(out / "flights.parquet")
    assert [f["log"] for f in flights] == [str(p) for p in logs]
    assert all(f["status"] == "ok" for f in flights)
    ran = [json.loads(x) for x in (out / "done.jsonl").read_text().splitlines()]
    assert len(ran) == 4  # each log estimated once


def test_the_parquet_history_holds_the_csvs_values(tmp_path: Path, logs: list[Path]) -> None:
    import numpy as np

    config = load_config(ROOT / "configs/noc_uav.toml")
    a = estimate_file(logs[1], config, tmp_path / "p", history_format="parquet")
    b = estimate_file(logs[1], config, tmp_path / "c", history_format="csv")
    assert a.error is None and b.error is None
    assert a.coefficients == b.coefficients
    wide = pq.read_table(tmp_path / "p" / "results_sys1_history.parquet").to_pydict()
    lines = (tmp_path / "c" / "results_sys1_history.csv").read_text().splitlines()
    header = lines[0].split(",")
    iekf = [line.split(",") for line in lines[1:] if line.startswith("IEKF,")]
    assert len(iekf) == len(wide["t_s"]) == 601
    for name, dtype in (("t_s", float), ("meas_V", float), ("CD0", np.float32),
                        ("sigma_CD0", np.float32)):  # fmt: skip
        column = f"IEKF_{name}" if dtype is np.float32 else name
        csv = np.array([float(r[header.index(name)]) for r in iekf]).astype(dtype)
        assert np.array_equal(np.asarray(wide[column]).astype(dtype), csv), name
    size = (tmp_path / "p" / "results_sys1_history.parquet").stat().st_size
    # A fifth of the CSV per vehicle-hour is the target (`bench fleet_dask`); 12 s of
    # flight carry the file's fixed cost too.
    assert size < (tmp_path / "c" / "results_sys1_history.csv").stat().st_size / 4


def _estimates(data: dict[str, Any]) -> dict[tuple[str, str], tuple[float, float, str]]:
    return {
        (kind, name): (c["estimate"], c["sigma"], c["identifiability"])
        for kind, f in data["filters"].items()
        for name, c in f["estimates"].items()
    }


def test_a_logs_frames_left_out_are_those_its_replay_or_offline_leaves_out(
    tmp_path: Path,
) -> None:
    """A batch's log is cut into the segments its `replay` (a .tlog: the live gate) or
    `offline` (a data file: the plan) would use: here a mission's turns beyond a bank
    limit of 20 degrees, and a take-off roll slower than half the trim airspeed."""
    import numpy as np

    from gcs_estimator.ingest.flightdata import write_csv
    from sim.scenario import mission

    flown = load_config("noc_uav", [*mission("none", 20.0), 'filter.structure_check="off"'])
    fl = simulate(flown, seed=2)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    tlog = tmp_path / "turns.tlog"
    SimulatedVehicle(rec, flown.link, ("127.0.0.1", 9), speed=0.0, tlog=tlog).run()
    slow = fl.measurements.copy()
    slow[:100, 0] = 5.0  # the first 2 s: a take-off roll
    csv = tmp_path / "take_off.csv"
    write_csv(csv, Recording(fl.t_s, fl.inputs, slow, "throttle"))
    sets = ["filter.bank_limit_deg=20", 'filter.structure_check="off"']
    config = load_config("noc_uav", sets)
    for log, command, reason in ((tlog, "replay", "bank"), (csv, "offline", "airspeed")):
        batch = estimate_file(log, config, tmp_path / f"batch_{log.stem}")
        assert batch.error is None, batch.error
        alone = tmp_path / f"alone_{log.stem}"
        argv = [command, str(log), "--config", "noc_uav", "--out", str(alone), "--view", "off"]
        assert cli.main([*argv, *(a for s in sets for a in ("--set", s))]) == 0
        own = json.loads((alone / "results_sys1.json").read_text())
        mine = json.loads((tmp_path / f"batch_{log.stem}" / "results_sys1.json").read_text())
        segments = mine["diagnostics"]["segments"]
        assert segments["left_out_frames"][reason] > 0, segments
        assert segments == own["diagnostics"]["segments"]
        assert _estimates(mine) == _estimates(own)
        assert np.isfinite(mine["diagnostics"]["frames"])
    # A config that cannot read a link's power input is refused for a .tlog, as replay
    # refuses it: a failed row that names the key.
    measured = load_config("noc_uav", ['propulsion.model="measured"'])
    refused = estimate_file(tlog, measured, tmp_path / "refused")
    assert refused.error is not None and "[link] throttle_servo" in refused.error


def test_the_autopilots_uid_is_read_from_the_log(logs: list[Path]) -> None:
    facts = tlog_facts(logs[0])
    assert facts.uids == {1: f"{UID:016x}"}
    assert facts.flight_time is not None
    assert tlog_facts(logs[1]).uids == {}


def test_a_vehicle_map_names_vehicles_by_identity_or_log_path(tmp_path: Path) -> None:
    from gcs_estimator.runtime.fleet import load_vehicle_map, rename_vehicles

    path = tmp_path / "fleet.toml"
    path.write_text('[vehicles]\n"sys3" = "plane B"\n"logs/a/*.tlog" = "plane A"\n')
    rows = [
        {"log": "logs/a/1.tlog", "vehicle": "sys1"},
        {"log": "logs/b/2.tlog", "vehicle": "sys3"},
        {"log": "logs/b/3.tlog", "vehicle": "uid:00ff"},
    ]
    rename_vehicles(rows, load_vehicle_map(str(path)))
    assert [r["vehicle"] for r in rows] == ["plane A", "plane B", "uid:00ff"]
    path.write_text('[vehicles]\n"sys3" = 3\n')
    with pytest.raises(ConfigError, match="needs a \\[vehicles\\] table"):
        load_vehicle_map(str(path))


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--workers", "0"], "--workers 0: at least 1"),
        (["--retries", "-1"], "--retries -1: 0 or more"),
        (["--timeout", "0"], "--timeout 0: seconds, more than 0"),
        (["--scheduler", "tcp://127.0.0.1:1", "--scheduler-file", "s.json"], "give one of them"),
        ([], "batch: no airframe file: give --config"),
    ],
)
def test_options_a_batch_cannot_use_are_refused(
    tmp_path: Path, options: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from gcs_estimator.cli import main

    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "o"), *options]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # refused before anything was written


def test_damaged_logs_are_failed_rows_that_name_them(tmp_path: Path) -> None:
    """Whatever a damaged log's bytes make its reader say (a tlog whose stamps are no time,
    random bytes a CSV or tlog reader takes up), estimate_file gives a failed row naming
    the log, never an exception."""
    config = load_config("noc_uav")
    codec = Codec(1, 1)
    heartbeat = codec.pack(codec.mav.heartbeat_encode(1, 3, 0, 0, 4))
    no_time = tmp_path / "no_time.tlog"  # a stamp some 290,000 years from now
    no_time.write_bytes(tlog_record(2**63 - 1, heartbeat) * 3)
    assert tlog_facts(no_time).flight_time is None
    damaged = [no_time]
    for seed in range(12):
        path = tmp_path / f"junk{seed}.tlog"
        path.write_bytes(random.Random(seed).randbytes(4000))
        damaged.append(path)
    for path in damaged:
        outcome = estimate_file(path, config, tmp_path / path.stem)
        assert outcome.error is not None and str(path) in outcome.error, outcome.error
        assert [r["status"] for r in outcome.coefficients] == ["failed"]
