"""DIC export import (inference.dic_import, ``skinid measurement``): fast, no FE, no MPI.

The fixtures in tests/data/dic/ are written by tests/data/dic/make_fixtures.py from a known
log-strain field in the membrane frame (file frames shifted, rotated, in px, mirrored; strains
converted to each file's measure with matrix exponentials). Imports must give back the field's
points and log strains to the files' printed precision.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest

from inference.__main__ import main
from inference.dic_import import (
    COS_MIN,
    RATIO_RANGE,
    DicField,
    ImportSettings,
    assess_plausibility,
    load_dic,
)
from inference.dic_readers import TableOptions, detect_format
from inference.observations import MeasurementError, read_measurement
from tests.scripts import load_script

DATA = Path(__file__).parent / "data" / "dic"


MF = load_script(DATA / "make_fixtures.py", "dic_make_fixtures")
FIXTURES = MF.FIXTURES
ALPHA, T = MF.ALPHA, MF.T
# the files' printed precision: %g (6 digits), DICe %.4E, DaVis 8 displacements 0.0001 px over 12 px
TOLERANCE = {"DICe_solution_12.txt": 1e-5, "davis8_vectors.txt": 2e-5}


def settings_for(fx, **changes) -> ImportSettings:
    """The import settings of a fixture (its frame and the options its extra CLI flags state)."""
    f = fx.frame
    settings = ImportSettings(
        format=fx.format,
        mm_per_px=f.mm_per_px,
        centre=f.centre,
        rotation=f.rotation,
        flip_y=f.flip_y,
        strain="engineering" if "engineering" in fx.extra else None,
        percent="--percent" in fx.extra,
    )
    return dataclasses.replace(settings, **changes)


def expected(fx) -> tuple[np.ndarray, np.ndarray]:
    """Membrane-frame points and log strains of the fixture's valid points inside the block."""
    xy, strain = fx.expected()
    inside = np.max(np.abs(xy), axis=1) <= 25.0
    return xy[inside], strain[inside]


