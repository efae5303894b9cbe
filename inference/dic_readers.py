"""Readers of DIC exports (facts and choices: docs/measurements.md): VIC-3D/VIC-2D classic CSV
(``vic``), VIC 9+ extract CSV (``vic9``), DaVis 8 2D-vector txt (``davis8``), DaVis 10 CSV
(``davis10``), Sandia DICe solution txt (``dice``) and any other table (``table``, options in
:class:`TableOptions`). Each returns a :class:`DicTable`: the file's points, strains, units and
strain measure as the file states them, and a missing-point mask; :mod:`inference.dic_import`
converts it into a measurement.
"""

from __future__ import annotations

import csv
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inference.observations import (
    MeasurementError,
)

FORMATS = ("vic", "vic9", "davis8", "davis10", "dice", "table")
LENGTH_UNITS = {"mm": 1.0, "m": 1000.0, "cm": 10.0, "µm": 1e-3, "μm": 1e-3, "um": 1e-3}
PIXEL_UNITS = ("px", "pixel", "pixels", "pix")
FRACTION_UNITS = ("", "1", "-", "s", "mm/mm", "m/m")
TENSORS = {
    "lagrange": "green",
    "green-lagrange": "green",
    "green lagrange": "green",
    "gl": "green",
    "green": "green",
    "hencky": "log",
    "logarithmic": "log",
    "log": "log",
    "true": "log",
}
MISSING = (
    "",
    "nan",
    "-nan",
    "+nan",
    "na",
    "n/a",
    "#n/a",
    "#nv",
    "null",
    "none",
    "-",
    "--",
    "n.def.",
    "n. def.",
    "1.#qnan",
    "-1.#ind",
)
ALIASES = {
    "x": ("x", "coordinate_x", "coordinate x", "x coordinate"),
    "y": ("y", "coordinate_y", "coordinate y", "y coordinate"),
    "exx": ("exx", "e_xx", "εxx", "ε_xx", "eps_xx", "epsxx", "strain_xx", "e11", "ε11"),
    "eyy": ("eyy", "e_yy", "εyy", "ε_yy", "eps_yy", "epsyy", "strain_yy", "e22", "ε22"),
    "exy": ("exy", "e_xy", "εxy", "ε_xy", "eps_xy", "epsxy", "strain_xy", "e12", "ε12"),
}
ROLES = tuple(ALIASES)
DICE_OK_STATUS = (0, 1, 2, 3, 4, 6, 18)  # DICe.h Status_Flag: the *_SUCCESSFUL codes
MIN_POINTS = 10
TENSOR_NOT_NAMED = "the header does not name the strain tensor"


@dataclass
class TableOptions:
    """How to read a generic table (``--format table``); None = detect from the file.

    Attributes:
        delimiter: field separator (detected: ';', tab, ',' or whitespace).
        decimal: '.' or ',' (detected from the numbers).
        encoding: text encoding (detected: BOM -> UTF-8, valid UTF-8, else Latin-1).
        columns: names of the x, y, exx, eyy, exy columns (default: matched by name).
        units: coordinate unit 'mm' or 'px' when the header does not say.
        missing: extra missing-value markers (besides :data:`MISSING`).
        skip: lines to skip before the header (lines starting with '#' are always skipped).
    """

    delimiter: str | None = None
    decimal: str | None = None
    encoding: str | None = None
    columns: tuple[str, ...] | None = None
    units: str | None = None
    missing: tuple[str, ...] = ()
    skip: int = 0

    def given(self) -> list[str]:
        """Names of the options set (they apply to ``--format table`` only)."""
        return [n for n, v in vars(self).items() if v not in (None, (), 0)]


