"""A configuration schema declared on dataclass fields, and the one walker that reads it.

Each TOML key is a field made with `setting()`: its default, unit, bounds and allowed
values sit in the field's metadata, nowhere else. `build(cls, table, where)` walks a parsed
TOML table against those fields, checks every value, and builds the frozen dataclass. An
error names the file, the table, the key, the value and what is allowed::

    plane.toml: [link] elevator_servo: must be a whole number >= 1 and <= 16, got 17

What a field's type means in TOML:

- ``float``, ``int``, ``bool``, ``str``: a value; ``float | None`` may be left out.
- ``tuple[float, ...]``, ``tuple[str, ...]``: a list.
- ``tuple[float, ...]`` with ``keys``: a table of one number per key (per coefficient,
  per channel, ...), stored in key order. ``fill`` gives the keys not set; a "default" key
  may override it; ``degrees`` keys may be given in degrees as KEY_deg; ``inline`` reads
  the keys from the enclosing table itself.
- a dataclass: a sub-table (``X | None``: absent means None).

Rules between keys go in a ``check(self)`` method that raises `Invalid(key, message)`.
"""

from __future__ import annotations

import difflib
import json
import math
import tomllib
import types
from collections.abc import Iterator, Mapping
from dataclasses import MISSING, Field, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, NamedTuple, TypeVar, Union, get_args, get_origin, get_type_hints

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is missing or not allowed; the message says where and why."""


class Invalid(Exception):  # noqa: N818 (raised inside check(), turned into a ConfigError)
    """Raised by a dataclass's check(): which of its keys is wrong, and why."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key
        self.message = message


@dataclass(frozen=True)
class Spec:
    """What the schema knows of one key (see the module docstring)."""

    doc: str = ""
    unit: str = ""
    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    choices: tuple[str, ...] = ()
    unique: bool = False
    keys: tuple[str, ...] | str = ()
    """Keys of a keyed table; a string names a context entry (known only at load time)."""
    fill: float | tuple[float, ...] | None = None
    """Value (or values, in key order) of keys not set; None: every key is required."""
    fallback: str = ""
    """A keyed table left out takes the values of this sibling field."""
    degrees: tuple[str, ...] = ()
    inline: bool = False
    toml: str = ""
    """The TOML key, where it differs from the field name."""
    internal: bool = False
    """Not read from TOML (set by the loader or the command line)."""

    def bounds(self) -> str:
        limits = ((">", self.gt), (">=", self.ge), ("<=", self.le))
        return " and ".join(f"{op} {v:g}" for op, v in limits if v is not None)

    def in_bounds(self, v: float) -> bool:
        return not (
            (self.gt is not None and v <= self.gt)
            or (self.ge is not None and v < self.ge)
            or (self.le is not None and v > self.le)
        )


def setting(default: Any = MISSING, **spec: Any) -> Any:
    """A schema field: its default (none: required) and Spec keywords."""
    meta = {"spec": Spec(**spec)}
    if isinstance(default, list):
        default = tuple(default)
    if default is MISSING:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


def table(cls: type[Any], *, required: bool = False, optional: bool = False, **spec: Any) -> Any:
    """A sub-table field: built from its defaults when left out, unless required/optional."""
    meta = {"spec": Spec(**spec)}
    if required:
        return field(metadata=meta)
    if optional:
        return field(default=None, metadata=meta)
    return field(default_factory=cls, metadata=meta)


def spec_of(f: Field[Any]) -> Spec:
    spec = f.metadata.get("spec", Spec())
    assert isinstance(spec, Spec)
    return spec


@dataclass(frozen=True)
class Where:
    """A table's place: the file (or other source) and the dotted table path."""

    source: str
    path: str = ""

    def sub(self, key: str) -> Where:
        return Where(self.source, f"{self.path}.{key}" if self.path else key)

    def error(self, key: str, message: str) -> ConfigError:
        at = f"[{self.path}] {key}" if self.path else key
        return ConfigError(f"{self.source}: {at}: {message}")


def _describe(tp: Any, spec: Spec) -> str:
    if tp is bool:
        return "true or false"
    if tp is int:
        return f"a whole number {spec.bounds()}".rstrip()
    if tp is str:
        return f"one of {', '.join(map(repr, spec.choices))}" if spec.choices else "a string"
    return f"a number {spec.bounds()}".rstrip()


def _scalar(tp: Any, spec: Spec, value: Any, key: str, where: Where) -> Any:
    wrong_type = (
        not isinstance(value, bool)
        if tp is bool
        else isinstance(value, bool)
        or not isinstance(value, int if tp is int else str if tp is str else int | float)
    )
    if wrong_type:
        raise where.error(key, f"must be {_describe(tp, spec)}, got {value!r}")
    if tp is str:
        if spec.choices and value not in spec.choices:
            raise where.error(key, f"must be {_describe(tp, spec)}, got {value!r}")
        return value
    if tp is float:
        value = float(value)
        if not math.isfinite(value):
            raise where.error(key, f"must be a finite number, got {value!r}")
    if not spec.in_bounds(value):
        raise where.error(key, f"must be {_describe(tp, spec)}, got {value!r}")
    return value


