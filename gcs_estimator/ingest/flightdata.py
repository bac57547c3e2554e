"""Recorded flight data files: the HFB-320 ASCII record and CSV.

The project's own CSV layout (header row, SI units, one row per sample, empty cell =
missing):

    time_s, airspeed_mps, alpha_rad, theta_rad, q_radps, qdot_radps2, ax_mps2, az_mps2,
    elevator_rad, and one of throttle (0..1) or thrust_n;
    optionally the air density per sample: air_density_kgpm3, or static_pressure_pa or
    pressure_altitude_m with air_temperature_k (standard temperature without it); the
    climb rate climb_rate_mps; the turns' bank angle, roll and yaw rates phi_rad, p_radps,
    r_radps; the attitude quaternion quat_w, quat_x, quat_y, quat_z (body to NED, scalar
    first), which gives theta and phi where their own columns are absent

Column order is free; extra columns are ignored. Any other CSV is read through the
config's [data.columns] (which column holds which quantity) and [data.units].
"""

from __future__ import annotations

import csv
import difflib
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcs_estimator import units
from gcs_estimator.arrays import BoolArray, FloatArray, IntArray
from gcs_estimator.config import (
    ATMOSPHERE_QUANTITIES,
    LATERAL_QUANTITIES,
    NORMALISED,
    PLAUSIBLE_MAX,
    PLAUSIBLE_QUANTITIES,
    POWER_COLUMNS,
    QUANTITY_KINDS,
    QUATERNION_QUANTITIES,
    Columns,
    DataConfig,
    PowerInput,
)
from gcs_estimator.model import atmosphere
from gcs_estimator.model.channels import N_OBS, pad_observations


class FlightDataError(ValueError):
    """A data file cannot be read as flight data; the message names the file and line."""


@dataclass(frozen=True)
class Recording:
    """Samples of one flight: t_s [N], inputs [N x 2] (elevator rad, throttle or thrust N)
    or [N x 3] with the air density [kg/m^3] (NaN where unknown: the airframe's),
    measurements [N x 7] (V, alpha, theta, q, qdot, a_x, a_z; NaN = missing)."""

    t_s: FloatArray
    inputs: FloatArray
    measurements: FloatArray
    power: PowerInput
    """What the second input column holds."""
    notes: tuple[str, ...] = ()
    """What reading the file mended or skipped, one sentence each (for the run's output)."""
    inputs_known: BoolArray | None = None
    """[N] False where a frame's input is a guess (a lost sample while the input changed,
    Frame.inputs_known); None: every input known."""
    aux: dict[str, FloatArray] = field(default_factory=dict)
    """Further signals at the sample times, by name (an autopilot's log: roll, roll and
    yaw rates, vertical speed, wind; ingest/logs/content.py AUX), unused by the filters."""
    compatibility: dict[str, Any] | None = None
    """What the data compatibility check found (ingest/compat.py), for the results JSON;
    None: not checked."""

    def __post_init__(self) -> None:
        """Measurements of the seven channels before the climb rate get a missing h_dot."""
        if np.ndim(self.measurements) == 2 and np.shape(self.measurements)[1] < N_OBS:
            object.__setattr__(self, "measurements", pad_observations(self.measurements))

    def __len__(self) -> int:
        return len(self.t_s)


# HFB-320 columns (1-based in the README): T, DELV, PDYN, THRUST, TASCG, ALFCG, THE, Q,
# QDOT, AXCG, AZCG, ...
_HFB_TIME, _HFB_ELEVATOR, _HFB_THRUST = 0, 1, 3
_HFB_OBSERVATIONS = [4, 5, 6, 7, 8, 9, 10]


DATA_SUFFIXES = (".asc", ".csv", ".bin", ".ulg")
"""Flight-data files a folder may stand for: the HFB-320 ASCII record, CSV, and the
autopilots' binary logs (ingest/logs: which of these a file is, its content says). A
text .log is given by itself: a folder's .log may be any program's output."""


BUNDLED = Path(__file__).resolve().parent.parent / "data"
"""Flight data shipped with the package, one folder per record (hfb320: the HFB-320
flight test, with its provenance and the textbook's reference values)."""


def bundled(name: str) -> Path:
    """The folder of a bundled flight-data record, e.g. bundled("hfb320")."""
    return BUNDLED / name