@dataclass
class DicTable:
    """What a reader found, in the file's frame, units and strain measure.

    Attributes:
        xy: (n, 2) point coordinates in ``length_unit``.
        strain: (n, 3) strain xx, yy, xy (tensor shear) as written (fraction or percent).
        valid: (n,) False where the file marks the point missing.
        lines: (n,) line number of each row in the file (for messages).
        length_unit: 'px', a key of :data:`LENGTH_UNITS`, or None when the file does not say.
        measure: strain measure (one of STRAIN_MEASURES) or None when unknown.
        measure_source: 'stated' when the file names it, else why it was assumed.
        percent: True/False when the file states the strain unit, else None.
        notes: what the reader could not decide (one short clause each).
    """

    path: Path
    format: str
    xy: np.ndarray
    strain: np.ndarray
    valid: np.ndarray
    lines: np.ndarray
    length_unit: str | None
    measure: str | None
    measure_source: str = "stated"
    percent: bool | None = None
    notes: list[str] = field(default_factory=list)


# ---------------------------------------------------------------- text and numbers


def fail(path: Path, line: int | None, problem: str):
    """Raise MeasurementError naming the file (and the line, when known)."""
    where = f"{path}:{line}" if line else f"{path}"
    raise MeasurementError(f"{where}: {problem}")


def _decode(path: Path, encoding: str | None, fallback: str = "utf-8") -> tuple[str, list[str]]:
    """The file's text and notes: a UTF-8 BOM wins, then ``encoding``, then ``fallback``, then
    Latin-1 (noted: it cannot be told from cp1252 and others)."""
    data = path.read_bytes()
    bom = data.startswith(b"\xef\xbb\xbf")
    chosen = "utf-8" if bom else encoding or fallback
    try:
        return data[3 if bom else 0 :].decode(chosen), []
    except LookupError:
        fail(path, None, f"unknown encoding '{chosen}'")
    except UnicodeDecodeError as exc:
        if bom or encoding:
            fail(path, None, f"is not valid {chosen} ({exc.reason} at byte {exc.start})")
    return data.decode("latin-1"), ["encoding not UTF-8: read as Latin-1 (give --encoding if wrong)"]


def _lines(path: Path, fallback: str = "utf-8") -> list[str]:
    """The lines of a program's export (BOM honoured, else ``fallback``, else Latin-1)."""
    lines = _decode(path, None, fallback)[0].splitlines()
    if not lines:
        fail(path, None, "is empty")
    return lines


def _cells(line: str, delimiter: str | None) -> list[str]:
    """Header cells without quotes and surrounding spaces (CSV quoting honoured)."""
    if delimiter is None:
        return [c.strip('"') for c in line.split()]
    return [c.strip().strip('"').strip() for c in next(csv.reader([line], delimiter=delimiter))]


def _numbers(
    path: Path,
    rows: list[tuple[int, str]],
    delimiter: str | None,
    n_cols: int,
    decimal: str = ".",
    missing: tuple[str, ...] = MISSING,
) -> np.ndarray:
    """(n, n_cols) values of data rows (line number, text); missing markers -> NaN.

    Raises:
        MeasurementError: a row with the wrong number of fields or a value that is not a number.
    """
    markers = {m.lower() for m in missing}
    out = np.empty((len(rows), n_cols))
    for i, (lineno, text) in enumerate(rows):
        parts = text.split(delimiter)
        if len(parts) != n_cols:
            fail(path, lineno, f"expected {n_cols} values, found {len(parts)}")
        for j, part in enumerate(parts):
            part = part.strip().strip('"').strip()
            if part.lower() in markers:
                out[i, j] = np.nan
                continue
            try:
                out[i, j] = float(part.replace(",", ".") if decimal == "," else part)
            except ValueError:
                fail(path, lineno, f"value '{part}' is not a number (give --missing if it marks a missing point)")
    return out


def _data_rows(lines: list[str], start: int) -> list[tuple[int, str]]:
    """(line number, text) of the non-empty lines from index ``start``."""
    return [(i + 1, line) for i, line in enumerate(lines[start:], start=start) if line.strip()]


# ---------------------------------------------------------------- column names