def _listed(item: Any, spec: Spec, value: Any, key: str, where: Where) -> tuple[Any, ...]:
    what = "strings" if item is str else "numbers"
    if not isinstance(value, list):
        raise where.error(key, f"must be a list of {what}, got {value!r}")
    out = []
    for v in value:
        if item is str and spec.choices and isinstance(v, str) and v not in spec.choices:
            raise where.error(key, f"unknown value {v!r}; allowed: {list(spec.choices)}")
        try:
            out.append(_scalar(item, spec, v, key, where))
        except ConfigError:
            allowed = f" {spec.bounds()}" if spec.bounds() else ""
            raise where.error(key, f"must be a list of {what}{allowed}, got {value!r}") from None
    if spec.unique and len(set(out)) != len(out):
        raise where.error(key, f"lists a value twice: {value!r}")
    return tuple(out)


def _keyed(
    spec: Spec, data: Mapping[str, Any], where: Where, context: Mapping[str, tuple[str, ...]]
) -> tuple[tuple[float, ...], set[str]]:
    """One number per key from a table (see Spec.keys); returns (values, keys read)."""
    names = context[spec.keys] if isinstance(spec.keys, str) else spec.keys
    fills: tuple[float | None, ...] = (
        spec.fill if isinstance(spec.fill, tuple) else (spec.fill,) * len(names)
    )
    used: set[str] = set()
    if not spec.inline and spec.fill is not None and not isinstance(spec.fill, tuple):
        used.add("default")
        if "default" in data:
            fills = (_scalar(float, spec, data["default"], "default", where),) * len(names)
    out = []
    for name, fill in zip(names, fills, strict=True):
        deg = name + "_deg"
        if name in data:
            out.append(_scalar(float, spec, data[name], name, where))
        elif name in spec.degrees and deg in data:
            out.append(math.radians(_scalar(float, spec, data[deg], deg, where)))
        elif fill is not None:
            out.append(float(fill))
        else:
            raise where.error(name, "missing; add it (a number)")
        used.update((name, deg) if name in spec.degrees else (name,))
    return tuple(out), used


def _optional(tp: Any) -> Any:
    """X for X | None, else None."""
    if get_origin(tp) in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(get_args(tp)) == 2:
            return args[0]
    return None


def build(
    cls: type[T],
    data: Mapping[str, Any],
    where: Where,
    context: Mapping[str, tuple[str, ...]] | None = None,
    **internal: Any,
) -> T:
    """The dataclass `cls` from a parsed TOML table, every key checked (module docstring)."""
    context = context or {}
    hints = get_type_hints(cls)
    values: dict[str, Any] = dict(internal)
    used: set[str] = set()
    for f in fields(cls):  # type: ignore[arg-type]
        spec = spec_of(f)
        if spec.internal:
            continue
        key = spec.toml or f.name
        values[f.name], keys = _field(f, hints[f.name], spec, key, data, where, context, values)
        used |= keys
    unknown = sorted(set(data) - used)
    if unknown:
        raise where.error(
            unknown[0],
            f"unknown key{_did_you_mean(unknown[0], used)}; known keys here: {sorted(used)}",
        )
    try:
        obj = cls(**values)
        check = getattr(obj, "check", None)
        if check is not None:
            check()
    except Invalid as exc:
        raise where.error(exc.key, exc.message) from None
    return obj


def _field(
    f: Field[Any],
    tp: Any,
    spec: Spec,
    key: str,
    data: Mapping[str, Any],
    where: Where,
    context: Mapping[str, tuple[str, ...]],
    built: Mapping[str, Any],
) -> tuple[Any, set[str]]:
    """The value of one field and the TOML keys it read."""
    if spec.keys and spec.inline:
        return _keyed(spec, data, where, context)
    sub = _optional(tp) or tp
    if spec.keys or is_dataclass(sub):
        return _subtable(f, sub, spec, key, data, where, context, built), {key}
    if key not in data:
        if f.default is MISSING:
            raise where.error(key, f"missing; add it ({_describe(sub, spec)})")
        return f.default, {key}
    if get_origin(tp) is tuple:
        return _listed(get_args(tp)[0], spec, data[key], key, where), {key}
    return _scalar(sub, spec, data[key], key, where), {key}


def _subtable(
    f: Field[Any],
    tp: Any,
    spec: Spec,
    key: str,
    data: Mapping[str, Any],
    where: Where,
    context: Mapping[str, tuple[str, ...]],
    built: Mapping[str, Any],
) -> Any:
    """A sub-table field: a keyed table or a nested dataclass (None if optional and absent)."""
    if key not in data:
        if spec.fallback:
            return built[spec.fallback]
        if f.default is MISSING and f.default_factory is MISSING:
            raise where.error(key, "missing table; add it")
        if f.default is None:
            return None
    inner = data.get(key, {})
    if not isinstance(inner, Mapping):
        raise where.error(key, f"must be a table, got {inner!r}")
    if not spec.keys:
        return build(tp, inner, where.sub(key), context)
    values, used = _keyed(spec, inner, where.sub(key), context)
    unknown = sorted(set(inner) - used)
    if unknown:
        raise where.sub(key).error(
            unknown[0], f"unknown key{_did_you_mean(unknown[0], used)}; allowed: {sorted(used)}"
        )
    return values