def data_file(path: str | Path) -> Path:
    """The flight-data file at path; a folder holding exactly one .asc or .csv file stands
    for that file (the HFB-320 folder, say), and the name of a bundled record for its
    folder (`hfb320`). Anything else is a FlightDataError that says what to give instead."""
    p = Path(path)
    if not p.exists() and (BUNDLED / str(path)).is_dir():
        p = BUNDLED / str(path)
    if not p.exists():
        known = ", ".join(sorted(d.name for d in BUNDLED.iterdir() if d.is_dir()))
        raise FlightDataError(f"{p}: no such file or folder (bundled records: {known})")
    if not p.is_dir():
        return p
    found = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in DATA_SUFFIXES)
    if len(found) == 1:
        return found[0]
    if not found:
        raise FlightDataError(
            f"{p}: a folder with no flight data in it ({' or '.join(DATA_SUFFIXES)}); "
            "give the data file itself"
        )
    names = ", ".join(f.name for f in found)
    raise FlightDataError(f"{p}: a folder with several flight-data files ({names}); give one")


def load_recording(
    path: str | Path, data: DataConfig | None = None, elevator_travel_deg: float = 0.0
) -> tuple[Path, Recording]:
    """The flight data at path (see data_file): a CSV (read as `data` says; a normalised
    elevator times elevator_travel_deg), else the HFB-320 ASCII format."""
    file = data_file(path)
    if file.suffix.lower() == ".csv":
        return file, load_csv(file, data, elevator_travel_deg)
    return file, load_hfb320(file)


def load_hfb320(path: str | Path) -> Recording:
    """Read the HFB-320 flight-test record (Jategaonkar test case 4, hfb320_1_10.asc):
    whitespace-separated columns, as many on every line as on the first. A line with
    fewer (a file cut while written, or two joined there) is skipped, as is a last line
    without a line end; a value that is not a number reads as missing; the time is
    mended as in a CSV (_in_time_order). Each is said in the recording's notes."""
    try:
        text = Path(path).read_text(encoding="latin-1")
    except OSError as exc:
        raise FlightDataError(f"{path}: cannot read: {exc.strerror}") from exc
    rows, lines, width, short, unread = _asc_rows(text)
    if not rows:
        raise FlightDataError(f"{path}: not an HFB-320 ASCII record: no data lines")
    if width < 11:
        raise FlightDataError(f"{path}: expected at least 11 columns, found {width}")
    notes: list[str] = []
    if short:
        notes.append(
            f"{path}: {len(short)} line(s) with fewer than {width} columns skipped (the first "
            f"at line {short[0]}: a file cut while it was written?)"
        )
    _drop_cut_line(path, text, rows, lines, lines[-1] == len(text.splitlines()), notes)
    if unread:
        notes.append(
            f"{path}: {len(unread)} value(s) not a number read as missing (the first at line "
            f"{unread[0]})"
        )
    if not rows:
        raise FlightDataError(f"{path}: not an HFB-320 ASCII record: no data lines")
    data = _in_time_order(path, "column 1", np.array(rows), np.array(lines), notes)
    return Recording(
        t_s=data[:, _HFB_TIME].copy(),
        inputs=np.column_stack([data[:, _HFB_ELEVATOR], data[:, _HFB_THRUST]]),
        measurements=data[:, _HFB_OBSERVATIONS].copy(),
        power="thrust",
        notes=tuple(notes),
    )


def _drop_cut_line(
    path: str | Path,
    text: str,
    rows: list[list[float]],
    lines: list[int],
    last_is_final: bool,
    notes: list[str],
) -> None:
    """Drop the last row (in place, with a note) where the file does not end with a line
    end and that row is its last line (last_is_final): a file cut while it was written,
    whose last number may be cut short (11603.15 read as 1)."""
    if last_is_final and not text.endswith(("\n", "\r")):
        rows.pop()
        notes.append(
            f"{path}: the last line (line {lines.pop()}) has no line end, as in a file cut "
            "while it was written: ignored"
        )