def parse_name(name: str) -> tuple[str, str | None, str | None]:
    """Split a column name into (base, unit, tensor).

    ``'exx [1] - Lagrange'`` -> ``('exx', '1', 'Lagrange')``;
    ``'Transverse strain Exx - GL[S]'`` -> ``('Transverse strain Exx', 'S', 'GL')``.
    """
    units = re.findall(r"\[([^\]]*)\]", name)
    rest = re.sub(r"\[[^\]]*\]", " ", name)
    base, _, tensor = rest.partition(" - ")
    return base.strip(), units[-1].strip() if units else None, tensor.strip() or None


def _matches(base: str, role: str) -> bool:
    low = base.lower()
    if low in ALIASES[role]:
        return True
    return role.startswith("e") and re.split(r"\s+", low)[-1] in ALIASES[role]


def find_columns(path: Path, names: list[str], wanted: tuple[str, ...] | None = None) -> dict[str, int]:
    """Index of the x, y, exx, eyy, exy columns among ``names``.

    By name (:data:`ALIASES`, case-insensitive; for coordinates a metric column wins over a
    pixel one) or, with ``wanted``, the five exact names given by the user.
    """
    bases = [parse_name(n) for n in names]
    found = {}
    for k, role in enumerate(ROLES):
        if wanted is not None:
            hits = [i for i, n in enumerate(names) if n == wanted[k] or bases[i][0] == wanted[k]]
        else:
            hits = [i for i, (b, _, _) in enumerate(bases) if _matches(b, role)]
            hits.sort(key=lambda i: (bases[i][1] or "").lower() in PIXEL_UNITS)
        if not hits:
            want = f"'{wanted[k]}'" if wanted else f"{role} (e.g. {', '.join(ALIASES[role][:3])})"
            fail(path, None, f"no column {want} among {names}; name them with --columns X Y EXX EYY EXY")
        found[role] = hits[0]
    return found


def _length_unit(path: Path, unit: str | None) -> str | None:
    if unit is None:
        return None
    low = unit.lower()
    if low in PIXEL_UNITS:
        return "px"
    if low in LENGTH_UNITS:
        return low
    fail(path, None, f"coordinate unit '{unit}' is not one of px, {', '.join(LENGTH_UNITS)}")


def _strain_unit(path: Path, unit: str | None) -> bool | None:
    """True for percent, False for a fraction, None when the header gives no unit."""
    if unit is None:
        return None
    if unit.strip() == "%":
        return True
    if unit.strip().lower() in FRACTION_UNITS:
        return False
    fail(path, None, f"strain unit '{unit}' is not understood (use a fraction [1] or percent [%])")


def _tensor(name: str | None) -> tuple[str | None, str]:
    """(measure, source) of a tensor name written in a header, e.g. 'Lagrange' -> green."""
    if name is None:
        return None, TENSOR_NOT_NAMED
    measure = TENSORS.get(name.strip().lower())
    return measure, "stated" if measure else f"strain tensor '{name}' is not recognised"


def _named_table(
    path: Path, fmt: str, names: list[str], values: np.ndarray, lines: np.ndarray, wanted: tuple[str, ...] | None = None
) -> DicTable:
    """A DicTable from named columns carrying units ('x [mm]') and tensors ('exx [1] - Lagrange')."""
    col = find_columns(path, names, wanted)
    _, x_unit, _ = parse_name(names[col["x"]])
    _, e_unit, tensor = parse_name(names[col["exx"]])
    measure, source = _tensor(tensor)
    return DicTable(
        path,
        fmt,
        values[:, [col["x"], col["y"]]],
        values[:, [col["exx"], col["eyy"], col["exy"]]],
        np.ones(len(values), dtype=bool),
        lines,
        _length_unit(path, x_unit),
        measure,
        source,
        _strain_unit(path, e_unit),
    )


def _sigma_mask(table: DicTable, names: list[str], values: np.ndarray) -> DicTable:
    """VIC: a point with sigma < 0 (written -1, every other field 0) was not correlated (a table
    read with --format table follows the same rule when it has a ``sigma`` column)."""
    hits = [i for i, n in enumerate(names) if parse_name(n)[0] == "sigma"]
    if hits:
        table.valid &= ~(values[:, hits[0]] < 0)
    return table


# ---------------------------------------------------------------- readers


