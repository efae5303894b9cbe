"""Write the DIC export fixtures of tests/test_dic_import.py from a known analytic field.

    .venv/bin/python tests/data/dic/make_fixtures.py      # rewrites the files next to it

The truth is a log-strain field in the membrane frame (:func:`log_strain`): the design's
ln(1 + t alpha) under the membrane (|x|, |y| <= 10 mm), decaying outside, plus small odd terms
and a shear so that a wrong rotation, mirror or scale shows. Each fixture places grid points
in its own file frame (:class:`Frame`: membrane centre in file units, rotation in degrees from
the file's x axis to the membrane's x axis, mm per px, y down), turns the tensor into that
frame, converts it to the file's strain measure with matrix exponentials (independent of
``inference.observations.to_log_strain``) and prints it as the program does. Where each
format detail comes from (sections of /work/shared/reference/dic-formats.md) is said in
README.md here and, where the format allows comments, in the file itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.linalg import expm

HERE = Path(__file__).parent
ALPHA = (0.05, -0.02)
T = 0.8
HALF = 10.0


def log_strain(xy: np.ndarray) -> np.ndarray:
    """(n, 3) log strain xx, yy, xy at membrane-frame points (n, 2) [mm]: the truth."""
    x, y = xy[:, 0], xy[:, 1]
    decay = np.exp(-((np.maximum(np.abs(x) - HALF, 0) / 4) ** 2)) * np.exp(
        -((np.maximum(np.abs(y) - HALF, 0) / 4) ** 2)
    )
    e1, e2 = math.log1p(T * ALPHA[0]), math.log1p(T * ALPHA[1])
    exx = e1 * decay + 0.003 * x / 25
    eyy = e2 * decay + 0.002 * y / 25
    exy = 0.004 * np.sin(np.pi * x / 25) * np.sin(np.pi * (y + 5) / 25)
    return np.column_stack([exx, eyy, exy])


# DaVis 8 fixture: a homogeneous deformation F = R(2°) U with ln U given (membrane frame).
DAVIS8_LOG_U = np.array([[math.log1p(T * ALPHA[0]), 0.003], [0.003, math.log1p(T * ALPHA[1])]])


def davis8_strain(xy: np.ndarray) -> np.ndarray:
    """(n, 3) the DaVis 8 fixture's (homogeneous) log strain."""
    L = DAVIS8_LOG_U
    return np.tile([L[0, 0], L[1, 1], L[0, 1]], (len(xy), 1))


@dataclass(frozen=True)
class Frame:
    """Where the membrane lies in a file's coordinates (the import's --centre/--rotation/...)."""

    centre: tuple[float, float]
    rotation: float  # degrees
    mm_per_px: float | None = None
    flip_y: bool = False

    def axes(self) -> np.ndarray:
        """(2, 2) rows: the membrane's x and y axes written in file coordinates."""
        a = math.radians(self.rotation)
        x_axis = np.array([math.cos(a), math.sin(a)])
        y_axis = np.array([-math.sin(a), math.cos(a)]) * (-1 if self.flip_y else 1)
        return np.array([x_axis, y_axis])

    def to_membrane(self, p: np.ndarray) -> np.ndarray:
        """File points (n, 2) -> membrane-frame points [mm]."""
        return (self.mm_per_px or 1.0) * (p - np.array(self.centre)) @ self.axes().T

    def to_file(self, log: np.ndarray) -> np.ndarray:
        """Membrane-frame tensors (n, 3) -> (n, 2, 2) tensors in the file frame."""
        q = self.axes()
        m = np.stack([np.stack([log[:, 0], log[:, 2]], -1), np.stack([log[:, 2], log[:, 1]], -1)], -2)
        return np.einsum("ki,nkl,lj->nij", q, m, q)

    def options(self) -> list[str]:
        """The import command-line options of this frame."""
        out = ["--centre", repr(self.centre[0]), repr(self.centre[1]), "--rotation", repr(self.rotation)]
        out += ["--mm-per-px", repr(self.mm_per_px)] if self.mm_per_px else []
        return out + (["--flip-y"] if self.flip_y else [])