def _asc_rows(
    text: str,
) -> tuple[list[list[float]], list[int], int, list[int], list[int]]:
    """A whitespace-separated table's rows of the first line's width: (rows, their line
    numbers, the width, lines with fewer columns, lines holding a value that is not a
    number (read as NaN))."""
    rows: list[list[float]] = []
    lines: list[int] = []
    short: list[int] = []
    unread: list[int] = []
    width = 0
    for number, line in enumerate(text.splitlines(), start=1):
        cells = line.split()
        if not cells:
            continue
        width = width or len(cells)
        if len(cells) < width:
            short.append(number)
            continue
        values = []
        for cell in cells[:width]:
            try:
                values.append(float(cell))
            except ValueError:
                values.append(math.nan)
                if not unread or unread[-1] != number:
                    unread.append(number)
        rows.append(values)
        lines.append(number)
    return rows, lines, width, short, unread


OBSERVED: tuple[str, ...] = ("airspeed", "alpha", "theta", "q", "qdot", "a_x", "a_z")
"""The quantities of a CSV that are observations, in channel order."""


def load_csv(
    path: str | Path, data: DataConfig | None = None, elevator_travel_deg: float = 0.0
) -> Recording:
    """Read flight data from a CSV: a header row, one row per sample, an empty cell for a
    missing value. Which column holds which quantity, and in which unit, come from the
    config's [data.columns] and [data.units] (default: the project's own SI layout, see
    the module docstring). One of the throttle and thrust columns must be present; air
    density comes from the atmosphere columns the file has (config.ATMOSPHERE_QUANTITIES).
    Each column is multiplied by [data.scale] after its unit (-1 flips an axis); a
    normalised elevator (-1..1) by elevator_travel_deg. Empty input cells are filled as
    [data] input_hold says (hold_inputs): an input is never missing."""
    data = data or DataConfig()
    try:
        return _load_csv(path, data, elevator_travel_deg, "utf-8-sig")
    except UnicodeDecodeError:
        # Not UTF-8: a byte such as a degree sign from a Windows program. Latin-1 reads
        # every byte; the numbers are ASCII either way.
        return _load_csv(path, data, elevator_travel_deg, "latin-1")


DELIMITER_NAMES = {",": "commas", ";": "semicolons", "\t": "tabs"}
"""Column separators a CSV may use (spreadsheets in locales whose decimal mark is a comma
write semicolons; some loggers write tabs)."""


def _delimiter(text: str) -> str:
    """The header line's column separator: a comma where it has one, else the first of
    a semicolon or a tab it has."""
    header = text.split("\n", 1)[0]
    if "," in header:
        return ","
    return next((d for d in (";", "\t") if d in header), ",")


def _read_rows(
    path: str | Path, reader: csv.DictReader[str], names: list[str], decimal_comma: bool
) -> tuple[list[list[float]], list[int], dict[str, tuple[int, int, str]]]:
    """The named columns' values of every row (NaN where empty or not a number; with
    decimal_comma, "0,5" is 0.5), each row's line, and per column the cells that were not
    numbers: (how many, the first one's line, its text)."""
    rows: list[list[float]] = []
    lines: list[int] = []
    unread: dict[str, tuple[int, int, str]] = {}
    line = 1
    try:
        for line, row in enumerate(reader, start=2):
            values = []
            for c in names:
                try:
                    cell = row[c]
                    if decimal_comma and cell is not None:
                        cell = cell.replace(",", ".")
                    values.append(_cell(cell))
                except ValueError:
                    n, first, shown = unread.get(c, (0, line, str(row[c])))
                    unread[c] = (n + 1, first, shown)
                    values.append(math.nan)
            rows.append(values)
            lines.append(line)
    except csv.Error as exc:
        raise FlightDataError(f"{path}:{line + 1}: not a CSV row: {exc}") from exc
    return rows, lines, unread


TIME_BACK_S = 1.0
"""A CSV's time may step back by at most this much [s] (rows out of order, put back in
order); further back, the file holds two recordings and is refused."""


