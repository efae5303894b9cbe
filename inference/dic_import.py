"""Import DIC exports as skinid measurements (design.md §4; docs/measurements.md).

Formats (facts and choices: docs/measurements.md): VIC-3D/VIC-2D classic CSV (``vic``), VIC 9+ extract
CSV (``vic9``), DaVis 8 2D-vector txt (``davis8``), DaVis 10 CSV (``davis10``), Sandia DICe
solution txt (``dice``) and any other table (``table``, options in :class:`TableOptions`).

Pipeline: a reader turns a file into a :class:`DicTable` (file frame, file units, the file's
strain measure, a missing-point mask); :func:`convert` masks, scales (px -> mm), moves and
rotates points and tensors into the membrane frame, converts the strain to log strain and
drops points outside the model block, giving a :class:`DicField`;
:func:`assess_plausibility` compares the mean strain under the membrane with the design's
imposed strain. Units: mm; angles in degrees in :class:`ImportSettings` (the user's input),
radians inside the functions that take ``rotation``.
"""

from __future__ import annotations

import csv
import math
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inference.observations import (
    STRAIN_MEASURES,
    Measurement,
    MeasurementError,
    read_measurement,
    to_log_strain,
    write_measurement,
)
from skinfem.outputs import write_atomically

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
# Plausibility tolerances (docs/measurements.md "The plausibility check").
RATIO_RANGE = (0.05, 5.0)  # |mean measured| / |imposed|; FE `small` sweep: 0.23 .. 1.08
COS_MIN = 0.8  # cosine of the angle between them; FE `small` sweep: >= 0.93
IMPOSED_FLOOR = 1e-4  # designs imposing less log strain than this are not checked


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
class ImportSettings:
    """What the user states about a DIC export.

    Attributes:
        format: one of :data:`FORMATS` or 'auto'.
        mm_per_px: image scale [mm/px]; required for pixel coordinates, refused for metric ones.
        centre: (2,) membrane centre in the file's coordinates (file units: px or mm).
        rotation: angle [degrees] from the file's x axis to the membrane's x axis (alpha11
            direction), positive towards the file's y axis.
        flip_y: the file's frame is mirrored (image coordinates, y down): the membrane's y axis
            is then the opposite of the file's y axis turned by ``rotation``.
        strain: strain measure (log, green, engineering) when the file does not state it.
        percent: strains are in percent.
        membrane_half, block_half: half side of the membrane and of the model block [mm].
        table: options of the generic table reader.
    """

    format: str = "auto"
    mm_per_px: float | None = None
    centre: tuple[float, float] = (0.0, 0.0)
    rotation: float = 0.0
    flip_y: bool = False
    strain: str | None = None
    percent: bool = False
    membrane_half: float = 10.0
    block_half: float = 25.0
    table: TableOptions = field(default_factory=TableOptions)

    def validate(self) -> None:
        """Raise ValueError naming the first bad setting."""
        if self.format not in (*FORMATS, "auto"):
            raise ValueError(f"format '{self.format}' is not one of auto, {', '.join(FORMATS)}")
        if self.mm_per_px is not None and not (math.isfinite(self.mm_per_px) and self.mm_per_px > 0):
            raise ValueError(f"--mm-per-px must be a positive number, got {self.mm_per_px}")
        if not all(math.isfinite(v) for v in (*self.centre, self.rotation)):
            raise ValueError("--centre and --rotation must be finite numbers")
        if self.strain is not None and self.strain not in STRAIN_MEASURES:
            raise ValueError(f"strain measure '{self.strain}' is not one of {', '.join(STRAIN_MEASURES)}")
        if self.format != "table" and self.table.given():
            raise ValueError(f"--{self.table.given()[0]} applies to --format table only")


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


@dataclass
class DicField:
    """An imported strain field in the membrane frame.

    Attributes:
        xy: (n, 2) points [mm], membrane frame (x = alpha11 direction, centred on the membrane).
        strain: (n, 3) log strain xx, yy, xy (tensor shear) in the membrane frame.
        n_rows, n_missing, n_outside: data rows read, masked as missing, dropped outside the block.
        notes: what could not be decided from the file (assumptions made).
    """

    path: Path
    format: str
    xy: np.ndarray
    strain: np.ndarray
    n_rows: int
    n_missing: int
    n_outside: int
    notes: list[str] = field(default_factory=list)

    def measurement(self, alpha, t: float) -> Measurement:
        """The field as a :class:`Measurement` of design ``alpha`` (2,) at load fraction ``t``."""
        alpha = np.asarray(alpha, dtype=float)
        if alpha.shape != (2,) or not np.all(np.isfinite(alpha)):
            raise MeasurementError(f"alpha must be two finite numbers (alpha11, alpha22), got {alpha}")
        if not (math.isfinite(t) and 0 < t <= 1):
            raise MeasurementError(f"t = {t} must be in (0, 1]")
        return Measurement(self.path, alpha, float(t), self.xy, self.strain, None)