@dataclass(frozen=True)
class Fixture:
    """One fixture file: its frame, the import options it needs, and which of its points are missing."""

    name: str
    format: str
    frame: Frame
    extra: tuple[str, ...] = ()  # further import options (strain measure, percent, ...)
    missing: tuple[int, ...] = ()  # indices (in grid order) written as missing
    omitted: tuple[int, ...] = ()  # indices not written at all (masked points in DaVis 10)
    truth: str = "field"  # "field" (log_strain) or "davis8" (davis8_strain)

    def grid(self) -> np.ndarray:
        """(n, 2) the file-frame points, in file order."""
        return GRIDS[self.name]()

    def expected(self) -> tuple[np.ndarray, np.ndarray]:
        """Membrane-frame points [mm] and log strains of the valid points in file order."""
        keep = [i for i in range(len(self.grid())) if i not in self.missing and i not in self.omitted]
        xy = self.frame.to_membrane(self.grid()[keep])
        return xy, (log_strain if self.truth == "field" else davis8_strain)(xy)


def _grid(x0: float, y0: float, step: float, nx: int, ny: int) -> np.ndarray:
    """Points on a regular grid, x varying fastest."""
    xs, ys = x0 + step * np.arange(nx), y0 + step * np.arange(ny)
    return np.array([(x, y) for y in ys for x in xs], dtype=float)


GRIDS = {
    "vic3d_classic.csv": lambda: _grid(3 - 21, -2 - 21, 7, 7, 7),
    "vic2d_classic.csv": lambda: _grid(612 - 300, 488 - 300, 100, 7, 7),
    "vic9_extract.csv": lambda: _grid(-1.5 - 14, 2 - 14, 4, 8, 8),
    "davis8_vectors.txt": lambda: _grid(6, 6, 12, 8, 7),
    "davis10.csv": lambda: _grid(1 - 16, 0.5 - 16, 4, 9, 9),
    "davis10_gl.csv": lambda: _grid(-10, -10, 4, 6, 6),
    "DICe_solution_12.txt": lambda: _grid(1024 - 375, 768 - 375, 125, 7, 7),
    "table_decimal_comma.csv": lambda: _grid(0.5 - 15, 0.5 - 15, 5, 7, 7),
    "table_percent.txt": lambda: _grid(-12, -12, 4, 7, 7),
}

FIXTURES = {
    f.name: f
    for f in [
        Fixture("vic3d_classic.csv", "vic", Frame((3.0, -2.0), 30.0), missing=(0, 17, 30)),
        Fixture("vic2d_classic.csv", "vic", Frame((612.0, 488.0), -20.0, 0.05, True), missing=(5, 40)),
        Fixture("vic9_extract.csv", "vic9", Frame((-1.5, 2.0), 0.0), missing=(9,)),
        Fixture("davis8_vectors.txt", "davis8", Frame((48.0, 42.0), 0.0, 0.25), truth="davis8"),
        Fixture("davis10.csv", "davis10", Frame((1.0, 0.5), 15.0), omitted=(0, 1, 9, 40, 79, 80)),
        Fixture("davis10_gl.csv", "davis10", Frame((0.0, 0.0), -45.0)),
        Fixture("DICe_solution_12.txt", "dice", Frame((1024.0, 768.0), 10.0, 0.04, True), missing=(3, 24, 47)),
        Fixture(
            "table_decimal_comma.csv",
            "table",
            Frame((0.5, 0.5), -30.0),
            ("--strain", "engineering", "--percent"),
            missing=(2, 33),
        ),
        Fixture("table_percent.txt", "table", Frame((0.0, 0.0), 0.0), ("--percent",)),
    ]
}


def green(m: np.ndarray) -> np.ndarray:
    """(n, 2, 2) log strain -> Green-Lagrange strain (exp(2L) - I) / 2."""
    return np.array([(expm(2 * a) - np.eye(2)) / 2 for a in m])