def read_vic(path: Path) -> DicTable:
    """VIC-3D (X, Y mm) or VIC-2D (x, y px) classic CSV; sigma < 0 marks missing points.

    The export does not name the strain tensor: Lagrange (VIC's default) is assumed.
    """
    lines = _lines(path)
    names = _cells(lines[0], ",")
    metric = "X" in names and "Y" in names
    xy_names = ("X", "Y") if metric else ("x", "y")
    missing = [n for n in (*xy_names, "exx", "eyy", "exy") if n not in names]
    if missing:
        fail(path, 1, f"VIC column(s) {', '.join(missing)} missing; found {names}")
    rows = _data_rows(lines, 1)
    values = _numbers(path, rows, ",", len(names))
    idx = [names.index(n) for n in (*xy_names, "exx", "eyy", "exy")]
    table = DicTable(
        path,
        "vic",
        values[:, idx[:2]],
        values[:, idx[2:]],
        np.ones(len(rows), dtype=bool),
        np.array([r[0] for r in rows]),
        "mm" if metric else "px",
        "green",
        "the classic VIC export does not name its strain tensor: assumed Lagrange, VIC's default",
        False,
    )
    return _sigma_mask(table, names, values)


def read_vic9(path: Path) -> DicTable:
    """VIC 9+ extract CSV: quoted names with units and tensor (``"exx [1] - Lagrange"``).

    Lines before the header (image name, polyline group row) are skipped; one image per file.
    """
    lines = _lines(path)
    start = next((i for i, line in enumerate(lines[:20]) if sum("[" in c for c in _cells(line, ",")) >= 3), None)
    if start is None:
        fail(path, None, 'no VIC header with units (e.g. "X [mm]") in the first 20 lines')
    end = next((i for i in range(start + 1, len(lines)) if not lines[i].strip()), len(lines))
    more = next((i for i in range(end, len(lines)) if lines[i].strip()), None)
    if more is not None:
        fail(path, more + 1, "the file holds several images (or slices): export one image per file")
    names = _cells(lines[start], ",")
    rows = _data_rows(lines[:end], start + 1)
    values = _numbers(path, rows, ",", len(names))
    table = _named_table(path, "vic9", names, values, np.array([r[0] for r in rows]))
    return _sigma_mask(table, names, values)


def read_davis10(path: Path) -> DicTable:
    """DaVis 10 CSV: ';', Latin-1, ``Exx [S]``; '- GL' names Green-Lagrange, otherwise DaVis
    writes linear strain, read as engineering (Biot) strain (equal to first order)."""
    lines = _lines(path, fallback="latin-1")
    names = _cells(lines[0], ";")
    rows = _data_rows(lines, 1)
    values = _numbers(path, rows, ";", len(names))
    table = _named_table(path, "davis10", names, values, np.array([r[0] for r in rows]))
    if table.measure_source == TENSOR_NOT_NAMED:
        table.measure = "engineering"
        table.measure_source = "no '- GL' in the names: DaVis linear strain read as engineering (Biot) strain"
    table.percent = bool(table.percent)
    return table


def read_dice(path: Path) -> DicTable:
    """DICe solution txt: ``***`` preamble, UPPER_CASE header, %.4E numbers, pixels.

    VSG (else NLVC) strains, Green-Lagrange. Missing: SIGMA < 0, MATCH < 0, or a STATUS_FLAG
    outside :data:`DICE_OK_STATUS`.
    """
    lines = _lines(path)
    start = next((i for i, line in enumerate(lines) if line.strip() and not line.startswith("***")), None)
    if start is None:
        fail(path, None, "no header line after the *** preamble")
    delimiter = "," if "," in lines[start] else None
    names = _cells(lines[start], delimiter)
    kind = "VSG" if "VSG_STRAIN_XX" in names else "NLVC"
    wanted = ("COORDINATE_X", "COORDINATE_Y", *(f"{kind}_STRAIN_{c}" for c in ("XX", "YY", "XY")))
    missing = [n for n in wanted if n not in names]
    if missing:
        fail(
            path,
            start + 1,
            f"DICe column(s) {', '.join(missing)} missing (strains need VSG_STRAIN_XX, _YY and _XY); found {names}",
        )
    rows = _data_rows(lines, start + 1)
    values = _numbers(path, rows, delimiter, len(names))
    col = {n: names.index(n) for n in names}
    valid = np.ones(len(rows), dtype=bool)
    for flag in ("SIGMA", "MATCH"):
        if flag in col:
            valid &= ~(values[:, col[flag]] < 0)
    if "STATUS_FLAG" in col:
        valid &= np.isin(values[:, col["STATUS_FLAG"]], DICE_OK_STATUS)
    idx = [col[n] for n in wanted]
    return DicTable(
        path,
        "dice",
        values[:, idx[:2]],
        values[:, idx[2:]],
        valid,
        np.array([r[0] for r in rows]),
        "px",
        "green",
        "stated",
        False,
    )