@dataclass
class Plausibility:
    """Mean measured log strain under the membrane against the design's imposed strain.

    Attributes:
        n_points: points with |x|, |y| <= membrane half side.
        measured: (3,) their mean log strain xx, yy, xy.
        imposed: (3,) ln(1 + t alpha11), ln(1 + t alpha22), 0: the membrane's eigen-strain.
        ratio: Frobenius norm of measured / of imposed (NaN when not checked).
        cosine: cosine of the angle between them (Frobenius inner product; NaN when not checked).
        problem: the likely cause, one line, when implausible; None otherwise.
    """

    n_points: int
    measured: np.ndarray
    imposed: np.ndarray
    ratio: float
    cosine: float
    problem: str | None

    def summary(self) -> str:
        """One line for the user."""
        m, e = self.measured, self.imposed
        if self.problem is not None:
            return f"implausible: {self.problem}"
        if not math.isfinite(self.ratio):
            return f"plausibility not checked: the design imposes less than {IMPOSED_FLOOR:g} log strain"
        return (
            f"plausible: mean log strain under the membrane ({self.n_points} points) xx {m[0]:.4g}, "
            f"yy {m[1]:.4g}, xy {m[2]:.2g}; design ln(1 + t·α) {e[0]:.4g}, {e[1]:.4g}; "
            f"ratio {self.ratio:.2f}, cosine {self.cosine:.3f}"
        )


# ---------------------------------------------------------------- text and numbers


def _fail(path: Path, line: int | None, problem: str):
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
        _fail(path, None, f"unknown encoding '{chosen}'")
    except UnicodeDecodeError as exc:
        if bom or encoding:
            _fail(path, None, f"is not valid {chosen} ({exc.reason} at byte {exc.start})")
    return data.decode("latin-1"), ["encoding not UTF-8: read as Latin-1 (give --encoding if wrong)"]


def _lines(path: Path, fallback: str = "utf-8") -> list[str]:
    """The lines of a program's export (BOM honoured, else ``fallback``, else Latin-1)."""
    lines = _decode(path, None, fallback)[0].splitlines()
    if not lines:
        _fail(path, None, "is empty")
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
            _fail(path, lineno, f"expected {n_cols} values, found {len(parts)}")
        for j, part in enumerate(parts):
            part = part.strip().strip('"').strip()
            if part.lower() in markers:
                out[i, j] = np.nan
                continue
            try:
                out[i, j] = float(part.replace(",", ".") if decimal == "," else part)
            except ValueError:
                _fail(path, lineno, f"value '{part}' is not a number (give --missing if it marks a missing point)")
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
            _fail(path, None, f"no column {want} among {names}; name them with --columns X Y EXX EYY EXY")
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
    _fail(path, None, f"coordinate unit '{unit}' is not one of px, {', '.join(LENGTH_UNITS)}")