def biot(m: np.ndarray) -> np.ndarray:
    """(n, 2, 2) log strain -> engineering (Biot) strain exp(L) - I."""
    return np.array([expm(a) - np.eye(2) for a in m])


def _file_tensors(fx: Fixture, convert) -> np.ndarray:
    """(n, 3) xx, yy, xy of the file's strain at every grid point."""
    xy = fx.frame.to_membrane(fx.grid())
    m = convert(fx.frame.to_file(log_strain(xy)))
    return np.column_stack([m[:, 0, 0], m[:, 1, 1], m[:, 0, 1]])


def _principal(e: np.ndarray) -> tuple[float, float, float]:
    """Principal strains e1 >= e2 and the angle [rad] of e1 (VIC's e1, e2, gamma)."""
    w, v = np.linalg.eigh(np.array([[e[0], e[2]], [e[2], e[1]]]))
    return w[1], w[0], math.atan2(v[1, 1], v[0, 1])


def _g(v: float) -> str:
    return f"{v:g}"


def vic3d(fx: Fixture) -> str:
    """VIC-3D classic: leading space, quoted names joined by comma + two spaces; %g data;
    missing rows keep x, y (px) with sigma = -1 and every other field 0."""
    names = ["X", "Y", "Z", "U", "V", "W", "exx", "eyy", "exy", "e1", "e2", "gamma", "sigma", "x", "y", "u", "v"]
    lines = [" " + ",  ".join(f'"{n}"' for n in names)]
    strain = _file_tensors(fx, green)
    for i, ((X, Y), e) in enumerate(zip(fx.grid(), strain)):
        px, py = 1224 + 25 * X, 1024 + 25 * Y
        if i in fx.missing:
            row = [0] * 12 + [-1, px, py, 0, 0]
        else:
            U, V = e[0] * (X - 3) + e[2] * (Y + 2), e[2] * (X - 3) + e[1] * (Y + 2)
            row = [X, Y, 0.002 * (X * X + Y * Y), U, V, 0.01, *e, *_principal(e), 0.0123, px, py, 25 * U, 25 * V]
        lines.append(",".join(_g(v) for v in row))
    return "\n".join(lines) + "\n"


def vic2d(fx: Fixture) -> str:
    """VIC-2D classic: the VIC-3D conventions with x, y, u, v in px."""
    names = ["x", "y", "u", "v", "exx", "eyy", "exy", "e1", "e2", "gamma", "sigma"]
    lines = [" " + ",  ".join(f'"{n}"' for n in names)]
    strain = _file_tensors(fx, green)
    for i, ((x, y), e) in enumerate(zip(fx.grid(), strain)):
        if i in fx.missing:
            row = [x, y] + [0] * 8 + [-1]
        else:
            row = [x, y, e[0] * (x - 612), e[1] * (y - 488), *e, *_principal(e), 0.0231]
        lines.append(",".join(_g(v) for v in row))
    return "\n".join(lines) + "\n"


def vic9(fx: Fixture) -> str:
    """VIC 9+ extract: UTF-8 BOM, an image-name line, quoted names with units and tensor, no spaces."""
    names = [
        "Index [1]",
        "X [mm]",
        "Y [mm]",
        "Z [mm]",
        "U [mm]",
        "V [mm]",
        "W [mm]",
        "exx [1] - Lagrange",
        "eyy [1] - Lagrange",
        "exy [1] - Lagrange",
        "sigma [pixel]",
    ]
    lines = ['"fixture-00000012_0"', ",".join(f'"{n}"' for n in names)]
    strain = _file_tensors(fx, green)
    for i, ((X, Y), e) in enumerate(zip(fx.grid(), strain)):
        row = [i, *([0] * 9), -1] if i in fx.missing else [i, X, Y, 0.0, e[0] * X, e[1] * Y, 0.0, *e, 0.0187]
        lines.append(",".join(_g(v) for v in row))
    return "\ufeff" + "\n".join(lines) + "\n"


