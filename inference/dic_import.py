"""Import DIC exports as skinid measurements (design.md §4; docs/measurements.md).

Pipeline: a reader (:mod:`inference.dic_readers`) turns a file into a :class:`DicTable` (file
frame, file units, the file's strain measure, a missing-point mask); :func:`convert` masks,
scales (px -> mm), moves and rotates points and tensors into the membrane frame, converts the
strain to log strain and drops points outside the model block, giving a :class:`DicField`;
:func:`assess_plausibility` compares the mean strain under the membrane with the design's
imposed strain. Units: mm; angles in degrees in :class:`ImportSettings` (the user's input),
radians inside the functions that take ``rotation``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inference.dic_readers import FORMATS, LENGTH_UNITS, MIN_POINTS, DicTable, TableOptions, fail, read_dic
from inference.observations import (
    STRAIN_MEASURES,
    Measurement,
    MeasurementError,
    load_fraction_problem,
    read_measurement,
    to_log_strain,
    write_measurement,
)
from skinfem.outputs import write_atomically

# Plausibility tolerances (docs/measurements.md "The plausibility check").
RATIO_RANGE = (0.05, 5.0)  # |mean measured| / |imposed|; FE `small` sweep: 1.000 (surface), 0.23 .. 1.08 (cell average)
COS_MIN = 0.8  # cosine of the angle between them; FE `small` sweep: 1.000 (surface), >= 0.92 (cell average)
IMPOSED_FLOOR = 1e-4  # designs imposing less log strain than this are not checked


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
        if problem := load_fraction_problem(t):
            raise MeasurementError(problem)
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
        fail(table.path, None, f"the file states {table.measure} strain; --strain {settings.strain} contradicts it")
    measure = settings.strain or table.measure
    if measure is None:
        fail(table.path, None, f"{table.measure_source}: give --strain {'|'.join(STRAIN_MEASURES)}")
    if settings.strain is None and table.measure_source != "stated":
        notes.append(table.measure_source)
    if table.percent is False and settings.percent:
        fail(table.path, None, "the file states strains as fractions; --percent contradicts it")
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
            fail(table.path, None, "coordinates are in pixels: give the image scale with --mm-per-px")
        return settings.mm_per_px, notes
    if settings.mm_per_px is not None:
        fail(table.path, None, f"coordinates are already in {unit}: drop --mm-per-px")
    return LENGTH_UNITS[unit], notes


def _drop_duplicates(table: DicTable, keep: np.ndarray) -> np.ndarray:
    """``keep`` without repeated points; the same point with different strains is an error."""
    idx = np.flatnonzero(keep)
    _, first, inverse = np.unique(table.xy[idx], axis=0, return_index=True, return_inverse=True)
    for k in np.flatnonzero(np.bincount(inverse.ravel()) > 1):
        rows = idx[inverse.ravel() == k]
        if not np.all(table.strain[rows] == table.strain[rows[0]]):
            x, y = table.xy[rows[0]]
            fail(
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
        fail(
            path,
            None,
            f"only {len(xy)} usable points inside the model block (|x|, |y| <= {block_half:g} mm; "
            f"{n_outside} outside: check --centre and --mm-per-px); need at least {MIN_POINTS}",
        )
    s = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        fail(path, None, f"the {len(xy)} points lie on one line: a strain map needs a 2-D field (a line-slice export?)")


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
        fail(table.path, None, f"{exc} (are the strains in percent? give --percent)")
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
    return convert(read_dic(path, settings.format, settings.table), settings)


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