def _load_csv(path: str | Path, data: DataConfig, travel_deg: float, encoding: str) -> Recording:
    cols = data.columns
    notes: list[str] = []
    text, delimiter, reader, header = _open_csv(path, encoding, notes)
    absent = [q for q in OBSERVED if getattr(cols, q) == ""]
    quaternion = all(getattr(cols, q) in header for q in QUATERNION_QUANTITIES)
    if quaternion and cols.theta not in header and "theta" not in absent:
        absent.append("theta")  # from the quaternion (_attitude)
    _require(path, header, [q for q in ("time", *OBSERVED, "elevator") if q not in absent], cols)
    for quantity in absent:
        if quantity == "theta" and quaternion:
            continue  # from the quaternion, noted there
        notes.append(
            f'{path}: no {quantity} column ([data.columns] {quantity} = ""): the filters go '
            "without that channel"
        )
    power, glide = _power_column(path, header, cols)
    if glide:
        absent.append("thrust")
        notes.append(f'{path}: no thrust column ([data.columns] thrust = ""): a glide, thrust 0')
    air = tuple(q for q in ATMOSPHERE_QUANTITIES if getattr(cols, q) in header)
    climb = ("climb_rate",) if cols.climb_rate in header else ()
    lateral = tuple(q for q in LATERAL_QUANTITIES if getattr(cols, q) in header)
    quat = QUATERNION_QUANTITIES if quaternion else ()
    wanted = ("time", *OBSERVED, "elevator", power, *air, *climb, *lateral, *quat)
    read = [i for i, q in enumerate(wanted) if q not in absent]
    scale = np.array([1.0 if q in quat else _factor(path, data, q, travel_deg) for q in wanted])
    shift = np.array([0.0 if q in quat else units.offset(getattr(data.units, q)) for q in wanted])
    names = [getattr(cols, wanted[i]) for i in read]
    rows, lines, unread = _read_rows(path, reader, names, decimal_comma=delimiter != ",")
    _drop_cut_line(path, text, rows, lines, bool(rows), notes)
    for c, (n, first, cell) in unread.items():
        notes.append(
            f"{path}: {n} cell(s) of {c!r} not a number (the first at line {first}: "
            f"{cell!r}): read as missing"
        )
    if not rows:
        raise FlightDataError(f"{path}: no data rows")
    arr = np.full((len(rows), len(wanted)), np.nan)
    arr[:, read] = np.array(rows, float).reshape(len(rows), len(read))
    if glide:
        arr[:, 9] = 0.0
    arr = arr * scale + shift
    arr = _in_time_order(path, cols.time, arr, np.array(lines), notes)
    by = dict(zip(wanted, arr.T, strict=True))
    turns = _attitude(path, cols, by, quaternion, notes)
    arr[:, OBSERVED.index("theta") + 1] = by["theta"]
    check_units(path, by, data)
    width = arr.shape[1]  # the turns ride along, so that the rows the hold drops go too
    arr = arr if turns is None else np.column_stack([arr, *turns])
    arr, known = hold_inputs(path, arr, (8, 9), (cols.elevator, getattr(cols, power)), data, notes)
    turns = None if turns is None else list(arr[:, width:].T)
    if power == "thrust" and not glide and not np.any(arr[:, 9]):
        notes.append(f"{path}: thrust 0 throughout ({cols.thrust!r}): a glide")
    inputs = arr[:, [8, 9]]
    rho = _density(dict(zip(air, arr[:, 10 : 10 + len(air)].T, strict=True)))
    if rho is not None:
        inputs = np.column_stack([inputs, rho])
    # The climb rate (h_dot) where the file has its column; missing otherwise.
    h_dot = arr[:, wanted.index("climb_rate")] if climb else np.full(len(arr), np.nan)
    return Recording(
        t_s=arr[:, 0],
        inputs=inputs if turns is None else _with_turns(inputs, turns),
        measurements=np.column_stack([arr[:, 1:8], h_dot]),
        power="thrust" if power == "thrust" else "throttle",
        notes=tuple(notes),
        inputs_known=None if known.all() else known,
        aux={} if turns is None else {"phi": turns[0]},  # the segments' bank limit
    )


def _with_turns(inputs: FloatArray, turns: list[FloatArray]) -> FloatArray:
    """The inputs with the turns' after the air density (NaN: the airframe's)."""
    if inputs.shape[1] < 3:
        inputs = np.column_stack([inputs, np.full(len(inputs), np.nan)])
    return np.column_stack([inputs, *turns])