def davis8(fx: Fixture) -> str:
    """DaVis 8 2D-vector: the header line, then tab-separated x y u v (px), x fastest."""
    q = fx.frame.axes()
    U = q.T @ expm(DAVIS8_LOG_U) @ q  # the stretch written in the file frame
    a = math.radians(2.0)
    F = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ U
    lines = ['#DaVis 8.4.0 2D-vector 12 7 8 "" "pixel" "" "pixel" "displacement" "pixel"']
    for x, y in fx.grid():
        u, v = (F - np.eye(2)) @ np.array([x - 48, y - 42]) + np.array([1.5, -0.75])
        lines.append(f"{x:g}\t{y:g}\t{u:.4f}\t{v:.4f}")
    return "\n".join(lines) + "\n"


def davis10(fx: Fixture) -> bytes:
    """DaVis 10 CSV: ';', Latin-1 (° is byte 0xB0), units in brackets, [S] = strain; masked
    points not written. Linear strain (DaVis) written as exp(L) - I; GL names for the GL file."""
    gl = fx.name.endswith("_gl.csv")
    if gl:
        names = [
            "x [mm]",
            "y [mm]",
            "Transverse strain Exx - GL[S]",
            "Longitudinal strain Eyy - GL[S]",
            "Shear strain Exy - GL[S]",
            "Maximum shear angle [°]",
        ]
    else:
        names = [
            "x [mm]",
            "y [mm]",
            "z [mm]",
            "X-displacement [mm]",
            "Y-displacement [mm]",
            "Z-displacement [mm]",
            "Exx [S]",
            "Eyy [S]",
            "Exy [S]",
            "Maximum shear angle [°]",
            "Max. normal strain [S]",
        ]
    strain = _file_tensors(fx, green if gl else biot)
    lines = [";".join(names)]
    for i, ((x, y), e) in enumerate(zip(fx.grid(), strain)):
        if i in fx.omitted:
            continue
        e1, _, angle = _principal(e)
        if gl:
            row = [x, y, *e, math.degrees(angle)]
        else:
            row = [x, y, 0.0, e[0] * x, e[1] * y, 0.0, *e, math.degrees(angle), e1]
        lines.append(";".join(f"{v:.8g}" for v in row))
    return ("\n".join(lines) + "\n").encode("latin-1")


def _e3(v: float) -> str:
    """%.4E with a 3-digit exponent, as old MSVC printf writes it: 3.0000E+001."""
    mantissa, exponent = f"{v:.4E}".split("E")
    return f"{mantissa}E{exponent[0]}{int(exponent[1:]):03d}"


