"""Installed from a wheel, the commands work from an empty directory: nothing of the
repository beside them (configs and the HFB-320 record are package data)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


class Installed:
    """A virtual environment with the project installed from its wheel, and an empty
    working directory to run its commands in."""

    def __init__(self, root: Path) -> None:
        wheels = root / "wheels"
        _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
              "-w", str(wheels), str(ROOT)], cwd=root)  # fmt: skip
        self.venv = root / "venv"
        _run([sys.executable, "-m", "venv", str(self.venv)], cwd=root)
        # The dependencies come from this environment: its site-packages as a plain path
        # (a .pth line runs no .pth inside it, so this checkout's editable finder stays out).
        purelib = Path(sysconfig.get_paths()["purelib"])
        (self._site() / "dependencies.pth").write_text(f"{purelib}\n")
        wheel = next(wheels.glob("gcs_estimator-*.whl"))
        _run([str(self.bin("python")), "-m", "pip", "install", "--no-deps", "--no-index",
              "--quiet", str(wheel)], cwd=root)  # fmt: skip
        self.cwd = root / "empty"
        self.cwd.mkdir()

    def _site(self) -> Path:
        found = list((self.venv / "lib").glob("python3*/site-packages"))
        assert len(found) == 1, found
        return found[0]

    def bin(self, name: str) -> Path:
        return self.venv / "bin" / name

    def run(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        return _run([str(self.bin(args[0])), *args[1:]], cwd=self.cwd, check=check)

    def popen(self, *args: str) -> subprocess.Popen[str]:
        return subprocess.Popen(
            [str(self.bin(args[0])), *args[1:]],
            cwd=self.cwd,
            env=_clean_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )


def _clean_env() -> dict[str, str]:
    # NUMBA_CACHE_DIR: this checkout's kernel cache (set on importing it), not the install's.
    drop = ("PYTHONPATH", "VIRTUAL_ENV", "NUMBA_CACHE_DIR")
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def _run(cmd: list[str], cwd: Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(cmd, cwd=cwd, env=_clean_env(), capture_output=True, text=True)
    assert not check or proc.returncode == 0, f"{cmd}\n{proc.stdout}\n{proc.stderr}"
    return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Installed]:
    yield Installed(tmp_path_factory.mktemp("install"))


def test_the_installed_package_is_the_wheel_not_this_checkout(installed: Installed) -> None:
    where = installed.run(
        "python", "-c", "import gcs_estimator, sim; print(gcs_estimator.__file__, sim.__file__)"
    )
    assert str(installed.venv) in where.stdout and str(ROOT) not in where.stdout
    assert installed.run("gcs-estimator", "--version").stdout.startswith("gcs-estimator ")
    mod = installed.run("python", "-m", "gcs_estimator", "keys", "--config", "hfb320")
    assert "| `CmV` |" in mod.stdout
    # What ./run does after installing: the kernels compiled into the install's own cache,
    # so that the tests below (and a user's first listen) start warm.
    pre = installed.run("python", "-m", "gcs_estimator.runtime.precompile")
    assert pre.stdout.startswith("compiled the kernels in ")
    cached = list((installed.venv / "lib").glob("python3*/site-packages/gcs_estimator/**/*.nbi"))
    assert cached, "no numba cache written next to the installed package"


def test_simulate_and_offline_from_an_empty_directory(installed: Installed) -> None:
    installed.run(
        "gcs-estimator", "simulate", "--view", "off", "--set", "simulation.manoeuvre.duration_s=20"
    )
    # Each run in a folder of its own under out/, the same file names from every command.
    (folder,) = (installed.cwd / "out").glob("simulate_*")
    sim = json.loads((folder / "results_sys1.json").read_text())
    assert sim["run"]["command"] == "simulate" and sim["run"]["version"] != "unknown"
    installed.run("gcs-estimator", "offline", "hfb320", "--view", "off", "--out", "hfb")
    hfb = json.loads((installed.cwd / "hfb" / "results_sys1.json").read_text())
    assert len(hfb["run"]["source_sha256"]) == 64
    again = installed.run(
        "gcs-estimator", "offline", "hfb320", "--view", "off", "--out", "hfb", check=False
    )
    assert again.returncode == 2 and "--force" in again.stderr
    assert sim["aircraft"] == "NOC UAV" and hfb["aircraft"] == "HFB-320"
    for res in (sim, hfb):
        assert len(res["filters"]["IEKF"]["estimates"]) == 11


def test_simulated_vehicle_to_listening_station_on_loopback(installed: Installed) -> None:
    station = installed.popen(
        "gcs-estimator", "listen", "udpin:127.0.0.1:0", "--view", "off", "--idle-exit", "2",
        "--set", "simulation.manoeuvre.duration_s=15",
    )  # fmt: skip
    assert station.stderr is not None
    port = ""
    for line in station.stderr:
        if line.startswith("listening on"):
            port = line.split()[3].rstrip(",").rsplit(":", 1)[1]
            break
    assert port, station.stderr.read()
    installed.run(
        "gcs-sim", "--target", f"127.0.0.1:{port}", "--speed", "4",
        "--set", "simulation.manoeuvre.duration_s=15",
    )  # fmt: skip
    _out, err = station.communicate(timeout=120)
    assert station.returncode == 0, err
    (folder,) = (installed.cwd / "out").glob("listen_*")
    res = json.loads((folder / "results_sys1.json").read_text())
    assert (folder / "telemetry.tlog").stat().st_size > 0
    assert res["link"]["received"] > 0
    assert len(res["filters"]["IEKF"]["estimates"]) == 11


def test_a_change_to_any_source_gives_the_compiled_kernels_a_fresh_cache(tmp_path: Path) -> None:
    """numba sees a change to the file holding a compiled function but not to the
    functions it calls from other files; the cache folder follows the sources instead."""
    for package in ("gcs_estimator", "sim"):
        shutil.copytree(
            ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__")
        )
    env = _clean_env()
    env["PYTHONPATH"] = str(tmp_path)
    probe = [sys.executable, "-c", "import gcs_estimator, os; print(os.environ['NUMBA_CACHE_DIR'])"]

    def cache_dir() -> Path:
        out = subprocess.run(probe, cwd=tmp_path, env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        return Path(out.stdout.strip())

    first = cache_dir()
    assert first.parent == tmp_path / "gcs_estimator" / "__pycache__"
    assert cache_dir() == first  # the same sources, the same cache
    first.mkdir()
    equations = tmp_path / "gcs_estimator" / "model" / "equations.py"
    equations.write_text(equations.read_text() + "\n# changed\n")
    second = cache_dir()
    assert second != first and not first.exists()  # the stale cache is gone too
