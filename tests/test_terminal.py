"""What the terminal shows: a status block redrawn in place (a line per vehicle, each at
most 100 columns, many vehicles summarised), a progress bar with rate and time left, and
at the end the paper's Table I within 100 columns. The escape sequences are played on a
small terminal model and the screen is checked."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.cli import STATUS_VEHICLES, _status_lines, main
from gcs_estimator.config import load_config
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.outputs.sinks import STATUS_WIDTH, ProgressSink, StatusSink
from gcs_estimator.outputs.text import TERMINAL_WIDTH
from gcs_estimator.runtime.session import Session


class Terminal(io.StringIO):
    """A text stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def screen(text: str) -> list[str]:
    """The lines a terminal shows after text: carriage return, newline, erase to the end
    of the line (ESC [K) and cursor up (ESC [nA) are played; any other escape fails."""
    rows: list[str] = [""]
    row = col = 0
    for token in re.findall(r"\x1b\[\d*[A-Za-z]|\r|\n|[^\x1b\r\n]+", text):
        if token == "\r":
            col = 0
        elif token == "\n":
            row, col = row + 1, 0
            if row == len(rows):
                rows.append("")
        elif token.startswith("\x1b["):
            n, op = int(token[2:-1] or 1), token[-1]
            if op == "K":
                rows[row] = rows[row][:col]
            elif op == "A":
                row = max(0, row - n)
            else:
                raise AssertionError(f"unexpected escape {token!r}")
        else:
            line = rows[row].ljust(col)
            rows[row] = line[:col] + token + line[col + len(token) :]
            col += len(token)
    return rows


def test_status_block_is_redrawn_in_place_longer_and_shorter() -> None:
    out = Terminal()
    draws = [["head 1", "a", "b", "c"], ["head 2", "x"], ["head 3", "p", "q"]]
    it = iter(draws)
    sink = StatusSink(lambda _: next(it), out=out, every_s=0.0)
    for _ in draws:
        sink.tick()
    shown = [row for row in screen(out.getvalue()) if row]
    assert shown == draws[-1]


def test_status_lines_fit_and_many_vehicles_are_summarised() -> None:
    config = load_config("noc_uav")
    session = Session(config, keep_history=False)
    link = MavlinkLink(config.link)
    n = STATUS_VEHICLES + 8
    for sid in range(1, n + 1):
        session.estimator(sid)
    lines = _status_lines(link, session, 12345.6)
    assert len(lines) == 1 + STATUS_VEHICLES + 1
    assert lines[-1].strip() == "... and 8 more vehicles"
    assert f"vehicles {n}" in lines[0]
    assert all(len(line) <= STATUS_WIDTH for line in lines)
    out = Terminal()
    sink = StatusSink(lambda _: [*lines, "z" * 300], out=out, every_s=0.0)
    sink.tick()
    assert all(len(row) <= STATUS_WIDTH for row in screen(out.getvalue()))


def test_progress_shows_rate_and_time_left() -> None:
    now = [100.0]
    done = [0]
    total = 200_000_000
    out = Terminal()
    bar = ProgressSink(lambda: (done[0], total), "replay", out=out, clock=lambda: now[0])
    now[0], done[0] = 104.0, 50_000_000  # 12.5 MB/s, 150 MB to go: 12 s
    bar.tick()
    (row,) = [r for r in screen(out.getvalue()) if r]
    assert " 25 % 50.0/200.0 MB" in row
    rate = float(re.search(r"([\d.]+) MB/s", row).group(1))  # type: ignore[union-attr]
    left = float(re.search(r"(\d+) s left", row).group(1))  # type: ignore[union-attr]
    assert np.isclose(rate, 12.5) and np.isclose(left, 12)
    now[0], done[0] = 104.0 + 40 * 60, 100_000_000  # minutes now
    bar.tick()
    assert "min" in screen(out.getvalue())[0] and len(screen(out.getvalue())[0]) <= STATUS_WIDTH


def test_progress_in_frames() -> None:
    now = [0.0]
    bar = ProgressSink(lambda: (1500, 3000), "offline", unit="frames", clock=lambda: now[0])
    now[0] = 2.0
    line = bar.line()
    assert "1,500/3,000 frames" in line and "750 frames/s" in line and "2 s left" in line


def test_a_runs_table_fits_the_terminal_in_the_papers_layout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The end of a real run (a short simulated flight) as the terminal shows it: per
    coefficient the IEKF's and the EKF's estimate and sigma, the truth and the mark, each
    line of the table and of the notes and warnings under it within TERMINAL_WIDTH
    columns; the sigma shown is the JSON's one sigma, and the full table (errors,
    convergence times) is in the results' .md file."""
    argv = ["simulate", "--config", "noc_uav", "--out", str(tmp_path), "--seed", "3"]
    assert main([*argv, "--set", "simulation.manoeuvre.duration_s=12"]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if line.startswith("|")]
    cells = [[c.strip() for c in line.strip(" |").split("|")] for line in lines]
    assert cells[0] == [
        "coefficient",
        "IEKF estimate",
        "IEKF σ",
        "EKF estimate",
        "EKF σ",
        "truth",
        "identified?",
    ]
    names = load_config("noc_uav").coefficient_names
    rows = cells[2:]
    assert [r[0] for r in rows] == list(names)
    shown = out[out.index(lines[0]) : out.index("\nresults: ")]
    assert all(len(line) <= TERMINAL_WIDTH for line in shown.splitlines())
    data = json.loads((tmp_path / "results_sys1.json").read_text())
    for row in rows:
        for kind, column in (("IEKF", 2), ("EKF", 4)):
            estimate = data["filters"][kind]["estimates"][row[0]]
            assert row[column] == f"{estimate['sigma']:.2g}", (kind, row)
        assert row[-1] == data["filters"]["IEKF"]["estimates"][row[0]]["identifiability"]
    full = (tmp_path / "results_sys1.md").read_text()
    assert "| IEKF error/σ |" in full and "IEKF within 5 % of truth from s" in full
