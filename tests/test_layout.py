"""The package's layout follows the data flow (gcs_estimator/__init__.py lists it): no
import cycle between modules, and each folder imports only from the folders before it in
the flow. Every import counts, at module level, inside functions and under TYPE_CHECKING
alike: a cycle hidden in a function is still a cycle a reader has to untangle."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "gcs_estimator"

FLOW = (
    ("arrays", "units", "stop", "schema", "blas", "frames", "differences"),
    ("model", "config"),  # the model and the airframe file that parameterises it
    ("ingest",),  # every source; ingest/logs (the autopilots' logs) imports flightdata
    ("estimation",),
    ("uncertainty",),
    ("refine",),
    ("outputs",),
    ("runtime",),
    ("cli", "__main__", "__init__"),
)
"""Each module's place in the flow, by its first name below gcs_estimator: a module may
import from its own rank and the ranks before it, never from a later one."""

RANK = {name: rank for rank, names in enumerate(FLOW) for name in names}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _imported(name: str, path: Path, known: set[str]) -> Iterator[str]:
    """The package's modules this module imports anywhere in its text."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*up, base] if base else up)
            # `from package import module` imports the module; otherwise the name's module
            targets = [
                f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names
            ]
        else:
            continue
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name and target != "gcs_estimator":
                yield target


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: set(_imported(name, path, known)) for name, path in modules.items()}


def _rank(module: str) -> int:
    first = module.split(".")[1] if "." in module else "__init__"
    return RANK[first]


def test_every_module_has_a_place_in_the_flow() -> None:
    missing = sorted(m for m in _modules() if m != "gcs_estimator" and _first(m) not in RANK)
    assert not missing, f"modules with no place in tests/test_layout.py's FLOW: {missing}"


def _first(module: str) -> str:
    return module.split(".")[1]


def test_folders_import_only_what_comes_before_them_in_the_flow() -> None:
    upward = sorted(
        f"{a} -> {b}"
        for a, deps in _graph().items()
        for b in deps
        if a != "gcs_estimator" and _rank(b) > _rank(a)
    )
    assert not upward, "imports against the flow:\n" + "\n".join(upward)


def _reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen: set[str] = set()
    todo = list(graph.get(start, ()))
    while todo:
        v = todo.pop()
        if v not in seen:
            seen.add(v)
            todo.extend(graph.get(v, ()))
    return seen


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import each other, directly or through others."""
    reach = {v: _reachable(graph, v) for v in graph}
    groups = {
        tuple(sorted({v} | {w for w in reach[v] if v in reach.get(w, set())}))
        for v in graph
        if v in reach[v]
    }
    return [list(g) for g in sorted(groups)]


def test_no_import_cycle() -> None:
    assert _cycles(_graph()) == []


@pytest.mark.parametrize(
    ("graph", "expected"),
    [
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, [["a", "b", "c"]]),
        ({"a": {"b"}, "b": set(), "c": {"a"}}, []),
    ],
)
def test_the_cycle_finder_finds_cycles(
    graph: dict[str, set[str]], expected: list[list[str]]
) -> None:
    assert _cycles(graph) == expected


def test_the_import_reader_sees_imports_inside_functions(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from gcs_estimator.runtime import session\n")
    known = {"gcs_estimator.runtime", "gcs_estimator.runtime.session", "gcs_estimator.m"}
    assert list(_imported("gcs_estimator.m", source, known)) == ["gcs_estimator.runtime.session"]


LONG_CLASS_LINES = 200
"""A class longer than this holds more than one job, unless a comment right above it
(starting "# Over 200 lines:") says why it should stay whole."""


def test_no_class_over_200_lines_without_a_reason() -> None:
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        lines = path.read_text().splitlines()
        for node in ast.walk(ast.parse("\n".join(lines))):
            if not isinstance(node, ast.ClassDef):
                continue
            size = (node.end_lineno or node.lineno) - node.lineno + 1
            first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            above = "\n".join(lines[max(0, first - 6) : first - 1])
            if size > LONG_CLASS_LINES and "# Over 200 lines:" not in above:
                long.append(f"{path.relative_to(PACKAGE.parent)}: {node.name} ({size} lines)")
    assert not long, "classes over 200 lines with no reason given:\n" + "\n".join(long)
