"""Observations: measured (or simulated) strain fields on the model's skin cells.

Sources:
- a dataset: :func:`from_dataset` (material index, designs, frames);
- measurement CSV files (design.md §4), one per (design, frame): :func:`read_measurement`,
  then :func:`map_to_cells`.

Mapping a measurement onto the skin cells: piecewise-linear interpolation on the Delaunay
triangulation of the measured points (``scipy.interpolate.LinearNDInterpolator``), evaluated
at the cell centroids. Cells outside the convex hull of the points, or farther than
``max_gap`` mm from the nearest point, get no value: they are masked out of the projection on
the PC basis (a masked least-squares fit), never zero-filled.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree

from skinfem.io import STATUS_OK, StrainDataset
from skinfem.params import Design

if TYPE_CHECKING:
    from inference.criticism.metrics import MembraneRegions

STRAIN_MEASURES = ("log", "green", "engineering")
COLUMNS = ("x", "y", "exx", "eyy", "exy")
SD_COLUMNS = ("sd_exx", "sd_eyy", "sd_exy")
HEADER = "# skinid-measurement v1"


class MeasurementError(ValueError):
    """A measurement file is malformed; the message names the file, line and problem."""


def load_fraction_problem(t: float) -> str | None:
    """Why ``t`` is not a load fraction (the share of the design's eigen-strain applied, in (0, 1]), or None."""
    if np.isfinite(t) and 0 < t <= 1:
        return None
    return f"t = {t} must be in (0, 1]"


@dataclass
class Observation:
    """One strain field on the skin cells for one membrane design and load fraction.

    Attributes:
        alpha: (2,) membrane eigen-strain (alpha11, alpha22).
        t: load fraction in (0, 1].
        fields: (n_cells, 3) log strain xx, yy, xy (NaN where masked).
        mask: (n_cells,) True where the cell has data.
        sd: (3,) or None: stated measurement standard deviation per component [strain].
        truth: (5,) or None: the parameters that generated it (theta in degrees), if known.
        source: where it came from (for reports).
    """

    alpha: np.ndarray
    t: float
    fields: np.ndarray
    mask: np.ndarray
    sd: np.ndarray | None = None
    truth: np.ndarray | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)


def from_dataset(
    data: StrainDataset, material: int, designs: list[int] | None = None, frames: list[int] | None = None
) -> list[Observation]:
    """Observations of one material of a dataset: every (design, frame) pair asked for.

    Defaults: every design, last frame. Negative frame indices count from the end.
    """
    n_mat, n_des, n_frames, _ = data.shape
    if not 0 <= material < n_mat:
        raise ValueError(f"material {material} is not in [0, {n_mat}) of {data.path}")
    designs = list(range(n_des)) if designs is None else designs
    frames = [-1] if frames is None else frames
    out = []
    for j in designs:
        if not -n_des <= j < n_des:
            raise ValueError(f"design {j} is not in [0, {n_des}) of {data.path}")
        if data.status[material, j] != STATUS_OK:
            raise ValueError(f"simulation (material {material}, design {j}) did not converge in {data.path}")
        strain = data.strain(material, j)
        for k in frames:
            if not -n_frames <= k < n_frames:
                raise ValueError(f"frame {k} is not in [0, {n_frames}) of {data.path}")
            out.append(
                Observation(
                    alpha=data.designs[j].copy(),
                    t=float(data.t[k]),
                    fields=strain[k].astype(float),
                    mask=np.ones(len(data.xy), dtype=bool),
                    truth=data.params[material].copy(),
                    source=f"{data.path.name}: material {material}, design {j}, frame {k % n_frames}",
                )
            )
    return out


def to_log_strain(exx: np.ndarray, eyy: np.ndarray, exy: np.ndarray, measure: str) -> np.ndarray:
    """Convert in-plane strains (tensor shear) of a measure to log strain; (n, 3).

    ``green``: E = (C - I)/2, so ln U = ln(C)/2 with C = I + 2E. ``engineering``: the Biot
    strain U - I, so ln U = ln(I + e). Both use the in-plane 2x2 tensor.
    """
    if measure == "log":
        return np.column_stack([exx, eyy, exy])
    tensors = np.stack([np.stack([exx, exy], -1), np.stack([exy, eyy], -1)], -2)
    eye = np.eye(2)
    stretch = eye + 2 * tensors if measure == "green" else eye + tensors
    power = 0.5 if measure == "green" else 1.0
    w, v = np.linalg.eigh(stretch)
    if np.any(w <= 0):
        raise ValueError(f"{measure} strains with a non-positive stretch cannot be converted")
    log = np.einsum("nij,nj,nkj->nik", v, power * np.log(w), v)
    return np.column_stack([log[:, 0, 0], log[:, 1, 1], log[:, 0, 1]])