def dice(fx: Fixture) -> str:
    """DICe solution: *** preamble, UPPER_CASE header, %.4E (3-digit exponents on Windows).
    Failed subsets: SIGMA = GAMMA = BETA = -1, a failure STATUS_FLAG, stale displacements and
    strains; one failure (index 24) has only its STATUS_FLAG set (12) and a positive SIGMA."""
    preamble = [
        "***",
        "*** Digital Image Correlation Engine (DICe), (git sha1: fixture) Copyright 2021 National Technology & "
        "Engineering Solutions of Sandia, LLC (NTESS)",
        "***",
        "*** fixture of skinid tests/test_dic_import.py (tests/data/dic/make_fixtures.py); format facts:",
        "*** dic-formats.md 'Sandia DICe': *** preamble, %.4E, 3-digit exponents, SIGMA = -1, STATUS_FLAG",
        "*** Reference image: ./images/ref.tif ",
        "*** Deformed image: ./images/def_12.tif ",
        "*** DIC method : local ",
        "*** Subset size: 31",
        "*** Step size: x 125 y 125 (-1 implies not regular grid)",
        "*** Strain window size in pixels: 125 (only first strain post-processor is reported)",
        "*** Coordinates given with (0,0) as upper left corner of image, x positive right, y positive down",
        "***",
    ]
    names = [
        "SUBSET_ID",
        "COORDINATE_X",
        "COORDINATE_Y",
        "DISPLACEMENT_X",
        "DISPLACEMENT_Y",
        "SIGMA",
        "GAMMA",
        "BETA",
        "STATUS_FLAG",
        "UNCERTAINTY",
        "VSG_STRAIN_XX",
        "VSG_STRAIN_YY",
        "VSG_STRAIN_XY",
    ]
    strain = _file_tensors(fx, green)
    lines = preamble + [",".join(names)]
    for i, ((x, y), e) in enumerate(zip(fx.grid(), strain)):
        u, v = e[0] * (x - 1024), e[1] * (y - 768)
        if i == 24:
            row = [x, y, u, v, 0.011, 0.02, 0.0, 12, 0.009, 0.2, -0.3, 0.1]
        elif i in fx.missing:
            row = [x, y, 0.5, -0.25, -1, -1, -1, 5 if i == 3 else 11, 0.0, 0.2, -0.3, 0.1]
        else:
            row = [x, y, u, v, 0.0102, 0.031, 0.0, 4, 0.0093, *e]
        lines.append(",".join([str(i)] + [_e3(val) for val in row]))
    return "\n".join(lines) + "\n"


def table(fx: Fixture) -> bytes:
    """A generic export: UTF-8 BOM, CRLF, '#' preamble, ';' with a decimal comma, non-ASCII names
    without units, engineering (Biot) strain in percent, missing points as 'NaN' and empty fields."""
    preamble = [
        "# fixture of skinid tests/test_dic_import.py (tests/data/dic/make_fixtures.py)",
        "# dic-formats.md 'Other systems': ';', decimal comma, CRLF, # preamble, BOM, localised NaN",
        "# Stage 12; units: mm, %",
    ]
    strain = 100 * _file_tensors(fx, biot)
    lines = preamble + ["x;y;εxx;εyy;εxy"]
    for i, ((x, y), e) in enumerate(zip(fx.grid(), strain)):
        cells = [f"{x:g}", f"{y:g}"] + (["NaN", "NaN", ""] if i in fx.missing else [f"{v:.6f}" for v in e])
        lines.append(";".join(c.replace(".", ",") for c in cells))
    return ("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8")


def table_percent(fx: Fixture) -> str:
    """A tab-separated table, coordinates with units, the tensor named (Hencky) but not the
    strain unit: log strain in percent, which only the plausibility check can tell."""
    lines = [
        "# fixture of skinid tests/test_dic_import.py (tests/data/dic/make_fixtures.py)",
        "# dic-formats.md 'Other systems': units in brackets or not at all; strains here in percent",
        "\t".join(["x [mm]", "y [mm]", "exx - Hencky", "eyy - Hencky", "exy - Hencky"]),
    ]
    strain = 100 * _file_tensors(fx, lambda m: m)
    for (x, y), e in zip(fx.grid(), strain):
        lines.append("\t".join([f"{x:g}", f"{y:g}"] + [f"{v:.6f}" for v in e]))
    return "\n".join(lines) + "\n"


WRITERS = {
    "vic3d_classic.csv": vic3d,
    "vic2d_classic.csv": vic2d,
    "vic9_extract.csv": vic9,
    "davis8_vectors.txt": davis8,
    "davis10.csv": davis10,
    "davis10_gl.csv": davis10,
    "DICe_solution_12.txt": dice,
    "table_decimal_comma.csv": table,
    "table_percent.txt": table_percent,
}


def write_all(directory: Path = HERE) -> list[Path]:
    """Write every fixture into ``directory`` (bytes exactly as the exporters would)."""
    paths = []
    for name, fx in FIXTURES.items():
        content = WRITERS[name](fx)
        path = directory / name
        path.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8"))
        paths.append(path)
    return paths


if __name__ == "__main__":
    for p in write_all():
        print(f"wrote {p}")