def read_davis8(path: Path) -> DicTable:
    """DaVis 8 2D-vector txt: x y u v on a regular grid; strains computed here.

    The deformation gradient F = I + grad u comes from ``np.gradient`` on the grid (central
    differences inside, one-sided at the edges; a NaN spreads to its neighbours, which are then
    missing), and the Green-Lagrange strain E = (F^T F - I)/2 from it.
    """
    lines = _lines(path)
    try:
        head = shlex.split(lines[0])
    except ValueError as exc:
        fail(path, 1, f"unreadable DaVis header ({exc})")
    if len(head) < 12 or head[2] != "2D-vector":
        fail(
            path,
            1,
            "not a DaVis 8 '2D-vector' header (#DaVis <version> 2D-vector <step> <ny> <nx> + 6 quoted "
            "labels and units)",
        )
    if not (head[4].isdigit() and head[5].isdigit() and int(head[4]) > 1 and int(head[5]) > 1):
        fail(path, 1, f"grid size '{head[4]} {head[5]}' is not two integers <ny> <nx> > 1")
    ny, nx = int(head[4]), int(head[5])
    units = {head[7].lower(), head[9].lower(), head[11].lower()}
    if len(units) != 1:
        fail(path, 1, f"coordinates ({head[7]}, {head[9]}) and displacement ({head[11]}) units differ")
    rows = _data_rows(lines, 1)
    if len(rows) != ny * nx:
        fail(path, None, f"the header announces {ny} x {nx} = {ny * nx} vectors, the file has {len(rows)}")
    grid = _numbers(path, rows, None, 4).reshape(ny, nx, 4)
    xs, ys = grid[0, :, 0], grid[:, 0, 1]
    if not (np.all(grid[..., 0] == xs) and np.all(grid[..., 1] == ys[:, None])):
        fail(path, None, "the vectors are not on a regular grid with x varying fastest")
    green = _green_from_displacement(grid[..., 2], grid[..., 3], xs, ys)
    xy = grid[..., :2].reshape(-1, 2)
    return DicTable(
        path,
        "davis8",
        xy,
        green.reshape(-1, 3),
        np.all(np.isfinite(green.reshape(-1, 3)), axis=1),
        np.array([r[0] for r in rows]),
        _length_unit(path, units.pop()),
        "green",
        "stated",
        False,
    )