@dataclass
class Measurement:
    """A parsed measurement file: points (n, 2) [mm], log strains (n, 3), optional sd (n, 3)."""

    path: Path
    alpha: np.ndarray
    t: float
    xy: np.ndarray
    strain: np.ndarray
    sd: np.ndarray | None


def read_measurement(path: Path | str, half_length: float | None = None) -> Measurement:
    """Read and check a measurement CSV (design.md §4); strains converted to log strain.

    A UTF-8 byte-order mark is ignored. Refused, besides a malformed file: a header design that
    is not a valid membrane design (finite, |alpha| < 0.5), a point given twice with other
    values, and points that all lie on one line.

    Args:
        half_length: if given, points with |x| or |y| above it (outside the block) are refused.

    Raises:
        MeasurementError: naming the file, the line and the problem.
    """
    path = Path(path)
    lines = _read_lines(path)

    def fail(lineno: int, problem: str):
        raise MeasurementError(f"{path}:{lineno}: {problem}")

    alpha, t, measure, lineno = _read_header(lines, fail)
    rows, numbers = _read_rows(lines, lineno, half_length, fail)
    _check_points(rows, numbers, fail)
    try:
        strain = to_log_strain(rows[:, 2], rows[:, 3], rows[:, 4], measure)
    except ValueError as exc:
        raise MeasurementError(f"{path}: {exc} (strains in percent? the file must hold fractions)") from None
    return Measurement(path, alpha, t, rows[:, :2], strain, rows[:, 5:8] if rows.shape[1] > 5 else None)


def _read_lines(path: Path) -> list[str]:
    """The file's lines (a BOM, as spreadsheet exports write, is dropped)."""
    if path.is_dir():
        raise MeasurementError(f"measurement file '{path}' is a folder")
    if not path.is_file():
        raise MeasurementError(f"measurement file '{path}' does not exist")
    try:
        return path.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError:
        raise MeasurementError(f"measurement file '{path}' is not UTF-8 text (a CSV file)") from None


def _read_header(lines: list[str], fail) -> tuple[np.ndarray, float, str, int]:
    """(alpha (2,), t, strain measure, line number of the column names) from the comment header."""
    if not lines or lines[0].strip() != HEADER:
        fail(1, f"first line must be '{HEADER}'")
    meta, lineno = {}, 1
    for lineno, line in enumerate(lines[1:], start=2):
        if not line.startswith("#"):
            break
        m = re.match(r"#\s*(\w+)\s*=\s*([^\s#]+)", line)
        if m:
            meta[m.group(1)] = m.group(2)
    for key in ("alpha11", "alpha22", "t"):
        if key not in meta:
            fail(lineno, f"header line '# {key} = ...' is missing")
    try:
        alpha = np.array([float(meta["alpha11"]), float(meta["alpha22"])])
        t = float(meta["t"])
    except ValueError as exc:
        fail(lineno, f"bad header value ({exc})")
    try:
        Design(*alpha)
    except ValueError as exc:
        fail(lineno, f"bad design in the header: {exc}")
    if problem := load_fraction_problem(t):
        fail(lineno, problem)
    measure = meta.get("strain", "log")
    if measure not in STRAIN_MEASURES:
        fail(lineno, f"unknown strain measure '{measure}' (use one of {', '.join(STRAIN_MEASURES)})")
    return alpha, t, measure, lineno