def _did_you_mean(key: str, known: set[str]) -> str:
    """' (did you mean 'x'?)' for a known key that a mistyped one stands for: one spelled
    nearly the same, or the key with its unit suffix left off (mass for mass_kg); else
    nothing (a key that is another real name, such as a coefficient the structure lacks,
    gets no guess)."""
    close = difflib.get_close_matches(key, sorted(known), n=1, cutoff=0.85)
    close += [name for name in sorted(known) if name.startswith(key + "_")]
    return f" (did you mean {close[0]!r}?)" if close else ""


class Key(NamedTuple):
    """One key of a schema (see leaves)."""

    table: str
    name: str
    spec: Spec
    type: Any
    default: Any
    """The default value; REQUIRED when the key must be given."""
    owner: type[Any]
    """The dataclass that declares the key's table."""


REQUIRED = "(required)"


def leaves(cls: type[Any], context: Mapping[str, tuple[str, ...]], path: str = "") -> Iterator[Key]:
    """Every key of the schema, depth first, in declaration order."""
    hints = get_type_hints(cls)
    for f in fields(cls):
        spec = spec_of(f)
        if spec.internal:
            continue
        key = spec.toml or f.name
        tp = hints[f.name]
        sub = _optional(tp) or tp
        at = f"{path}.{key}" if path else key
        if spec.keys:
            names = context[spec.keys] if isinstance(spec.keys, str) else spec.keys
            fills = spec.fill if isinstance(spec.fill, tuple) else (spec.fill,) * len(names)
            for name, fill in zip(names, fills, strict=True):
                default = REQUIRED if fill is None else fill
                yield Key(path if spec.inline else at, name, spec, float, default, cls)
        elif is_dataclass(sub):
            yield from leaves(sub, context, at)  # type: ignore[arg-type]
        else:
            yield Key(path, key, spec, tp, REQUIRED if f.default is MISSING else f.default, cls)


def reference(cls: type[Any], context: Mapping[str, tuple[str, ...]], path: str = "") -> str:
    """Every key as Markdown tables, one per TOML table (each once, however the fields of
    its dataclass interleave scalars and sub-tables): default, unit, allowed, meaning.
    path: the table cls is read from (empty: the top level)."""
    tables: dict[str, list[Key]] = {}
    for k in leaves(cls, context, path):
        tables.setdefault(k.table, []).append(k)
    out: list[str] = []
    for name, keys in tables.items():
        out += _table_heading(name, keys[0])
        out += [_key_row(k) for k in keys]
    return "\n".join(out[1:]) + "\n"


def _table_heading(name: str, first: Key) -> list[str]:
    out = ["", f"## [{name}]" if name else "## top level", ""]
    if first.spec.keys and not first.spec.inline:
        out += [f"One number per key ({first.spec.doc or 'see below'}).", ""]
    elif first.owner.__doc__:
        out += [" ".join(first.owner.__doc__.split("\n\n")[0].split()), ""]
    return [*out, "| key | default | unit | allowed | meaning |", "|---|---|---|---|---|"]


def _key_row(k: Key) -> str:
    allowed = ", ".join(k.spec.choices) if k.spec.choices else k.spec.bounds()
    default = "required" if k.default is REQUIRED else _toml(k.default)
    doc = k.spec.doc + (f" (or {k.name}_deg in degrees)" if k.name in k.spec.degrees else "")
    return f"| `{k.name}` | {default} | {k.spec.unit} | {allowed} | {doc} |"


def _toml(value: Any) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.6g}"
    return json.dumps(value) if isinstance(value, str) else str(value)


def read_toml(path: str | Path) -> dict[str, Any]:
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from exc
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(
            f"{path}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); TOML files are "
            "UTF-8: save it as UTF-8"
        ) from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc


def apply_overrides(data: Mapping[str, Any], overrides: list[str], source: str) -> dict[str, Any]:
    """Command-line overrides "table.key=value" (value in TOML syntax) on parsed TOML.

    Example: ``filter.iterations=3``, ``filter.restart_times_s=[4.0]``,
    ``simulation.turbulence.preset=light`` (a bare word is taken as a string).
    """
    out = _deep_copy(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. filter.iterations=3")
        key, text = item.split("=", 1)
        parts = key.strip().split(".")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        node = out
        for part in parts[:-1]:
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                raise ConfigError(f"{source}: --set {key}: {part!r} is not a table")
            node = nxt
        node[parts[-1]] = value
    return out


def merge_tables(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """`over` on top of `base`: tables merge key by key, any other value replaces."""
    out = _deep_copy(base)
    for key, value in over.items():
        below = out.get(key)
        if isinstance(value, Mapping) and isinstance(below, Mapping):
            out[key] = merge_tables(below, value)
        else:
            out[key] = _deep_copy(value) if isinstance(value, Mapping) else value
    return out


def _deep_copy(data: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy(v) if isinstance(v, Mapping) else v for k, v in data.items()}