def attitude_of_quaternion(
    w: FloatArray, x: FloatArray, y: FloatArray, z: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Bank, pitch and heading [rad] of a quaternion body to north-east-down, scalar first
    (PX4's vehicle_attitude.q), normalised first (a logger's rounding leaves its norm off
    1): the 3-2-1 Euler angles; NaN where it is zero or missing."""
    with np.errstate(invalid="ignore", divide="ignore"):
        norm = np.sqrt(w * w + x * x + y * y + z * z)
        norm = np.where(norm > 0.0, norm, np.nan)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    phi = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    theta = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    psi = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return phi, theta, psi


def _attitude(
    path: str | Path,
    cols: Columns,
    by: dict[str, FloatArray],
    quaternion: bool,
    notes: list[str],
) -> list[FloatArray] | None:
    """The pitch angle from the quaternion where the file has no theta column (set into
    `by`), and the turns' inputs [bank, roll rate, yaw rate] from their columns or the
    quaternion (each NaN where the file has none, the bank then wings level; a missing
    cell interpolated between its neighbours, as a link's bank is); None where the file
    has none of them."""
    phi = by.get("phi")
    if quaternion:
        from_q_phi, from_q_theta, _ = attitude_of_quaternion(
            *(by[q] for q in QUATERNION_QUANTITIES)
        )
        if not np.any(np.isfinite(by["theta"])):  # no theta column, or an empty one
            by["theta"] = from_q_theta
            notes.append(f"{path}: the pitch angle from the attitude quaternion")
        if phi is None:
            phi = from_q_phi
            notes.append(f"{path}: the bank angle from the attitude quaternion")
    columns = (phi, by.get("p"), by.get("r"))
    if all(c is None for c in columns):
        return None
    _check_turn_units(path, cols, columns)
    t = by["time"]
    out = []
    for col in columns:
        filled = np.full(len(t), np.nan) if col is None else col.copy()
        ok = np.isfinite(filled)
        if ok.sum() >= 2 and not ok.all():
            inside = (t >= t[ok][0]) & (t <= t[ok][-1])
            filled[inside] = np.interp(t[inside], t[ok], filled[ok])
        out.append(filled)
    return out


TURN_LIMITS: tuple[tuple[str, str, float, str, str], ...] = (
    ("phi", "bank angle", math.pi + 0.01, "rad", "deg"),
    ("p", "roll rate", PLAUSIBLE_MAX[PLAUSIBLE_QUANTITIES.index("q")], "rad/s", "deg/s"),
    ("r", "yaw rate", PLAUSIBLE_MAX[PLAUSIBLE_QUANTITIES.index("q")], "rad/s", "deg/s"),
)
"""Each turn column's largest magnitude in SI (half a turn of bank; the pitch rate's
limit for the rates), its unit and the unit a larger value is likely in."""


def _check_turn_units(
    path: str | Path, cols: Columns, columns: tuple[FloatArray | None, ...]
) -> None:
    """Refuse a turn column whose values cannot be in its configured unit, naming the
    likely one."""
    for (key, what, limit, si, likely), col in zip(TURN_LIMITS, columns, strict=True):
        if col is None or not np.any(np.isfinite(col)):
            continue
        worst = float(np.nanmax(np.abs(col)))
        if worst > limit:
            raise FlightDataError(
                f"{path}: the {what} reaches {worst:g} (read as {si}): if {getattr(cols, key)!r} "
                f'is in {likely}, set [data.units] {key} = "{likely}" (or --set '
                f'data.units.{key}="{likely}")'
            )


def _open_csv(
    path: str | Path, encoding: str, notes: list[str]
) -> tuple[str, str, csv.DictReader[str], list[str]]:
    """A CSV's text, column separator (noted unless a comma), reader and header row."""
    try:
        with open(path, newline="", encoding=encoding) as fh:
            text = fh.read()
    except OSError as exc:
        raise FlightDataError(f"{path}: cannot read: {exc.strerror}") from exc
    delimiter = _delimiter(text)
    if delimiter != ",":
        notes.append(
            f"{path}: columns separated by {DELIMITER_NAMES[delimiter]}; a comma in a number "
            "read as its decimal point"
        )
    reader = csv.DictReader(io.StringIO(text), delimiter=delimiter)
    try:
        header = list(reader.fieldnames or [])
    except csv.Error as exc:
        raise FlightDataError(f"{path}:1: not a CSV row: {exc}") from exc
    if not header:
        raise FlightDataError(f"{path}: an empty file: a CSV needs a header row and data rows")
    return text, delimiter, reader, header


def _factor(path: str | Path, data: DataConfig, quantity: str, travel_deg: float) -> float:
    """A column's multiplier to SI: its unit's factor times its [data.scale]; a
    normalised elevator's unit is the airframe's elevator travel."""
    unit = data.units.factor(quantity)
    if quantity == "elevator" and data.units.elevator == NORMALISED:
        if travel_deg <= 0:
            raise FlightDataError(
                f'{path}: the elevator column is a normalised command ([data.units] elevator = "'
                f'{NORMALISED}"): set [airframe] elevator_travel_deg to the deflection at full '
                "command in degrees (or --set airframe.elevator_travel_deg=DEG)"
            )
        unit = math.radians(travel_deg)
    return unit * data.scale.of(quantity)


def hold_inputs(
    path: str | Path,
    arr: FloatArray,
    columns: tuple[int, ...],
    names: tuple[str, ...],
    data: DataConfig,
    notes: list[str],
) -> tuple[FloatArray, BoolArray]:
    """The rows (in time order, time in the first column) with every empty cell of the
    input columns filled as [data] input_hold says: linear between the samples either
    side, or the earlier sample held; after the last sample, the last held. Rows before
    the first sample of every input are dropped (nothing to hold). Each is counted in
    notes. An input column with no number at all is refused.

    Also which rows' inputs are known: an empty run longer than LOST_GAP times the
    column's usual one (its median: 0 for a column logged every row, 7 for one logged
    every 8th) is a lost sample, and where the samples either side differ the filled
    value is a guess (False), as the link marks a frame whose input sample was lost
    while the input changed."""
    for j, name in zip(columns, names, strict=True):
        if not np.isfinite(arr[:, j]).any():
            raise FlightDataError(f"{path}: {name!r} (an input) holds no number")
    first = max(int(np.flatnonzero(np.isfinite(arr[:, j]))[0]) for j in columns)
    arr = arr.copy()
    t = arr[:, 0]
    held = 0
    known_rows = np.ones(len(arr), bool)
    for j in columns:
        v = arr[:, j]
        known = np.isfinite(v)
        held += int((~known[first:]).sum())
        known_rows &= ~_lost_and_changed(v, known)
        if data.input_hold == "linear":
            arr[:, j] = np.interp(t, t[known], v[known])
        else:
            last = np.maximum.accumulate(np.where(known, np.arange(len(v)), 0))
            arr[:, j] = v[last]
    if first:
        notes.append(
            f"{path}: {first} row(s) before the first sample of every input skipped (no input "
            "to hold there)"
        )
        arr, known_rows = arr[first:], known_rows[first:]
    if held:
        how = (
            "interpolated between the samples either side"
            if data.input_hold == "linear"
            else "the earlier sample held"
        )
        guessed = int((~known_rows).sum())
        notes.append(
            f"{path}: {held} empty input cell(s) filled ([data] input_hold = "
            f'"{data.input_hold}": {how})'
            + (
                f"; {guessed} of them in gaps over {LOST_GAP:g} x the column's usual while "
                "the input changed: those frames' inputs are guesses, and the flight states "
                "start again from their measurements"
                if guessed
                else ""
            )
        )
    return arr, known_rows


LOST_GAP = 2.0
"""A run of empty input cells longer than this many times the column's median run is a
lost sample, not the column's lower rate (a merge of topics spaces a column's samples
unevenly: up to twice its usual run is still its rate)."""


def _lost_and_changed(v: FloatArray, known: BoolArray) -> BoolArray:
    """The empty cells of an input column that are lost samples (a run of empty cells
    longer than LOST_GAP times the column's median run between samples) between samples
    that differ."""
    n = len(v)
    idx = np.arange(n)
    prev = np.maximum.accumulate(np.where(known, idx, -1))
    nxt = np.minimum.accumulate(np.where(known, idx, n)[::-1])[::-1]
    inside = ~known & (prev >= 0) & (nxt < n)
    samples = np.flatnonzero(known)
    usual = float(np.median(np.diff(samples) - 1)) if len(samples) > 1 else 0.0
    gap = nxt - prev - 1
    p, q = np.clip(prev, 0, n - 1), np.clip(nxt, 0, n - 1)
    out: BoolArray = inside & (gap > LOST_GAP * usual) & (v[p] != v[q])
    return out


def _in_time_order(
    path: str | Path, column: str, arr: FloatArray, lines: IntArray, notes: list[str]
) -> FloatArray:
    """The rows (time in SI in the first column) in time order, as a logger's file may
    hold them: rows without a time and rows that repeat an earlier row's time are
    skipped, rows out of order put back in order, each counted in notes. A step back of
    more than TIME_BACK_S is two recordings in one file: refused."""
    t = arr[:, 0]
    timed = np.isfinite(t)
    if not timed.any():
        raise FlightDataError(f"{path}: {column!r} (time) holds no number")
    if not timed.all():
        notes.append(
            f"{path}: {int((~timed).sum())} row(s) without a time skipped (the first at line "
            f"{int(lines[~timed][0])})"
        )
        arr, lines, t = arr[timed], lines[timed], t[timed]
    back = np.flatnonzero(np.diff(t) < -TIME_BACK_S)
    if len(back):
        k = int(back[0])
        raise FlightDataError(
            f"{path}:{int(lines[k + 1])}: {column!r} (time) goes back from {t[k]:g} to "
            f"{t[k + 1]:g} s: two recordings in one file? Split it and read each"
        )
    order = np.argsort(t, kind="stable")
    moved = int(np.count_nonzero(order != np.arange(len(t))))
    if moved:
        notes.append(f"{path}: {moved} row(s) out of time order put back in order")
        arr, lines, t = arr[order], lines[order], t[order]
    repeat = np.concatenate([[False], np.diff(t) <= 0.0])
    if repeat.any():
        notes.append(
            f"{path}: {int(repeat.sum())} row(s) repeating an earlier row's time skipped (the "
            f"first at line {int(lines[repeat][0])})"
        )
        arr = arr[~repeat]
    return arr


LIKELY_UNITS: dict[str, tuple[str, ...]] = {
    "time": ("ms", "us", "ns"),
    "airspeed": ("km/h", "kt", "ft/s"),
    "alpha": ("deg",),
    "theta": ("deg",),
    "elevator": ("deg",),
    "q": ("deg/s",),
    "qdot": ("deg/s^2",),
    "a_x": ("ft/s^2",),
    "a_z": ("ft/s^2",),
}
"""Units a column in the wrong unit is likely in, tried in order."""


def check_units(path: str | Path, si: dict[str, FloatArray], data: DataConfig) -> None:
    """Refuse a file whose values, read in the configured units, cannot be a fixed-wing
    aircraft's (config.PLAUSIBLE_MAX), naming the unit they are likely in. The time
    steps of a flight record are below a second."""
    t = si["time"]
    if len(t) > 2 and float(np.median(np.diff(t))) >= 1.0:
        step = float(np.median(np.diff(t)))
        now = units.factor("time", data.units.time)
        unit = next(
            (u for u in LIKELY_UNITS["time"] if step / now * units.factor("time", u) < 1.0),
            LIKELY_UNITS["time"][-1],
        )
        raise FlightDataError(
            f"{path}: time steps of {step:g} s (read as {data.units.time}); a flight record's "
            f'are below a second: if the column is in {unit}, set [data.units] time = "{unit}" '
            f"(or --set data.units.time={unit})"
        )
    limits = dict(zip(PLAUSIBLE_QUANTITIES, PLAUSIBLE_MAX, strict=True))
    for quantity, limit in limits.items():
        values = si.get(quantity)
        if values is None or not np.any(np.isfinite(values)):
            continue
        worst = float(np.nanmax(np.abs(values)))
        if worst <= limit:
            continue
        now = getattr(data.units, quantity)
        kind = QUANTITY_KINDS[quantity]
        hint = _normalised_hint(quantity, worst, now)
        for unit in () if hint or now == NORMALISED else LIKELY_UNITS.get(quantity, ()):
            if unit != now and worst / units.factor(kind, now) * units.factor(kind, unit) <= limit:
                hint = (
                    f"; if the column is in {unit}, set [data.units] {quantity} = "
                    f'"{unit}" (or --set data.units.{quantity}={unit})'
                )
                break
        raise FlightDataError(
            f"{path}: {quantity} reaches {worst:g} (SI, read as {now}), beyond the "
            f"{limit:g} a fixed-wing aircraft's can reach{hint}"
        )


def _normalised_hint(quantity: str, worst: float, now: str) -> str:
    """The advice for an elevator column that reaches 1 read as radians: a normalised
    command (-1..1, a PX4 or ROS export) rather than degrees."""
    if quantity != "elevator" or now != "rad" or not 0.95 <= worst <= 1.0 + 1e-9:
        return ""
    return (
        f'; if the column is a command -1..1, set [data.units] elevator = "{NORMALISED}" '
        "and [airframe] elevator_travel_deg (the deflection at full command)"
    )


def _density(air: dict[str, FloatArray]) -> FloatArray | None:
    """Air density per sample [kg/m^3] from the atmosphere columns read (SI), or None."""
    temp = air.get("air_temperature")
    if "air_density" in air:
        return air["air_density"]
    if "static_pressure" in air:
        return atmosphere.density(air["static_pressure"], temp)
    if "pressure_altitude" in air:
        return atmosphere.density(atmosphere.pressure(air["pressure_altitude"]), temp)
    return None


def _require(path: str | Path, header: list[str], quantities: list[str], cols: Columns) -> None:
    """Refuse a file without the columns of these quantities, naming every one missing,
    the file's column it may be, and the key to set."""
    missing = [q for q in quantities if getattr(cols, q) not in header]
    if not missing:
        return
    parts = []
    for q in missing:
        guess = difflib.get_close_matches(q, header, n=1, cutoff=0.6)
        like = f", perhaps {guess[0]!r}" if guess and guess[0] not in _named(cols) else ""
        parts.append(f"no column {getattr(cols, q)!r} for {q}{like}")
    keys = ", ".join(f'{q} = "..."' for q in missing)
    lack = [q for q in missing if q in OBSERVED]
    raise FlightDataError(
        f"{path}: {'; '.join(parts)}; name the file's column{'s' if len(missing) > 1 else ''} "
        f"with [data.columns] {keys} (or --set data.columns.{missing[0]}=NAME)"
        + (
            f'; if the data have no {lack[0]}, {lack[0]} = "" (the filters then go without it)'
            if lack
            else ""
        )
        + f"; the file has {header}"
    )


def _named(cols: Columns) -> set[str]:
    """The column names the config gives."""
    return {str(v) for v in vars(cols).values()}


def _power_column(path: str | Path, header: list[str], cols: Columns) -> tuple[str, bool]:
    """Which power input the file holds: thrust if its column is there, else throttle;
    and whether it is a glide (thrust = "" and no throttle column: thrust 0)."""
    if cols.thrust and cols.thrust in header:
        return "thrust", False
    if cols.throttle and cols.throttle in header:
        return "throttle", False
    if cols.thrust == "":
        return "thrust", True
    raise FlightDataError(
        f"{path}: no column {cols.throttle!r} (throttle) nor {cols.thrust!r} (thrust); name "
        f'one with [data.columns] throttle or thrust, or thrust = "" for a glide (no thrust); '
        f"the file has {header}"
    )


def _cell(text: str | None) -> float:
    if text is None or text.strip() == "":
        return math.nan
    return float(text)


def write_csv(path: str | Path, rec: Recording) -> None:
    """Write a recording in the documented CSV layout."""
    power_col = POWER_COLUMNS[rec.power]
    cols = Columns()
    head = [getattr(cols, q) for q in ("time", *OBSERVED, "elevator")] + [power_col]
    n_in = min(rec.inputs.shape[1], 3)
    if n_in == 3:
        head.append(cols.air_density)
    climb = rec.measurements.shape[1] > len(OBSERVED) and np.isfinite(rec.measurements[:, -1]).any()
    if climb:
        head.append(cols.climb_rate)
    turns = rec.inputs.shape[1] > 3 and bool(np.isfinite(rec.inputs[:, 3:]).any())
    if turns:
        head += [getattr(cols, q) for q in LATERAL_QUANTITIES]

    def cell(v: float) -> str:
        return "" if not math.isfinite(v) else repr(float(v))

    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for i in range(len(rec)):
            w.writerow(
                [repr(float(rec.t_s[i]))]
                + [cell(v) for v in rec.measurements[i, : len(OBSERVED)]]
                + [cell(v) for v in rec.inputs[i, :n_in]]
                + ([cell(rec.measurements[i, -1])] if climb else [])
                + ([cell(v) for v in rec.inputs[i, 3:6]] if turns else [])
            )