def _read_rows(lines: list[str], lineno: int, half_length: float | None, fail) -> tuple[np.ndarray, list[int]]:
    """Data rows (n, 5) x, y, exx, eyy, exy [+ sd_exx, sd_eyy, sd_exy: (n, 8)] after the column
    names on line ``lineno``, and their line numbers."""
    columns = [c.strip() for c in lines[lineno - 1].split(",")]
    missing = [c for c in COLUMNS if c not in columns]
    if missing:
        fail(lineno, f"column(s) {', '.join(missing)} missing; need {','.join(COLUMNS)}[,{','.join(SD_COLUMNS)}]")
    has_sd = all(c in columns for c in SD_COLUMNS)
    idx = [columns.index(c) for c in list(COLUMNS) + (list(SD_COLUMNS) if has_sd else [])]
    rows, numbers = [], []
    for n, line in enumerate(lines[lineno:], start=lineno + 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split(",")
        if len(parts) != len(columns):
            fail(n, f"expected {len(columns)} values, found {len(parts)}")
        try:
            values = [float(parts[i]) for i in idx]
        except ValueError:
            fail(n, "a value is not a number")
        if not np.all(np.isfinite(values)):
            fail(n, "NaN or infinite value")
        if half_length is not None and max(abs(values[0]), abs(values[1])) > half_length:
            fail(n, f"point ({values[0]}, {values[1]}) mm lies outside the block |x|, |y| <= {half_length}")
        if has_sd and min(values[5:]) <= 0:
            fail(n, "standard deviations must be > 0")
        rows.append(values)
        numbers.append(n)
    if len(rows) < 3:
        fail(len(lines), f"only {len(rows)} data rows; need at least 3")
    return np.array(rows), numbers


def _check_points(rows: np.ndarray, numbers: list[int], fail) -> None:
    """Refuse a point given twice with different values, and points that all lie on one line."""
    _, first, inverse = np.unique(rows[:, :2], axis=0, return_index=True, return_inverse=True)
    earlier = first[inverse.ravel()]  # the first row of each row's point
    conflicts = np.flatnonzero(np.any(rows != rows[earlier], axis=1))
    if len(conflicts):
        k = conflicts[0]
        fail(
            numbers[k],
            f"point ({rows[k, 0]:g}, {rows[k, 1]:g}) is also on line {numbers[earlier[k]]}, with other values",
        )
    s = np.linalg.svd(rows[:, :2] - rows[:, :2].mean(axis=0), compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        fail(numbers[-1], f"the {len(rows)} points lie on one line: a strain map needs a 2-D field")


def write_measurement(
    path: Path | str, xy: np.ndarray, strain: np.ndarray, alpha, t: float, sd: np.ndarray | None = None
) -> Path:
    """Write log strains at points as a measurement CSV (the format DIC exports are converted to)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = [HEADER, f"# alpha11 = {alpha[0]}", f"# alpha22 = {alpha[1]}", f"# t = {t}", "# strain = log"]
    cols = list(COLUMNS) + (list(SD_COLUMNS) if sd is not None else [])
    table = np.column_stack([xy, strain] + ([sd] if sd is not None else []))
    body = "\n".join(",".join(f"{v:.9g}" for v in row) for row in table)
    path.write_text("\n".join(header) + "\n" + ",".join(cols) + "\n" + body + "\n")
    return path


def map_to_cells(measurement: Measurement, cells_xy: np.ndarray, max_gap: float = 2.0) -> Observation:
    """Interpolate a measurement onto cell centroids (n_cells, 2); cells without data masked."""
    interp = LinearNDInterpolator(measurement.xy, measurement.strain)
    values = interp(cells_xy)
    gap, _ = cKDTree(measurement.xy).query(cells_xy)
    mask = np.all(np.isfinite(values), axis=1) & (gap <= max_gap)
    if mask.sum() < 10:
        raise MeasurementError(f"{measurement.path}: only {mask.sum()} skin cells lie inside the measured region")
    values[~mask] = np.nan
    sd = None if measurement.sd is None else np.median(measurement.sd, axis=0)
    return Observation(
        alpha=measurement.alpha,
        t=measurement.t,
        fields=values,
        mask=mask,
        sd=sd,
        source=str(measurement.path),
    )


def thinned(xy: np.ndarray, spacing: float) -> np.ndarray:
    """Indices (m,), ascending, of the points of ``xy`` (n, 2) [mm] that :func:`thin` keeps: the
    first in each square of side ``spacing`` [mm]."""
    cells = np.floor(xy / spacing).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def thin(measurement: Measurement, spacing: float) -> Measurement:
    """Keep one point (the first) per square of side ``spacing`` [mm]: DIC points closer than
    the strain window carry little independent information, and the check's cost grows with
    the point count (dense noise covariances)."""
    keep = thinned(measurement.xy, spacing)
    sd = None if measurement.sd is None else measurement.sd[keep]
    return Measurement(
        measurement.path, measurement.alpha, measurement.t, measurement.xy[keep], measurement.strain[keep], sd
    )


def check_field_of_view(measurement: Measurement, membrane: MembraneRegions, n_params: int) -> None:
    """Refuse a measurement the check cannot use: too few points, or no point of ``membrane``'s
    edge strip in view.

    Raises:
        MeasurementError: naming the file and the problem.
    """
    if len(measurement.xy) <= n_params:
        raise MeasurementError(
            f"{measurement.path}: {len(measurement.xy)} measured points are not more than the "
            f"{n_params} parameters the check calibrates"
        )
    ring = np.max(np.abs(measurement.xy), axis=1)
    if not np.any(np.abs(ring - membrane.half) <= membrane.band):
        lo, hi = measurement.xy.min(axis=0), measurement.xy.max(axis=0)
        raise MeasurementError(
            f"{measurement.path}: the field of view (x {lo[0]:.3g}..{hi[0]:.3g}, y {lo[1]:.3g}..{hi[1]:.3g} mm) "
            f"contains no membrane edge (|x| or |y| = {membrane.half:g} mm): the check needs the edges"
        )