def cli(capsys, *args) -> tuple[int, str, str]:
    code = main(["measurement", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out, out.err


def table_file(
    path: Path, xy: np.ndarray, strain: np.ndarray, header: str = "x,y,exx,eyy,exy", encoding: str = "utf-8"
) -> Path:
    """A small generic table (',' delimiter, '.' decimals)."""
    rows = [",".join(f"{v:.10g}" for v in row) for row in np.column_stack([xy, strain])]
    path.write_bytes(("\n".join([header, *rows]) + "\n").encode(encoding))
    return path


GRID = np.array([(x, y) for y in np.linspace(-12, 12, 5) for x in np.linspace(-12, 12, 5)])


# ---------------------------------------------------------------- fixtures and formats


def test_fixtures_are_what_make_fixtures_writes(tmp_path):
    for path in MF.write_all(tmp_path):
        assert path.read_bytes() == (DATA / path.name).read_bytes(), f"{path.name}: rerun make_fixtures.py"


def test_fixtures_follow_the_format_facts():
    vic = (DATA / "vic3d_classic.csv").read_text().splitlines()
    assert vic[0].startswith(' "X",  "Y",  "Z",') and '"' not in vic[1] and " " not in vic[1]
    assert any(line.split(",")[12] == "-1" and set(line.split(",")[:12]) == {"0"} for line in vic)
    vic9 = (DATA / "vic9_extract.csv").read_bytes()
    assert vic9.startswith(b'\xef\xbb\xbf"') and b'"exx [1] - Lagrange"' in vic9 and b'", "' not in vic9
    davis8 = (DATA / "davis8_vectors.txt").read_text().splitlines()
    assert davis8[0].startswith("#DaVis 8.4.0 2D-vector 12 7 8") and davis8[1].count("\t") == 3
    davis10 = (DATA / "davis10.csv").read_bytes()
    assert b"[\xb0]" in davis10 and b"Exx [S]" in davis10 and davis10.count(b";") > 100
    with pytest.raises(UnicodeDecodeError):
        davis10.decode("utf-8")
    dice = (DATA / "DICe_solution_12.txt").read_text()
    assert dice.startswith("***") and re.search(r"\dE[+-]\d{3},", dice) and "-1.0000E+000" in dice
    table = (DATA / "table_decimal_comma.csv").read_bytes()
    assert table.startswith(b"\xef\xbb\xbf#") and b"\r\n" in table and b";-14,5;" in table and b"NaN" in table


@pytest.mark.parametrize("name", [n for n, fx in FIXTURES.items() if fx.format != "table"])
def test_the_format_is_detected_from_the_first_lines(name):
    assert detect_format(DATA / name) == FIXTURES[name].format


@pytest.mark.parametrize("name", [n for n, fx in FIXTURES.items() if fx.format == "table"])
def test_a_generic_table_is_not_guessed(name):
    with pytest.raises(MeasurementError, match="give --format"):
        detect_format(DATA / name)


@pytest.mark.parametrize("name", list(FIXTURES))
def test_each_format_gives_back_the_known_field(name):
    fx = FIXTURES[name]
    field = load_dic(DATA / name, settings_for(fx, format="auto" if fx.format != "table" else "table"))
    xy, strain = expected(fx)
    assert field.format == fx.format and field.n_rows == len(fx.grid()) - len(fx.omitted)
    assert field.n_missing == len(fx.missing)
    np.testing.assert_allclose(field.xy, xy, rtol=0, atol=1e-9)
    np.testing.assert_allclose(field.strain, strain, rtol=0, atol=TOLERANCE.get(name, 1e-6))
    check = assess_plausibility(field.xy, field.strain, ALPHA, T, 10.0)
    assert check.problem is None and abs(check.ratio - 1) < 0.02, check.summary()


def test_points_outside_the_model_block_are_dropped():
    fx = FIXTURES["vic3d_classic.csv"]
    field = load_dic(DATA / fx.name, settings_for(fx))
    all_xy, _ = fx.expected()
    assert field.n_outside == int((np.max(np.abs(all_xy), axis=1) > 25).sum()) > 0
    assert np.max(np.abs(field.xy)) <= 25


# ---------------------------------------------------------------- conversions


@pytest.mark.parametrize("flip", [False, True])
def test_rotation_is_the_tensor_rotation_closed_form(tmp_path, flip):
    e = np.array([0.03, -0.01, 0.005])  # homogeneous file-frame log strain xx, yy, xy
    path = table_file(tmp_path / "t.csv", GRID + [2, 1], np.tile(e, (len(GRID), 1)))
    deg = 35.0
    field = load_dic(
        path,
        ImportSettings(
            format="table", strain="log", centre=(2.0, 1.0), rotation=deg, flip_y=flip, table=TableOptions(units="mm")
        ),
    )
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    sign = -1 if flip else 1
    x, y = GRID[:, 0], GRID[:, 1]
    np.testing.assert_allclose(field.xy[:, 0], c * x + s * y, atol=1e-12)
    np.testing.assert_allclose(field.xy[:, 1], sign * (-s * x + c * y), atol=1e-12)
    exx = e[0] * c**2 + e[1] * s**2 + 2 * e[2] * s * c
    eyy = e[0] * s**2 + e[1] * c**2 - 2 * e[2] * s * c
    exy = sign * ((e[1] - e[0]) * s * c + e[2] * (c**2 - s**2))
    np.testing.assert_allclose(field.strain, np.tile([exx, eyy, exy], (len(GRID), 1)), atol=1e-14)


def test_pixels_need_a_scale_and_are_scaled_to_mm():
    fx = FIXTURES["vic2d_classic.csv"]
    with pytest.raises(MeasurementError, match="--mm-per-px"):
        load_dic(DATA / fx.name, settings_for(fx, mm_per_px=None))
    base = load_dic(DATA / fx.name, settings_for(fx))
    double = load_dic(DATA / fx.name, settings_for(fx, mm_per_px=2 * fx.frame.mm_per_px, block_half=50.0))
    np.testing.assert_allclose(double.xy, 2 * base.xy, atol=1e-12)
    np.testing.assert_allclose(double.strain, base.strain, atol=0)
    metric = FIXTURES["vic3d_classic.csv"]
    with pytest.raises(MeasurementError, match="already in mm: drop --mm-per-px"):
        load_dic(DATA / metric.name, settings_for(metric, mm_per_px=0.05))


def test_strain_measures_and_the_percent_unit_are_converted(tmp_path):
    xy, log = GRID, np.tile([0.04, -0.02, 0.01], (len(GRID), 1))
    for measure, values in [("green", _green(log)), ("engineering", _biot(log)), ("log", log)]:
        for percent in (False, True):
            path = table_file(tmp_path / f"{measure}{percent}.csv", xy, values * (100 if percent else 1))
            field = load_dic(
                path, ImportSettings(format="table", strain=measure, percent=percent, table=TableOptions(units="mm"))
            )
            np.testing.assert_allclose(field.strain, log, atol=1e-10)


def _green(log):
    return np.array([_sym((_expm2(a, 2) - np.eye(2)) / 2) for a in log])


def _biot(log):
    return np.array([_sym(_expm2(a, 1) - np.eye(2)) for a in log])


def _expm2(a, k):
    from scipy.linalg import expm

    return expm(k * np.array([[a[0], a[2]], [a[2], a[1]]]))


def _sym(m):
    return [m[0, 0], m[1, 1], m[0, 1]]


def test_a_stated_measure_or_unit_cannot_be_contradicted():
    fx = FIXTURES["vic9_extract.csv"]  # "exx [1] - Lagrange"
    with pytest.raises(MeasurementError, match="states green strain; --strain log contradicts"):
        load_dic(DATA / fx.name, settings_for(fx, strain="log"))
    with pytest.raises(MeasurementError, match="fractions; --percent contradicts"):
        load_dic(DATA / fx.name, settings_for(fx, percent=True))


def test_an_assumed_measure_can_be_overridden():
    fx = FIXTURES["vic3d_classic.csv"]  # Lagrange assumed: the classic export does not name it
    assumed = load_dic(DATA / fx.name, settings_for(fx))
    declared = load_dic(DATA / fx.name, settings_for(fx, strain="log"))
    assert "assumed Lagrange" in "; ".join(assumed.notes) and declared.notes == []
    assert not np.allclose(declared.strain, assumed.strain, rtol=0, atol=1e-5)


def test_table_options_say_what_detection_cannot(capsys, tmp_path):
    log = np.tile([0.04, -0.02, 0.003], (len(GRID), 1))
    px = GRID / 0.1 + 500
    rows = ["\t".join(f"{v:.10g}".replace(".", ",") for v in row) for row in np.column_stack([px, log])]
    path = tmp_path / "export.txt"
    path.write_text("\n".join(["Stage 3 of 5", "a\tb\tc\td\te", *rows]) + "\n")
    out = tmp_path / "m.csv"
    code, stdout, err = cli(
        capsys,
        "import",
        path,
        "--format",
        "table",
        "--skip",
        1,
        "--delimiter",
        "tab",
        "--decimal",
        ",",
        "--columns",
        "a",
        "b",
        "c",
        "d",
        "e",
        "--units",
        "px",
        "--mm-per-px",
        0.1,
        "--centre",
        500,
        500,
        "--strain",
        "log",
        "--alpha",
        0.05,
        -0.02,
        "--t",
        0.8,
        "--out",
        out,
    )
    assert code == 0, err
    assert "could not decide: strain unit not stated" in stdout
    m = read_measurement(out)
    np.testing.assert_allclose(m.xy, GRID, atol=1e-9)
    np.testing.assert_allclose(m.strain, log, atol=1e-9)


def test_an_unstated_measure_must_be_given(tmp_path):
    path = table_file(tmp_path / "t.csv", GRID, np.zeros((len(GRID), 3)))
    with pytest.raises(MeasurementError, match="give --strain"):
        load_dic(path, ImportSettings(format="table"))


# ---------------------------------------------------------------- plausibility


def test_percent_read_as_fractions_is_caught_by_the_plausibility_check():
    fx = FIXTURES["table_percent.txt"]
    field = load_dic(DATA / fx.name, settings_for(fx, percent=False))
    assert "strain unit not stated" in "; ".join(field.notes)
    check = assess_plausibility(field.xy, field.strain, ALPHA, T, 10.0)
    assert check.ratio == pytest.approx(100, rel=0.02) and "add --percent" in check.problem


def test_fractions_declared_as_percent_are_caught(tmp_path):
    log = np.tile([math.log1p(T * ALPHA[0]), math.log1p(T * ALPHA[1]), 0], (len(GRID), 1))
    path = table_file(tmp_path / "t.csv", GRID, log)
    field = load_dic(path, ImportSettings(format="table", strain="log", percent=True, table=TableOptions(units="mm")))
    check = assess_plausibility(field.xy, field.strain, ALPHA, T, 10.0)
    assert check.ratio == pytest.approx(0.01) and "drop --percent" in check.problem


def test_swapped_axes_and_flipped_signs_are_caught():
    fx = FIXTURES["vic9_extract.csv"]
    turned = load_dic(DATA / fx.name, settings_for(fx, rotation=90.0))
    assert "x and y swapped" in assess_plausibility(turned.xy, turned.strain, ALPHA, T, 10.0).problem
    field = load_dic(DATA / fx.name, settings_for(fx))
    flipped = assess_plausibility(field.xy, field.strain, (-ALPHA[0], -ALPHA[1]), T, 10.0).problem
    assert "sign flipped" in flipped and "swapped" not in flipped
    swapped = assess_plausibility(field.xy, field.strain, ALPHA[::-1], T, 10.0).problem
    assert "x and y swapped" in swapped


def test_plausibility_tolerances():
    xy = np.zeros((3, 2))
    imposed = np.array([math.log1p(0.05), math.log1p(-0.05), 0.0])

    def problem(strain):
        return assess_plausibility(xy, np.tile(strain, (3, 1)), (0.05, -0.05), 1.0, 10.0).problem

    assert problem(0.23 * imposed) is None  # the weakest mean under the membrane in the FE `small` sweep
    assert problem(imposed * RATIO_RANGE[1] * 1.01) is not None
    assert problem(imposed * RATIO_RANGE[0] * 0.99) is not None
    for factor, accepted in ((0.99, True), (1.01, False)):  # at the edge of the cone of accepted directions
        a = math.acos(COS_MIN) * factor
        turned = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ imposed[:2]
        assert (problem(np.array([*turned, 0.0])) is None) == accepted
    assert "under the membrane" in assess_plausibility(xy + 20, np.zeros((3, 3)), (0.05, 0), 1.0, 10.0).problem
    assert assess_plausibility(xy, np.ones((3, 3)), (0.0, 0.0), 1.0, 10.0).problem is None


# ---------------------------------------------------------------- missing, duplicates, spread


def test_missing_points_are_masked_whatever_the_format():
    for name in (
        "vic3d_classic.csv",
        "vic2d_classic.csv",
        "vic9_extract.csv",
        "DICe_solution_12.txt",
        "table_decimal_comma.csv",
    ):
        fx = FIXTURES[name]
        field = load_dic(DATA / name, settings_for(fx))
        assert field.n_missing == len(fx.missing) > 0, name
    # DICe subset 24 failed with STATUS_FLAG 12 only (SIGMA > 0): masked too
    assert 24 in FIXTURES["DICe_solution_12.txt"].missing
    # a VIC export read as a generic table keeps VIC's rule (sigma < 0: missing), not zero-strain points
    fx = FIXTURES["vic3d_classic.csv"]
    field = load_dic(DATA / fx.name, settings_for(fx, format="table", strain="green", table=TableOptions(units="mm")))
    assert field.n_missing == len(fx.missing)


def test_localised_missing_markers(tmp_path):
    text = (DATA / "table_decimal_comma.csv").read_bytes().replace(b"NaN", b"n. v.")
    path = tmp_path / "t.csv"
    path.write_bytes(text)
    fx = FIXTURES["table_decimal_comma.csv"]
    with pytest.raises(MeasurementError, match="'n. v.' is not a number"):
        load_dic(path, settings_for(fx))
    options = TableOptions(missing=("n. v.",))
    assert load_dic(path, settings_for(fx, table=options)).n_missing == 2


def test_conflicting_duplicates_are_refused(tmp_path):
    fx = FIXTURES["vic3d_classic.csv"]
    lines = (DATA / fx.name).read_text().splitlines()
    cells = lines[10].split(",")
    path = tmp_path / "same.csv"
    path.write_text("\n".join(lines + [lines[10]]) + "\n")
    assert len(load_dic(path, settings_for(fx)).xy) == len(expected(fx)[0])  # an exact repeat is dropped
    cells[6] = "0.5"
    path.write_text("\n".join(lines + [",".join(cells)]) + "\n")
    with pytest.raises(MeasurementError, match=r"appears on lines 11 and 51 with different strains"):
        load_dic(path, settings_for(fx))


def test_collinear_or_too_few_points_are_refused(tmp_path):
    line = np.column_stack([np.linspace(-10, 10, 20), np.linspace(-5, 5, 20)])
    path = table_file(tmp_path / "line.csv", line, np.zeros((20, 3)))
    with pytest.raises(MeasurementError, match="lie on one line"):
        load_dic(path, ImportSettings(format="table", strain="log", table=TableOptions(units="mm")))
    path = table_file(tmp_path / "few.csv", GRID[:5] + [0, 3], np.zeros((5, 3)))
    with pytest.raises(MeasurementError, match="only 5 usable points"):
        load_dic(path, ImportSettings(format="table", strain="log", table=TableOptions(units="mm")))


# ---------------------------------------------------------------- text details and bad files


def test_latin1_table_is_read_and_said(tmp_path):
    header = "x [mm],y [mm],exx [1] - Lagrange,eyy [1] - Lagrange,exy [1] - Lagrange,angle [°]"
    path = tmp_path / "t.csv"
    path.write_bytes("\n".join([header, *(f"{x:g},{y:g},0,0,0,0" for x, y in GRID)]).encode("latin-1"))
    field = load_dic(path, ImportSettings(format="table"))
    assert len(field.xy) == len(GRID) and "Latin-1" in "; ".join(field.notes)
    with pytest.raises(MeasurementError, match="is not valid utf-8"):
        load_dic(path, ImportSettings(format="table", table=TableOptions(encoding="utf-8")))


@pytest.mark.parametrize(
    "name, edit, message",
    [
        ("vic9_extract.csv", lambda t: t + "\n" + t.split("\n", 1)[1], "several images"),
        ("DICe_solution_12.txt", lambda t: t.replace(",VSG_STRAIN_XY", ",OTHER"), "VSG_STRAIN_XY missing"),
        ("davis8_vectors.txt", lambda t: t.rsplit("\n", 2)[0] + "\n", "the file has 55"),
        ("vic3d_classic.csv", lambda t: t.replace("0.0123,", "x,", 1), "'x' is not a number"),
        ("vic3d_classic.csv", lambda t: t.replace('"exy"', '"gxy"'), "column(s) exy missing"),
    ],
)
def test_bad_files_are_one_clear_error(tmp_path, name, edit, message):
    path = tmp_path / name
    path.write_bytes(edit((DATA / name).read_bytes().decode("latin-1")).encode("latin-1"))
    with pytest.raises(MeasurementError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_dic(path, settings_for(FIXTURES[name]))


# ---------------------------------------------------------------- command line


@pytest.mark.parametrize("name", list(FIXTURES))
def test_cli_import_writes_a_measurement_every_command_reads(capsys, tmp_path, name):
    fx = FIXTURES[name]
    out = tmp_path / "m.csv"
    fmt = ["--format", "table"] if fx.format == "table" else []
    code, stdout, err = cli(
        capsys, "import", DATA / name, *fmt, *fx.frame.options(), *fx.extra, "--alpha", *ALPHA, "--t", T, "--out", out
    )
    assert code == 0, err
    assert "plausible" in stdout and f"wrote {out}" in stdout
    m = read_measurement(out, half_length=25.0)
    xy, strain = expected(fx)
    assert m.alpha.tolist() == list(ALPHA) and m.t == T
    np.testing.assert_allclose(m.xy, xy, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(m.strain, strain, rtol=0, atol=TOLERANCE.get(name, 1e-6))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]  # no temporary file left


def test_cli_refuses_to_overwrite_without_force(capsys, tmp_path):
    fx = FIXTURES["vic9_extract.csv"]
    out = tmp_path / "m.csv"
    args = ["import", DATA / fx.name, *fx.frame.options(), "--alpha", *ALPHA, "--t", T, "--out", out]
    assert cli(capsys, *args)[0] == 0
    out.write_text("keep me")
    code, _, err = cli(capsys, *args)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"error: {out} exists; pass --force to replace it" in err
    assert out.read_text() == "keep me"
    assert cli(capsys, *args, "--force")[0] == 0 and read_measurement(out).xy.shape == (63, 2)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--centre", "612", "488"], "give the image scale with --mm-per-px"),
        (["--mm-per-px", "0.05", "--centre", "612", "488", "--rotation", "70", "--flip-y"], "x and y swapped"),
        (["--mm-per-px", "0.05", "--delimiter", ";"], "--delimiter applies to --format table only"),
        (["--mm-per-px", "-1"], "--mm-per-px must be a positive number"),
        (["--mm-per-px", "0.05", "--centre", "612", "488", "--t", "1.5"], "t = 1.5 must be in (0, 1]"),
        (["--format", "dice", "--mm-per-px", "0.05"], "DICe column(s) COORDINATE_X, COORDINATE_Y"),
        (["--config", "nope"], "no such preset"),
    ],
)
def test_cli_errors_are_one_line_and_exit_2(capsys, tmp_path, args, message):
    design = [] if "--t" in args else ["--t", T]
    code, _, err = cli(
        capsys, "import", DATA / "vic2d_classic.csv", *args, "--alpha", *ALPHA, *design, "--out", tmp_path / "m.csv"
    )
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and not (tmp_path / "m.csv").exists()


def test_cli_missing_file_is_one_line(capsys, tmp_path):
    code, _, err = cli(capsys, "import", tmp_path / "none.csv", "--alpha", *ALPHA, "--t", T, "--out", tmp_path / "m")
    assert code == 2 and "does not exist" in err and len(err.strip().splitlines()) == 1


def test_cli_show_plots_an_export_and_a_measurement(capsys, tmp_path):
    fx = FIXTURES["DICe_solution_12.txt"]
    fig = tmp_path / "dice.png"
    code, stdout, err = cli(
        capsys, "show", DATA / fx.name, *fx.frame.options(), "--alpha", *ALPHA, "--t", T, "--out", fig
    )
    assert code == 0, err
    assert fig.read_bytes().startswith(b"\x89PNG") and "plausible" in stdout
    m = tmp_path / "m.csv"
    assert cli(capsys, "import", DATA / fx.name, *fx.frame.options(), "--alpha", *ALPHA, "--t", T, "--out", m)[0] == 0
    code, stdout, err = cli(capsys, "show", m, "--out", tmp_path / "m.png")
    assert code == 0 and (tmp_path / "m.png").stat().st_size > 0 and "plausible" in stdout, err
    code, _, err = cli(capsys, "show", m, "--out", tmp_path / "m.png")
    assert code == 2 and "--force" in err


def test_a_field_becomes_a_measurement():
    fx = FIXTURES["vic9_extract.csv"]
    field = load_dic(DATA / fx.name, settings_for(fx))
    assert isinstance(field, DicField)
    m = field.measurement(ALPHA, T)
    assert m.alpha.tolist() == list(ALPHA) and m.t == T and m.sd is None and m.xy is field.xy
    with pytest.raises(MeasurementError, match="two finite numbers"):
        field.measurement((0.05, math.nan), T)