def _strain_unit(path: Path, unit: str | None) -> bool | None:
    """True for percent, False for a fraction, None when the header gives no unit."""
    if unit is None:
        return None
    if unit.strip() == "%":
        return True
    if unit.strip().lower() in FRACTION_UNITS:
        return False
    _fail(path, None, f"strain unit '{unit}' is not understood (use a fraction [1] or percent [%])")


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
        _fail(path, 1, f"VIC column(s) {', '.join(missing)} missing; found {names}")
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
        _fail(path, None, 'no VIC header with units (e.g. "X [mm]") in the first 20 lines')
    end = next((i for i in range(start + 1, len(lines)) if not lines[i].strip()), len(lines))
    more = next((i for i in range(end, len(lines)) if lines[i].strip()), None)
    if more is not None:
        _fail(path, more + 1, "the file holds several images (or slices): export one image per file")
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
        _fail(path, None, "no header line after the *** preamble")
    delimiter = "," if "," in lines[start] else None
    names = _cells(lines[start], delimiter)
    kind = "VSG" if "VSG_STRAIN_XX" in names else "NLVC"
    wanted = ("COORDINATE_X", "COORDINATE_Y", *(f"{kind}_STRAIN_{c}" for c in ("XX", "YY", "XY")))
    missing = [n for n in wanted if n not in names]
    if missing:
        _fail(
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
        _fail(path, 1, f"unreadable DaVis header ({exc})")
    if len(head) < 12 or head[2] != "2D-vector":
        _fail(
            path,
            1,
            "not a DaVis 8 '2D-vector' header (#DaVis <version> 2D-vector <step> <ny> <nx> + 6 quoted "
            "labels and units)",
        )
    if not (head[4].isdigit() and head[5].isdigit() and int(head[4]) > 1 and int(head[5]) > 1):
        _fail(path, 1, f"grid size '{head[4]} {head[5]}' is not two integers <ny> <nx> > 1")
    ny, nx = int(head[4]), int(head[5])
    units = {head[7].lower(), head[9].lower(), head[11].lower()}
    if len(units) != 1:
        _fail(path, 1, f"coordinates ({head[7]}, {head[9]}) and displacement ({head[11]}) units differ")
    rows = _data_rows(lines, 1)
    if len(rows) != ny * nx:
        _fail(path, None, f"the header announces {ny} x {nx} = {ny * nx} vectors, the file has {len(rows)}")
    grid = _numbers(path, rows, None, 4).reshape(ny, nx, 4)
    xs, ys = grid[0, :, 0], grid[:, 0, 1]
    if not (np.all(grid[..., 0] == xs) and np.all(grid[..., 1] == ys[:, None])):
        _fail(path, None, "the vectors are not on a regular grid with x varying fastest")
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
        _fail(path, None, "no data rows after a header" if body else "no header line")
    header, rows = body[0], [(i + 1, lines[i]) for i in body[1:]]
    delimiter = options.delimiter or _sniff_delimiter(lines[header], rows[0][1])
    decimal = options.decimal or _sniff_decimal(path, rows, delimiter)
    if decimal == delimiter:
        _fail(path, None, f"the decimal mark and the delimiter are both '{decimal}'")
    names = _cells(lines[header], delimiter)
    values = _numbers(path, rows, delimiter, len(names), decimal, MISSING + tuple(options.missing))
    table = _sigma_mask(
        _named_table(path, "table", names, values, np.array([r[0] for r in rows]), options.columns), names, values
    )
    table.notes = notes
    if options.units is not None:
        unit = _length_unit(path, options.units)
        if table.length_unit not in (None, unit):
            _fail(
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
        _fail(path, None, "numbers use both '.' and ',' as decimal mark: give --decimal")
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
        _fail(path, 1, "is already a skinid measurement: use it directly")
    if ";" in first and ("[S]" in first or "displacement [" in first.lower()):
        return "davis10"
    if first.lstrip().startswith('"'):
        if any(sum("[" in c for c in _cells(line, ",")) >= 3 for line in head):
            return "vic9"
        if "sigma" in _cells(first, ","):
            return "vic"
    _fail(
        path,
        1,
        f"format not recognised from the first line ({first[:60]!r}): give --format "
        f"({', '.join(FORMATS)}; 'table' for any other table)",
    )


def read_dic(path: Path | str, settings: ImportSettings) -> DicTable:
    """Read a DIC export (format from ``settings.format`` or detected)."""
    path = Path(path)
    if not path.is_file():
        raise MeasurementError(f"DIC file '{path}' does not exist")
    fmt = detect_format(path) if settings.format == "auto" else settings.format
    if fmt == "table":
        return read_table(path, settings.table)
    readers = {"vic": read_vic, "vic9": read_vic9, "davis8": read_davis8, "davis10": read_davis10, "dice": read_dice}
    return readers[fmt](path)


# ---------------------------------------------------------------- conversion


def frame_matrix(rotation: float, flip_y: bool = False) -> np.ndarray:
    """(2, 2) Q whose rows are the membrane's x and y axes in file coordinates.

    Args:
        rotation: angle [rad] from the file's x axis to the membrane's x axis, towards file y.
        flip_y: the file frame is mirrored with respect to the membrane frame (y down).
    """
    c, s = math.cos(rotation), math.sin(rotation)
    return np.array([[c, s], [s, -c]] if flip_y else [[c, s], [-s, c]])


def to_membrane_frame(
    xy: np.ndarray, strain: np.ndarray, centre, scale: float, rotation: float, flip_y: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 2) [file units] and strains (n, 3) [xx, yy, xy] into the membrane frame.

    x' = Q scale (x - centre) [mm] and E' = Q E Q^T, Q = :func:`frame_matrix` (rotation [rad]).
    """
    q = frame_matrix(rotation, flip_y)
    points = scale * (xy - np.asarray(centre, dtype=float)) @ q.T
    tensors = np.stack([np.stack([strain[:, 0], strain[:, 2]], -1), np.stack([strain[:, 2], strain[:, 1]], -1)], -2)
    rotated = q @ tensors @ q.T
    return points, np.column_stack([rotated[:, 0, 0], rotated[:, 1, 1], rotated[:, 0, 1]])


def _resolve_strain(table: DicTable, settings: ImportSettings) -> tuple[str, bool, list[str]]:
    """(measure, percent, notes) from the file and the user; a contradiction is an error."""
    notes = []
    if table.measure_source == "stated" and settings.strain and settings.strain != table.measure:
        _fail(table.path, None, f"the file states {table.measure} strain; --strain {settings.strain} contradicts it")
    measure = settings.strain or table.measure
    if measure is None:
        _fail(table.path, None, f"{table.measure_source}: give --strain {'|'.join(STRAIN_MEASURES)}")
    if settings.strain is None and table.measure_source != "stated":
        notes.append(table.measure_source)
    if table.percent is False and settings.percent:
        _fail(table.path, None, "the file states strains as fractions; --percent contradicts it")
    if table.percent is None and not settings.percent:
        notes.append("strain unit not stated: read as fractions (the plausibility check tests it)")
    return measure, bool(table.percent or settings.percent), notes


def _resolve_scale(table: DicTable, settings: ImportSettings) -> tuple[float, list[str]]:
    """(mm per file unit, notes): pixels need --mm-per-px; metric files refuse it."""
    unit = table.length_unit
    if unit is None:
        unit = "px" if settings.mm_per_px is not None else "mm"
        notes = [f"coordinate unit not stated: read as {unit} (give --units)"]
    else:
        notes = []
    if unit == "px":
        if settings.mm_per_px is None:
            _fail(table.path, None, "coordinates are in pixels: give the image scale with --mm-per-px")
        return settings.mm_per_px, notes
    if settings.mm_per_px is not None:
        _fail(table.path, None, f"coordinates are already in {unit}: drop --mm-per-px")
    return LENGTH_UNITS[unit], notes


def _drop_duplicates(table: DicTable, keep: np.ndarray) -> np.ndarray:
    """``keep`` without repeated points; the same point with different strains is an error."""
    idx = np.flatnonzero(keep)
    _, first, inverse = np.unique(table.xy[idx], axis=0, return_index=True, return_inverse=True)
    for k in np.flatnonzero(np.bincount(inverse.ravel()) > 1):
        rows = idx[inverse.ravel() == k]
        if not np.all(table.strain[rows] == table.strain[rows[0]]):
            x, y = table.xy[rows[0]]
            _fail(
                table.path,
                None,
                f"point ({x:g}, {y:g}) appears on lines {table.lines[rows[0]]} and "
                f"{table.lines[rows[1]]} with different strains",
            )
    out = np.zeros_like(keep)
    out[idx[np.sort(first)]] = True
    return out


def _check_spread(path: Path, xy: np.ndarray, n_outside: int, block_half: float) -> None:
    """At least MIN_POINTS points, not all on one line."""
    if len(xy) < MIN_POINTS:
        _fail(
            path,
            None,
            f"only {len(xy)} usable points inside the model block (|x|, |y| <= {block_half:g} mm; "
            f"{n_outside} outside: check --centre and --mm-per-px); need at least {MIN_POINTS}",
        )
    s = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        _fail(
            path, None, f"the {len(xy)} points lie on one line: a strain map needs a 2-D field (a line-slice export?)"
        )


def convert(table: DicTable, settings: ImportSettings) -> DicField:
    """Mask, scale, move and rotate into the membrane frame, convert to log strain, crop.

    Points outside the model block (|x| or |y| > ``settings.block_half``) are dropped.
    """
    measure, percent, notes = _resolve_strain(table, settings)
    scale, scale_notes = _resolve_scale(table, settings)
    finite = np.all(np.isfinite(table.xy), axis=1) & np.all(np.isfinite(table.strain), axis=1)
    valid = table.valid & finite
    keep = _drop_duplicates(table, valid)
    strain = table.strain[keep] / (100.0 if percent else 1.0)
    try:
        log = to_log_strain(strain[:, 0], strain[:, 1], strain[:, 2], measure)
    except ValueError as exc:
        _fail(table.path, None, f"{exc} (are the strains in percent? give --percent)")
    xy, log = to_membrane_frame(
        table.xy[keep], log, settings.centre, scale, math.radians(settings.rotation), settings.flip_y
    )
    inside = np.max(np.abs(xy), axis=1) <= settings.block_half
    _check_spread(table.path, xy[inside], int((~inside).sum()), settings.block_half)
    return DicField(
        table.path,
        table.format,
        xy[inside],
        log[inside],
        len(table.xy),
        int((~valid).sum()),
        int((~inside).sum()),
        table.notes + notes + scale_notes,
    )


def load_dic(path: Path | str, settings: ImportSettings) -> DicField:
    """Read and convert a DIC export: the field in the membrane frame, log strain, mm."""
    settings.validate()
    return convert(read_dic(path, settings), settings)


def save_measurement(measurement: Measurement, out: Path | str, block_half: float) -> Path:
    """Write a measurement CSV (design.md §4) under a temporary name, read it back with
    ``read_measurement`` (points within ``block_half`` mm), then rename it to ``out``."""
    out = Path(out)
    if out.parent.exists() and not out.parent.is_dir():
        raise MeasurementError(f"cannot write '{out}': '{out.parent}' is not a directory")
    m = measurement

    def write_and_check(tmp: Path) -> None:
        write_measurement(tmp, m.xy, m.strain, m.alpha, m.t, m.sd)
        read_measurement(tmp, block_half)

    try:
        return write_atomically(out, write_and_check)
    except OSError as exc:
        raise MeasurementError(f"cannot write '{out}': {exc.strerror or exc}") from None


# ---------------------------------------------------------------- plausibility


def _frobenius(a: np.ndarray, b: np.ndarray) -> float:
    """Inner product of two in-plane tensors given as (xx, yy, xy)."""
    return float(a[0] * b[0] + a[1] * b[1] + 2 * a[2] * b[2])


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    norm = math.sqrt(_frobenius(a, a) * _frobenius(b, b))
    return _frobenius(a, b) / norm if norm > 0 else 0.0


def assess_plausibility(xy: np.ndarray, strain: np.ndarray, alpha, t: float, membrane_half: float) -> Plausibility:
    """Compare the mean log strain of the points under the membrane (|x|, |y| <= membrane_half)
    with the membrane's imposed log strain ln(1 + t alpha); see :func:`likely_cause`."""
    under = np.max(np.abs(xy), axis=1) <= membrane_half
    imposed = np.array([math.log1p(t * alpha[0]), math.log1p(t * alpha[1]), 0.0])
    measured = strain[under].mean(axis=0) if under.any() else np.full(3, np.nan)
    if math.sqrt(_frobenius(imposed, imposed)) < IMPOSED_FLOOR:
        return Plausibility(int(under.sum()), measured, imposed, math.nan, math.nan, None)
    if not under.any():
        problem = (
            f"no measured point lies under the membrane (|x|, |y| <= {membrane_half:g} mm in the membrane "
            "frame): check --centre and --mm-per-px"
        )
        return Plausibility(0, measured, imposed, math.nan, math.nan, problem)
    ratio = math.sqrt(_frobenius(measured, measured) / _frobenius(imposed, imposed))
    cosine = _cosine(measured, imposed)
    problem = likely_cause(measured, imposed, ratio, cosine)
    return Plausibility(int(under.sum()), measured, imposed, ratio, cosine, problem)


def likely_cause(measured: np.ndarray, imposed: np.ndarray, ratio: float, cosine: float) -> str | None:
    """One line naming the likely cause of a mismatch, or None when plausible.

    Scale: ``ratio`` outside :data:`RATIO_RANGE` (percent read as fraction gives ~100).
    Direction: ``cosine`` below :data:`COS_MIN`; then x/y swapped (the field turned by 90°
    matches) and a flipped sign (the negated field matches) are named.
    """
    m, e = measured, imposed
    what = f"the mean log strain under the membrane (xx {m[0]:.3g}, yy {m[1]:.3g}, xy {m[2]:.2g})"
    design = f"the design's ln(1 + t·α) (xx {e[0]:.3g}, yy {e[1]:.3g})"
    if ratio > RATIO_RANGE[1]:
        return f"{what} is {ratio:.3g}x {design}: strains in percent read as fractions? (add --percent)"
    if ratio < RATIO_RANGE[0]:
        return f"{what} is {ratio:.2g}x {design}: fractions read as percent (drop --percent), or a wrong --alpha/--t?"
    if cosine >= COS_MIN:
        return None
    causes = []
    if _cosine(np.array([m[1], m[0], -m[2]]), e) >= COS_MIN:
        causes.append("x and y swapped (--rotation off by 90°?)")
    if -cosine >= COS_MIN:
        causes.append("the sign flipped (wrong --alpha sign?)")
    cause = " or ".join(causes) if causes else "check --alpha, --rotation and --centre"
    return f"{what} does not match {design} (cosine {cosine:.2f} < {COS_MIN}): {cause}"


# ---------------------------------------------------------------- figure