def _green_from_displacement(u: np.ndarray, v: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(ny, nx, 3) Green-Lagrange strain xx, yy, xy of displacements u, v (ny, nx) on a grid."""
    du_dy, du_dx = np.gradient(u, ys, xs)
    dv_dy, dv_dx = np.gradient(v, ys, xs)
    exx = du_dx + 0.5 * (du_dx**2 + dv_dx**2)
    eyy = dv_dy + 0.5 * (du_dy**2 + dv_dy**2)
    exy = 0.5 * (du_dy + dv_dx + du_dx * du_dy + dv_dx * dv_dy)
    return np.stack([exx, eyy, exy], axis=-1)


def read_table(path: Path, options: TableOptions) -> DicTable:
    """Any delimited table with x, y, exx, eyy, exy columns (see :class:`TableOptions`)."""
    text, notes = _decode(path, options.encoding)
    lines = text.splitlines()
    body = [i for i, line in enumerate(lines) if i >= options.skip and line.strip() and not line.startswith("#")]
    if len(body) < 2:
        fail(path, None, "no data rows after a header" if body else "no header line")
    header, rows = body[0], [(i + 1, lines[i]) for i in body[1:]]
    delimiter = options.delimiter or _sniff_delimiter(lines[header], rows[0][1])
    decimal = options.decimal or _sniff_decimal(path, rows, delimiter)
    if decimal == delimiter:
        fail(path, None, f"the decimal mark and the delimiter are both '{decimal}'")
    names = _cells(lines[header], delimiter)
    values = _numbers(path, rows, delimiter, len(names), decimal, MISSING + tuple(options.missing))
    table = _sigma_mask(
        _named_table(path, "table", names, values, np.array([r[0] for r in rows]), options.columns), names, values
    )
    table.notes = notes
    if options.units is not None:
        unit = _length_unit(path, options.units)
        if table.length_unit not in (None, unit):
            fail(
                path,
                None,
                f"the header states coordinates in {table.length_unit}; --units {options.units} contradicts it",
            )
        table.length_unit = unit
    return table


def _sniff_delimiter(header: str, first_row: str) -> str | None:
    """';', tab or ',' when the header and the first row have as many of it; else whitespace."""
    for d in (";", "\t", ","):
        if header.count(d) and header.count(d) == first_row.count(d):
            return d
    return None


def _sniff_decimal(path: Path, rows: list[tuple[int, str]], delimiter: str | None) -> str:
    """',' when numbers such as '0,5' occur (never with a ',' delimiter), else '.'."""
    if delimiter == ",":
        return "."
    fields = [f.strip() for _, text in rows for f in text.split(delimiter)]
    comma = any(re.fullmatch(r"[+-]?\d*,\d+([eE][+-]?\d+)?", f) for f in fields)
    point = any(re.fullmatch(r"[+-]?\d*\.\d+([eE][+-]?\d+)?", f) for f in fields)
    if comma and point:
        fail(path, None, "numbers use both '.' and ',' as decimal mark: give --decimal")
    return "," if comma else "."


# ---------------------------------------------------------------- detection


def detect_format(path: Path) -> str:
    """The format of a DIC export from its first lines, when unambiguous.

    Raises:
        MeasurementError: the first lines match no known export (use --format).
    """
    head = path.read_bytes()[:8192].removeprefix(b"\xef\xbb\xbf").decode("latin-1").splitlines()[:6]
    first = head[0] if head else ""
    if first.startswith("#DaVis"):
        return "davis8"
    if first.startswith("***") or first.startswith(("SUBSET_ID", "COORDINATE_X")):
        return "dice"
    if first.startswith("# skinid-measurement"):
        fail(path, 1, "is already a skinid measurement: use it directly")
    if ";" in first and ("[S]" in first or "displacement [" in first.lower()):
        return "davis10"
    if first.lstrip().startswith('"'):
        if any(sum("[" in c for c in _cells(line, ",")) >= 3 for line in head):
            return "vic9"
        if "sigma" in _cells(first, ","):
            return "vic"
    fail(
        path,
        1,
        f"format not recognised from the first line ({first[:60]!r}): give --format "
        f"({', '.join(FORMATS)}; 'table' for any other table)",
    )


def read_dic(path: Path | str, fmt: str = "auto", table: TableOptions | None = None) -> DicTable:
    """Read a DIC export of format ``fmt`` (one of :data:`FORMATS`, or "auto": detected); ``table``:
    the options of the generic table reader."""
    path = Path(path)
    if not path.is_file():
        raise MeasurementError(f"DIC file '{path}' does not exist")
    fmt = detect_format(path) if fmt == "auto" else fmt
    if fmt == "table":
        return read_table(path, table or TableOptions())
    readers = {"vic": read_vic, "vic9": read_vic9, "davis8": read_davis8, "davis10": read_davis10, "dice": read_dice}
    return readers[fmt](path)
