"""`./run bench all` (benchmarks/all.py): its plan covers every benchmark, its index says
where each record came from, and a record holds nothing of the machine it ran on."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))  # the benchmarks import each other as top-level modules

import all as bench_all  # noqa: E402  (benchmarks/all.py)
import record  # noqa: E402  (benchmarks/record.py)

MAIN = 'if __name__ == "__main__":'


def _helpers() -> set[str]:
    """The modules `./run bench` does not offer (its BENCH_HELPERS)."""
    found = re.search(r'^BENCH_HELPERS="([^"]*)"', (ROOT / "run").read_text(), re.MULTILINE)
    assert found is not None, "the run script lists its helpers in BENCH_HELPERS"
    return set(found[1].split())


def test_every_benchmark_is_planned_or_says_why_not() -> None:
    scripts = {p.stem for p in BENCHMARKS.glob("*.py")} - _helpers() - {"all"}
    planned = {run.script for run in bench_all.PLAN}
    assert planned | set(bench_all.NOT_IN_PLAN) == scripts
    assert not planned & set(bench_all.NOT_IN_PLAN)


def test_helpers_have_no_command_line_and_benchmarks_do() -> None:
    for path in BENCHMARKS.glob("*.py"):
        assert (MAIN in path.read_text()) == (path.stem not in _helpers()), path.name


def test_records_have_one_name_each_and_their_command() -> None:
    names = [run.name for run in bench_all.PLAN]
    assert len(names) == len(set(names))
    for run in bench_all.PLAN:
        named = run.name == run.script or run.command().endswith(f"--record {run.name}")
        assert named, run.command()
        assert run.command().startswith(f"./run bench {run.script}")


def test_only_picks_records_by_name_or_benchmark() -> None:
    assert [run.name for run in bench_all.chosen(["speed"])] == ["speed"]
    accuracy = [run.name for run in bench_all.chosen(["accuracy"])]
    assert accuracy == ["accuracy_none", "accuracy_light", "accuracy_moderate"]
    with pytest.raises(SystemExit):
        bench_all.chosen(["no_such_record"])


def _entry(name: str, revision: str, status: str = "ok") -> bench_all.Entry:
    return bench_all.Entry(
        name, f"./run bench {name}", 90.0, revision, "2026-01-01 00:00 UTC", status
    )


def test_index_of_one_revision_links_each_record() -> None:
    text = bench_all.render([_entry("speed", "abc1234"), _entry("fleet", "abc1234")], "a CPU")
    assert "- revision: abc1234 (no uncommitted changes)\n" in text
    assert "| [speed.md](speed.md) | `./run bench speed` | 1.5 min | abc1234 | ok |" in text
    assert "more than one revision" not in text


def test_index_says_loudly_when_records_mix_revisions_or_failed() -> None:
    entries = [_entry("speed", "abc1234"), _entry("fleet", "def5678", "failed (exit 1)")]
    text = bench_all.render(entries, "a CPU")
    assert "**these records are of more than one revision**" in text
    assert "| fleet | `./run bench fleet` |" in text  # no link to a failed record
    dirty = bench_all.render([_entry("speed", "abc1234 with local changes")], "a CPU")
    assert "**the tree had uncommitted changes**" in dirty


def test_problems_finds_paths_and_simulator_chatter() -> None:
    assert bench_all.problems("| CLa | 5.28 |\n") == []
    assert bench_all.problems(f"screenshot: {ROOT}/docs/view.png") == ["an absolute path"]
    assert bench_all.problems("JSBSim startup beginning ...") == ["a simulator's start-up output"]


def test_record_writes_paths_under_the_project_relative(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(record, "RESULTS", tmp_path)
    monkeypatch.setattr(sys, "argv", ["bench.py", "--seeds", "2"])
    with record.recorded("demo", "demo_record", "A title"):
        print(f"picture: {ROOT / 'docs' / 'view.png'}")
    text = (tmp_path / "demo_record.md").read_text(encoding="utf-8")
    assert "- command: `./run bench demo --seeds 2`" in text
    assert text.endswith("picture: docs/view.png\n")
    assert bench_all.problems(text) == []
    assert "picture:" in capsys.readouterr().out  # the console still gets the output
