"""The bad-input corpus: each wrong input a user has been seen to give ``skinid``, one test each.

Every case feeds one bad input to one command and expects it refused:

- exit status 2 and ONE line on stderr, ``skinid <command>: error: ...``, holding the case's
  message (never a traceback);
- before any computing: the FE model, the sweep, GP fitting, MCMC sampling, noise generation and
  the check's calibration are replaced by a function that fails the test if it is called;
- nothing written or changed: every file under the test's folder and the shared inputs keeps
  its bytes and mtime, and no file (output, temporary or lock) appears or disappears.

Sources: ../shared/reference/bad-inputs-found.md (100 inputs tried as a new user), issue 19 ("accepted
without a word", "tracebacks instead of one line", ...) and what the command-line code checks.
The cases are grouped by what is wrong: measurement files, ``check`` options, ``infer``,
datasets, emulators, ``noise`` / ``surrogate`` / ``study`` options, configurations (TOML),
``simulate`` / ``sweep`` / ``merge`` / ``info``, DIC imports, and outputs (existing, in a file,
not writable, locked by another sweep). Bad DIC export files are in tests/test_dic_import.py, and
measurements the check cannot use (outside the block, no membrane edge, NaN, too few points) in
tests/test_check_robustness.py.

The commands run in this process (``skinfem.cli.main``; a ``skinid`` subprocess costs seconds
of imports). Two cases run a subprocess, for what only a new process shows: a refusal must not
print PETSc's list of unused options when the process exits.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest

from inference.observations import write_measurement
from tests.cli_helpers import MPIRUN, skinid, skinid_command, skinid_env
from tests.test_cli_conventions import OLD_BYTES, fake_dataset, old_output

DIC = Path(__file__).parent / "data" / "dic" / "vic9_extract.csv"
PETSC_WARNING = "There are options you set that were not used"
COMPUTING = {  # what a refusal must come before: module attribute -> what it computes
    "skinfem.model.SkinModel": "the FE model",
    "skinfem.mesh.build_mesh": "the mesh",
    "skinfem.sweep._sweep": "the sweep",
    "surrogate.emulator.fit_emulator": "the emulator fit",
    "inference.studies.sample_posterior": "MCMC sampling",
    "inference.studies.noise_study": "the noise study",
    "inference.studies.test_set_study": "the test-set study",
    "inference.coverage.coverage_study": "the coverage study",
    "inference.noise.add_noise": "the noisy dataset",
    "inference.criticism.check.run_check": "the check",
}


# ---------------------------------------------------------------- inputs, snapshot, running


@dataclass(frozen=True)
class Inputs:
    """Valid inputs every case shares (none may change): a dataset, an emulator of it and a
    measurement of design (0.05, -0.05) at t = 1 with sd columns."""

    folder: Path
    data: Path
    emu: Path
    m: Path


def grid(extent: float = 20.0, step: float = 2.0) -> np.ndarray:
    g = np.arange(-extent, extent + 1e-9, step)
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def plausible_strain(xy: np.ndarray, alpha=(0.05, -0.05), scale: float = 1.0) -> np.ndarray:
    """Log strains like the design's under the membrane, fading outside it (times ``scale``)."""
    shape = np.exp(-(np.maximum(np.abs(xy).max(axis=1) - 10, 0) ** 2) / 20)
    return scale * np.column_stack([np.log1p(alpha[0]) * shape, np.log1p(alpha[1]) * shape, 0 * shape])


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Inputs:
    from skinfem.io import StrainDataset
    from surrogate.emulator import fit_emulator

    folder = tmp_path_factory.mktemp("inputs")
    data = fake_dataset(folder / "data.h5")
    emu = fit_emulator(StrainDataset.open(data), gp_fraction=0.5, restarts=0, seed=0, n_jobs=1).save(folder / "emu")
    xy = grid()
    m = write_measurement(folder / "m.csv", xy, plausible_strain(xy), (0.05, -0.05), 1.0, np.full((len(xy), 3), 1e-3))
    return Inputs(folder, data, emu, m)


@pytest.fixture(autouse=True)
def no_computing(monkeypatch):
    """Any computing fails the test: a refusal comes first."""
    for target, what in COMPUTING.items():

        def started(*args, what=what, **kwargs):
            pytest.fail(f"{what} started before the input was refused")

        monkeypatch.setattr(target, started)


def snapshot(*folders: Path) -> dict[Path, tuple[int, bytes] | None]:
    """Every path under the folders: a file's mtime and bytes, None for a folder."""
    return {
        p: (p.stat().st_mtime_ns, p.read_bytes()) if p.is_file() else None
        for folder in folders
        for p in sorted(folder.rglob("*"))
    }


def run_here(argv: list[str], capsys) -> tuple[int, str]:
    """``skinid argv`` in this process: (exit status, stderr)."""
    from skinfem.cli import main

    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code
    return code, capsys.readouterr().err


def assert_refused(code: int, err: str, message: str) -> None:
    """Exit status 2 and one line ``skinid ...: error: ...`` containing ``message``."""
    lines = err.strip().splitlines()
    assert "Traceback" not in err, err
    assert code == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith("skinid ") and ": error: " in lines[0] and message in lines[0], err


# ---------------------------------------------------------------- making bad inputs
# Each maker writes the bad input into the test's folder ``tmp`` (from the shared ``Inputs``).


def measurement(edit):
    """tmp/bad.csv: the shared measurement's text through ``edit``."""

    def make(tmp: Path, inp: Inputs) -> None:
        (tmp / "bad.csv").write_bytes(edit(inp.m.read_text()).encode())

    return make


def measurement_of(xy, strain=None, alpha=(0.05, -0.05)):
    """tmp/bad.csv: a measurement of points ``xy`` (plausible strains unless given, sd 1e-3)."""

    def make(tmp: Path, inp: Inputs) -> None:
        xy_ = np.asarray(xy, dtype=float)
        values = plausible_strain(xy_, alpha) if strain is None else strain(xy_)
        write_measurement(tmp / "bad.csv", xy_, values, alpha, 1.0, np.full((len(xy_), 3), 1e-3))

    return make


def replace_values(text: str, k: int, values: str) -> str:
    """The measurement text with the values after x, y of data row ``k`` (0-based) replaced."""
    lines = text.splitlines()
    row = next(i for i, line in enumerate(lines) if line.startswith("x,")) + 1 + k
    lines[row] = ",".join(lines[row].split(",")[:2] + [values])
    return "\n".join(lines) + "\n"


def dataset(edit):
    """tmp/bad.h5: a copy of the shared dataset changed by ``edit(h5py.File)``."""

    def make(tmp: Path, inp: Inputs) -> None:
        shutil.copy(inp.data, tmp / "bad.h5")
        with h5py.File(tmp / "bad.h5", "r+") as f:
            edit(f)

    return make


def set_status(f) -> None:
    f["status"][0, 0] = -1


def other_mesh(f) -> None:
    f.attrs["mesh_sha256"] = "0" * 64


def emulator(edit):
    """tmp/emu: a copy of the shared emulator, one file changed by ``edit(folder)``."""

    def make(tmp: Path, inp: Inputs) -> None:
        shutil.copytree(inp.emu, tmp / "emu")
        edit(tmp / "emu")

    return make


def truncate(name: str):
    def edit(folder: Path) -> None:
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: len(data) // 2])

    return edit


def meta(change):
    """Edit meta.json: ``change(dict)`` or, if it is a string, replace the file's text by it."""

    def edit(folder: Path) -> None:
        path = folder / "meta.json"
        if isinstance(change, str):
            path.write_text(change)
            return
        entries = json.loads(path.read_text())
        change(entries)
        path.write_text(json.dumps(entries))

    return edit


def file(name: str, content: bytes | str):
    """tmp/name holding ``content``."""

    def make(tmp: Path, inp: Inputs) -> None:
        (tmp / name).write_bytes(content.encode() if isinstance(content, str) else content)

    return make


def config(toml: str | bytes):
    """tmp/c.toml."""
    return file("c.toml", toml)


def bounds(theta="[0.0, 90.0]", mu="[0.001, 0.002]") -> str:
    return (
        f"[sweep]\nbounds = {{ mu = {mu}, k1 = [0.012, 0.022], k2 = [8.3, 15.3], kappa = [0.27, 0.3], "
        f"theta = {theta} }}\n"
    )


# ---------------------------------------------------------------- the corpus
# (arguments, message, maker): {data}, {emu}, {m} are the shared inputs, {tmp} the test's folder
# (bad files: bad.csv, bad.h5, emu/, c.toml) and {out} an output in it that must not appear.

CHECK = "check --config small --out {out} --measurement"
CHECK_M = "check --config small --out {out} --measurement {m}"
INFER = "infer --emulator {emu} --out {out}"
INFER_DATA = "infer --emulator {emu} --out {out} --data {data} --material 0"
FIT = "surrogate fit --data {data} --out {out}"
TEST_SET = "study test-set --emulator {emu} --data {data} --out {out}"
STUDY_NOISE = "study noise --data {data} --out {out} --designs 0"
COVERAGE = "study coverage --emulator {emu} --data {data} --out {out}"
NOISE = "noise --data {data} --length 1 --level 0.05 --out {tmp}/noisy.h5"
SWEEP = "sweep --quiet --out {tmp}/data.h5 --config {tmp}/c.toml"
SIMULATE = "simulate --mu 0.0012 --k1 0.017 --k2 12 --kappa 0.28 --alpha 0.05 -0.05"
IMPORT = "measurement import --alpha 0.05 -0.02 --t 0.8 --out {out}.csv"

CASES = {
    # -- measurement files (check and infer read them alike)
    "measurement-missing": (f"{CHECK} {{tmp}}/none.csv", "measurement file '{tmp}/none.csv' does not exist", None),
    "measurement-is-a-folder": (f"{CHECK} {{tmp}}", "is a folder", None),
    "measurement-is-binary": (f"{CHECK} {{data}}", "is not UTF-8 text", None),
    "measurement-empty": (f"{CHECK} {{tmp}}/bad.csv", "bad.csv:1: first line must be", file("bad.csv", "")),
    "measurement-is-a-dic-export": (f"{CHECK} " + str(DIC), "first line must be '# skinid-measurement v1'", None),
    "measurement-with-bom-is-read": (  # the BOM is not the problem any more: the NaN row is
        f"{CHECK} {{tmp}}/bad.csv",
        "NaN or infinite value",
        measurement(lambda t: "\ufeff" + replace_values(t, 3, "nan,0,0,0.001,0.001,0.001")),
    ),
    "measurement-header-without-alpha22": (
        f"{CHECK} {{tmp}}/bad.csv",
        "header line '# alpha22 = ...' is missing",
        measurement(lambda t: t.replace("# alpha22 = -0.05\n", "")),
    ),
    "measurement-alpha-nan": (
        f"{CHECK} {{tmp}}/bad.csv",
        "bad design in the header: alpha11 must be a finite number",
        measurement(lambda t: t.replace("# alpha11 = 0.05", "# alpha11 = nan")),
    ),
    "measurement-alpha-beyond-any-design": (
        f"{CHECK} {{tmp}}/bad.csv",
        "|alpha22| must be < 0.5",
        measurement(lambda t: t.replace("# alpha22 = -0.05", "# alpha22 = -5")),
    ),
    "measurement-t-zero": (
        f"{CHECK} {{tmp}}/bad.csv",
        "t = 0.0 must be in (0, 1]",
        measurement(lambda t: t.replace("# t = 1.0", "# t = 0")),
    ),
    "measurement-unknown-strain-measure": (
        f"{CHECK} {{tmp}}/bad.csv",
        "unknown strain measure 'cauchy'",
        measurement(lambda t: t.replace("= log", "= cauchy")),
    ),
    "measurement-column-missing": (
        f"{CHECK} {{tmp}}/bad.csv",
        "column(s) exy missing",
        measurement(lambda t: t.replace(",exy,", ",gxy,")),
    ),
    "measurement-short-row": (
        f"{CHECK} {{tmp}}/bad.csv",
        "expected 8 values, found 7",
        measurement(lambda t: replace_values(t, 5, "0,0,0,0.001,0.001")),
    ),
    "measurement-value-not-a-number": (
        f"{CHECK} {{tmp}}/bad.csv",
        "a value is not a number",
        measurement(lambda t: replace_values(t, 5, "0.01,x,0,0.001,0.001,0.001")),
    ),
    "measurement-infinite-strain": (
        f"{CHECK} {{tmp}}/bad.csv",
        "NaN or infinite value",
        measurement(lambda t: replace_values(t, 5, "inf,0,0,0.001,0.001,0.001")),
    ),
    "measurement-zero-sd": (
        f"{CHECK} {{tmp}}/bad.csv",
        "standard deviations must be > 0",
        measurement(lambda t: replace_values(t, 5, "0,0,0,0,0.001,0.001")),
    ),
    "measurement-two-rows": (
        f"{CHECK} {{tmp}}/bad.csv",
        "only 2 data rows; need at least 3",
        measurement_of([[0, 0], [1, 1]]),
    ),
    "measurement-conflicting-duplicate": (  # was silently dropped by the thinning
        f"{CHECK} {{tmp}}/bad.csv",
        "point (-20, -20) is also on line 7, with other values",
        measurement(lambda t: t + "-20,-20,0.3,0,0,0.001,0.001,0.001\n"),
    ),
    "measurement-collinear": (  # was a QhullError traceback
        f"{CHECK} {{tmp}}/bad.csv",
        "the 41 points lie on one line",
        measurement_of(np.column_stack([np.linspace(-20, 20, 41), np.full(41, 10.0)])),
    ),
    "measurement-percent": (  # was accepted: "chi2/dof 1.8e8, no candidate explains it"
        f"{CHECK} {{tmp}}/bad.csv",
        "strains in percent?",
        measurement_of(grid(), strain=lambda xy: plausible_strain(xy, scale=100)),
    ),
    "measurement-percent-declared-green": (  # said neither which file nor why
        f"{CHECK} {{tmp}}/bad.csv",
        "bad.csv: green strains with a non-positive stretch cannot be converted",
        measurement(lambda t: replace_values(t, 5, "-60,0,0,0.001,0.001,0.001").replace("= log", "= green")),
    ),
    "measurement-thinned-to-fewer-points-than-parameters": (
        f"{CHECK_M} --spacing 25",
        "4 measured points are not more than the 5 parameters",
        None,
    ),
    # -- check options
    "check-noise-sd-negative": (
        f"{CHECK_M} --noise-sd -0.001 1e-3 1e-3",
        "noise sd must be three positive numbers",
        None,
    ),
    "check-noise-sd-nan": (f"{CHECK_M} --noise-sd nan 1e-3 1e-3", "noise sd must be three positive numbers", None),
    "check-noise-length-nan": (  # ran the FE model, then said "mu must be a finite number"
        f"{CHECK_M} --noise-length nan",
        "--noise-length must be a number >= 0 mm, got nan",
        None,
    ),
    "check-noise-length-negative": (f"{CHECK_M} --noise-length -1", "--noise-length must be a number >= 0 mm", None),
    "check-noise-nugget-above-1": (f"{CHECK_M} --noise-nugget 2", "--noise-nugget must be in [0, 1]", None),
    "check-smooth-noise-without-nugget": (
        f"{CHECK_M} --noise-length 2",
        "--noise-length > 0 needs --noise-nugget > 0",
        None,
    ),
    "check-spacing-zero": (f"{CHECK_M} --spacing 0", "the point spacing must be > 0 mm", None),
    "check-dic-window-negative": (f"{CHECK_M} --dic-window -1", "the DIC strain window must be > 0 mm", None),
    "check-unknown-candidate": (f"{CHECK_M} --candidates bogus", "unknown effect 'bogus'; known effects:", None),
    "check-unknown-added-effect": (f"{CHECK_M} --add glue", "unknown effect 'glue'; known effects:", None),
    "check-increments-zero": (f"{CHECK_M} --increments 0", "--increments must be >= 1", None),
    "check-confirm-negative": (f"{CHECK_M} --confirm -1", "--confirm must be >= 0", None),
    "check-no-sd-anywhere": (
        f"{CHECK} {{tmp}}/bad.csv",
        "the measurements have no sd_exx, sd_eyy, sd_exy columns: give --noise-sd",
        measurement(lambda t: t.replace(",sd_exx,sd_eyy,sd_exy", "").replace(",0.001,0.001,0.001", "")),
    ),
    "check-config-unknown": (
        "check --config smal --out {out} --measurement {m}",
        "config 'smal': no such file and no such preset",
        None,
    ),
    "check-emulator-not-an-emulator": (
        "check --emulator {tmp} --out {out} --measurement {m}",
        "is not an emulator directory (no meta.json)",
        None,
    ),
    # -- infer
    "infer-draws-negative": (f"{INFER_DATA} --draws -1", "--draws must be >= 1", None),  # was ZeroDivisionError
    "infer-chains-zero": (f"{INFER_DATA} --chains 0", "--chains must be >= 1", None),  # "need at least one array"
    "infer-warmup-negative": (f"{INFER_DATA} --warmup -1", "--warmup must be >= 0", None),
    "infer-jobs-zero": (f"{INFER_DATA} --jobs 0", "--jobs must be >= 1", None),
    "infer-data-without-material": (f"{INFER} --data {{data}}", "--data needs --material", None),
    "infer-material-out-of-range": (f"{INFER} --data {{data}} --material 12", "material 12 is not in [0, 12)", None),
    "infer-design-out-of-range": (f"{INFER_DATA} --designs 2", "design 2 is not in [0, 2)", None),
    "infer-frame-out-of-range": (f"{INFER_DATA} --frames 2", "frame 2 is not in [0, 2)", None),
    "infer-designs-not-integers": (f"{INFER_DATA} --designs 0,a", "--designs takes design indices", None),
    "infer-design-alpha-not-in-the-dataset": (
        f"{INFER_DATA} --designs 0.05,0.01",
        "has no design alpha = 0.05,0.01",
        None,
    ),
    "infer-design-alpha-odd-count": (f"{INFER_DATA} --designs 0.05,0.05,0.05", "come in pairs", None),
    "infer-failed-simulation": (
        f"{INFER} --data {{tmp}}/bad.h5 --material 0 --designs 0",
        "simulation (material 0, design 0) did not converge",
        dataset(set_status),
    ),
    "infer-dataset-of-another-mesh-same-cells": (  # was accepted
        f"{INFER} --data {{tmp}}/bad.h5 --material 0",
        "was simulated on another mesh than the emulator's dataset",
        dataset(other_mesh),
    ),
    "infer-known-noise-without-sd": (
        f"{INFER} --noise known --measurement {{tmp}}/bad.csv",
        "noise='known' needs measurements with sd_exx",
        measurement(lambda t: t.replace(",sd_exx,sd_eyy,sd_exy", "").replace(",0.001,0.001,0.001", "")),
    ),
    "infer-alpha-outside-the-emulators-range": (  # gave only R-hat warnings
        f"{INFER} --measurement {{tmp}}/bad.csv",
        "alpha11*t = 0.3 is outside the emulator's training range",
        measurement_of(grid(), alpha=(0.3, 0.0)),
    ),
    "infer-measurement-outside-the-block": (
        f"{INFER} --measurement {{tmp}}/bad.csv",
        "lies outside the block |x|, |y| <= 25",
        measurement(lambda t: t + "30,0,0,0,0,0.001,0.001,0.001\n"),
    ),
    "infer-measurement-covering-no-skin-cell": (
        f"{INFER} --measurement {{tmp}}/bad.csv",
        "only 0 skin cells lie inside the measured region",
        measurement_of(grid(1.0, 0.5)),
    ),
    "infer-measurement-percent": (
        f"{INFER} --measurement {{tmp}}/bad.csv",
        "strains in percent?",
        measurement_of(grid(), strain=lambda xy: plausible_strain(xy, scale=100)),
    ),
    "infer-measurement-collinear": (  # was a QhullError traceback
        f"{INFER} --measurement {{tmp}}/bad.csv",
        "points lie on one line",
        measurement_of(np.column_stack([np.linspace(-20, 20, 41), np.linspace(-10, 10, 41)])),
    ),
    # -- datasets
    "info-missing-dataset": ("info {tmp}/none.h5", "dataset '{tmp}/none.h5' does not exist", None),
    "info-folder": ("info {tmp}", "is a folder, not a dataset", None),
    "info-not-hdf5": ("info {m}", "is not a readable HDF5 file", None),
    "info-hdf5-not-a-dataset": (
        "info {tmp}/bad.h5",
        "is not a skinid dataset (no format attribute)",
        dataset(lambda f: f.attrs.__delitem__("format")),
    ),
    "info-other-format-version": (
        "info {tmp}/bad.h5",
        "has dataset format 7, this skinid reads format 1",
        dataset(lambda f: f.attrs.__setitem__("format_version", 7)),
    ),
    "info-no-strain": (
        "info {tmp}/bad.h5",
        "is not a complete skinid dataset: it has no /strain",  # KeyError
        dataset(lambda f: f.__delitem__("strain")),
    ),
    "fit-corrupt-noise-attribute": (
        "surrogate fit --data {tmp}/bad.h5 --out {out}",
        "has a corrupt 'noise' attribute (no entry 'amplitude')",  # KeyError
        dataset(lambda f: f.attrs.__setitem__("noise", '{"length_mm": 0.1, "level": 0.01}')),
    ),
    "noise-on-noisy-data": (  # the copy's noise attribute would have named only the second noise
        "noise --data {tmp}/bad.h5 --length 1 --level 0.05 --out {out}.h5",
        "already carries added noise: add noise to the clean dataset",
        dataset(lambda f: f.attrs.__setitem__("noise", '{"length_mm": 0.1, "level": 0.01, "amplitude": [1, 1, 1]}')),
    ),
    "info-noise-attribute-not-json": (
        "info {tmp}/bad.h5",
        "has a corrupt 'noise' attribute (Expecting value",
        dataset(lambda f: f.attrs.__setitem__("noise", "not json")),
    ),
    "fit-no-strain": (
        "surrogate fit --data {tmp}/bad.h5 --out {out}",
        "it has no /strain",  # KeyError
        dataset(lambda f: f.__delitem__("strain")),
    ),
    "noise-no-status": (
        "noise --data {tmp}/bad.h5 --length 1 --level 0.05 --out {out}.h5",
        "it has no /status",
        dataset(lambda f: f.__delitem__("status")),
    ),
    "merge-no-cells": (
        "merge {tmp}/bad.h5 --out {out}.h5",
        "it has no /cells/xy",
        dataset(lambda f: f.__delitem__("cells/xy")),
    ),
    "merge-missing-shard": (
        "merge {data} {tmp}/none.h5 --out {out}.h5",
        "dataset '{tmp}/none.h5' does not exist",
        None,
    ),
    "merge-shard-of-another-mesh": (
        "merge {data} {tmp}/bad.h5 --out {out}.h5",
        "cannot merge: '{tmp}/bad.h5' has another mesh than",
        dataset(other_mesh),
    ),
    "merge-shard-not-hdf5": ("merge {m} --out {out}.h5", "is not a readable HDF5 file", None),
    # -- emulators
    "emulator-missing": (
        "infer --emulator {tmp}/none --data {data} --material 0 --out {out}",
        "emulator directory '{tmp}/none' does not exist",
        None,
    ),
    "emulator-truncated-gp": (  # was BadZipFile
        "infer --emulator {tmp}/emu --data {data} --material 0 --out {out}",
        "gp.npz' is truncated or corrupt",
        emulator(truncate("gp.npz")),
    ),
    "emulator-truncated-pca": (
        "surrogate validate --emulator {tmp}/emu",
        "pca.npz' is truncated or corrupt",
        emulator(truncate("pca.npz")),
    ),
    "emulator-truncated-sklearn-gps": (  # said only "EOF: reading array data, ..."
        "infer --emulator {tmp}/emu --data {data} --material 0 --out {out}",
        "sklearn_gps.joblib' cannot be read",
        emulator(truncate("sklearn_gps.joblib")),
    ),
    "emulator-meta-without-lower": (  # was KeyError
        "infer --emulator {tmp}/emu --data {data} --material 0 --out {out}",
        "meta.json' has no entry 'lower'",
        emulator(meta(lambda e: e.pop("lower"))),
    ),
    "emulator-meta-not-json": (  # said only "Expecting property name ..."
        "infer --emulator {tmp}/emu --data {data} --material 0 --out {out}",
        "meta.json' is not valid JSON",
        emulator(meta("{not json")),
    ),
    "infer-scaled-with-an-emulator-fitted-before-the-material-scale": (  # a ValueError, not checked before
        f"{INFER_DATA} --emulator-error scaled".replace("{emu}", "{tmp}/emu"),
        "an emulator that fitted its material scale: refit it with 'skinid surrogate fit'",
        emulator(meta(lambda e: e["held_out_excess"].pop("material_scale"))),
    ),
    "infer-shift-with-an-emulator-fitted-before-the-parameter-shift": (
        f"{INFER_DATA} --emulator-error shift".replace("{emu}", "{tmp}/emu"),
        "the parameter shift needs the emulator's error model (emulator_error on) and an emulator that fitted it",
        emulator(meta(lambda e: e["held_out_excess"].pop("parameter_shift"))),
    ),
    "emulator-other-format": (
        "infer --emulator {tmp}/emu --data {data} --material 0 --out {out}",
        "is not a skinid emulator",
        emulator(meta(lambda e: e.update(format="other"))),
    ),
    "emulator-newer-format-version": (
        "infer --emulator {tmp}/emu --data {data} --material 0 --out {out}",
        "was written in emulator format 9",
        emulator(meta(lambda e: e.update(format_version=9))),
    ),
    "validate-dataset-of-another-mesh": (
        "surrogate validate --emulator {tmp}/emu --data {tmp}/bad.h5",
        "was simulated on another mesh than the emulator's data",
        lambda tmp, inp: (emulator(lambda f: None)(tmp, inp), dataset(other_mesh)(tmp, inp)),
    ),
    # -- surrogate fit options
    "fit-n-components-zero": (f"{FIT} --n-components 0", "--n-components must be >= 1", None),  # was ignored
    "fit-variance-above-1": (f"{FIT} --variance 1.5", "--variance must be in (0, 1), got 1.5", None),
    "fit-gp-fraction-zero": (f"{FIT} --gp-fraction 0", "--gp-fraction must be in (0, 1]", None),
    "fit-max-gp-rows-one": (f"{FIT} --max-gp-rows 1", "--max-gp-rows must be >= 2", None),
    "fit-restarts-negative": (f"{FIT} --restarts -1", "--restarts must be >= 0", None),
    "fit-cv-folds-one": (f"{FIT} --cv-folds 1", "--cv-folds must be >= 2", None),
    "fit-missing-dataset": ("surrogate fit --data {tmp}/none.h5 --out {out}", "does not exist", None),
    # -- noise options
    "noise-length-negative": (
        NOISE.replace("--length 1", "--length -1"),
        "--length: the noise length scale must be > 0 mm",
        None,
    ),
    "noise-length-nan": (
        NOISE.replace("--length 1", "--length nan"),  # read the data, then failed to write it
        "--length: the noise length scale must be > 0 mm, got nan",
        None,
    ),
    "noise-level-nan": (
        NOISE.replace("--level 0.05", "--level nan"),
        "--level: the noise level must be a fraction in [0, 1), got nan",
        None,
    ),
    "noise-out-not-h5": (NOISE.replace("noisy.h5", "noisy.csv"), "--out must end in .h5", None),
    # -- study options
    "study-test-set-design-out-of-range": (f"{TEST_SET} --designs 7", "--designs 7 is not in [0, 2)", None),
    "study-test-set-frame-out-of-range": (f"{TEST_SET} --designs 0 --frames 9", "--frames 9 is not in [0, 2)", None),
    "study-test-set-material-out-of-range": (
        f"{TEST_SET} --designs 0 --materials 99",
        "--materials 99 is not in [0, 12)",
        None,
    ),
    "study-test-set-draws-zero": (f"{TEST_SET} --designs 0 --draws 0", "--draws must be >= 1", None),
    "study-test-set-dataset-of-another-mesh": (
        "study test-set --emulator {emu} --data {tmp}/bad.h5 --designs 0 --out {out}",
        "was simulated on another mesh than the emulator's dataset",
        dataset(other_mesh),
    ),
    "study-coverage-n-beyond-the-frames": (
        f"{COVERAGE} --setup frames --n 3",
        "--n must be in [1, 2] for the frames setup",
        None,
    ),
    "study-coverage-n-beyond-the-designs": (
        f"{COVERAGE} --setup membranes --n 5",
        "--n must be in [1, 2] for the membranes setup",
        None,
    ),
    "study-coverage-noise-negative": (f"{COVERAGE} --noise-sd -0.001", "--noise-sd must be >= 0, got -0.001", None),
    "study-coverage-no-noise-seed": (f"{COVERAGE} --noise-seeds 0", "--noise-seeds must be >= 1, got 0", None),
    "study-coverage-starts-beyond-the-designs": (f"{COVERAGE} --starts 3", "--starts must be in [1, 2], got 3", None),
    "study-coverage-model-data-without-noise": (
        f"{COVERAGE} --data-from model",
        "--data-from model needs a stated --noise-sd > 0",
        None,
    ),
    "study-setups-design-out-of-range": (
        "study setups --emulator {emu} --data {data} --designs 9 --out {out}",
        "design 9 is not in [0, 2)",
        None,
    ),
    "study-noise-two-designs": (
        STUDY_NOISE.replace("--designs 0", "--designs 0,1"),
        "--designs names one design",
        None,
    ),
    "study-noise-design-out-of-range": (
        STUDY_NOISE.replace("--designs 0", "--designs 9"),
        "--designs 9 is not in [0, 2)",
        None,
    ),
    "study-noise-level-negative": (
        f"{STUDY_NOISE} --levels 0.05 -1",
        "--levels must be positive numbers, got -1",
        None,
    ),
    "study-noise-length-zero": (f"{STUDY_NOISE} --lengths 0", "--lengths must be positive numbers, got 0", None),
    "study-noise-gp-fraction-above-1": (f"{STUDY_NOISE} --gp-fraction 2", "--gp-fraction must be in (0, 1]", None),
    "study-noise-no-component": (f"{STUDY_NOISE} --n-components 0", "--n-components must be >= 1, got 0", None),
    # -- configurations (TOML), read by every FE command
    "config-unknown-key": (SWEEP, "config key 'solver.increment': unknown key", config("[solver]\nincrement = 5\n")),
    "config-integer-expected": (
        SWEEP,
        "config key 'solver.increments': expected an integer, got 2.5",
        config("[solver]\nincrements = 2.5\n"),
    ),
    "config-boolean-for-integer": (
        SWEEP,
        "config key 'solver.increments': expected an integer, got True",
        config("[solver]\nincrements = true\n"),
    ),
    "config-negative-size": (
        SWEEP,
        "config key 'mesh.length': must be > 0, got -50.0",
        config("[mesh]\nlength = -50.0\n"),
    ),
    "config-zero-layers": (SWEEP, "config key 'mesh.skin_layers': must be > 0", config("[mesh]\nskin_layers = 0\n")),
    "config-nan": (
        SWEEP,
        "config key 'muscle.bulk_ratio': must be a finite number, got nan",
        config("[muscle]\nbulk_ratio = nan\n"),
    ),
    "config-infinite": (
        SWEEP,
        "config key 'muscle.mu': must be a finite number, got inf",  # was accepted
        config("[muscle]\nmu = inf\n"),
    ),
    "config-section-not-a-table": (SWEEP, "config key 'mesh': must be a table", config("mesh = 3\n")),
    "config-invalid-toml": (SWEEP, "invalid TOML", config("[mesh\nh_far = 2.0\n")),
    "config-not-utf8": (SWEEP, "c.toml' is not UTF-8 text", config(b'name = "caf\xe9"\n')),  # said only "codec"
    "config-folder": ("sweep --quiet --out {tmp}/data.h5 --config {tmp}", "is a folder, not a TOML file", None),
    "config-theta-bound-400": (
        SWEEP,
        "theta must be in [-180, 180] deg, got 400.0",  # was stored as is
        config(bounds(theta="[0.0, 400.0]")),
    ),
    "config-bound-not-a-number": (
        SWEEP,
        "config key 'sweep.bounds.mu': must be two finite numbers",
        config(bounds(mu='["low", 0.002]')),
    ),
    "config-bounds-reversed": (
        SWEEP,
        "config key 'sweep.bounds.mu': low 0.002 > high 0.001",
        config(bounds(mu="[0.002, 0.001]")),
    ),
    "config-all-materials-held-out": (
        SWEEP,
        "config key 'sweep.n_test': must be in [0, n_materials)",
        config("[sweep]\nn_materials = 4\nn_test = 4\n"),
    ),
    "config-no-design": (
        SWEEP,
        "config key 'sweep.designs': must list at least one design",
        config("[sweep]\ndesigns = []\n"),
    ),
    "config-unknown-membrane-model": (
        SWEEP,
        "config key 'membrane.model': must be 'elastic' or 'rigid'",
        config('[membrane]\nmodel = "soft"\n'),
    ),
    # -- simulate, sweep, mesh
    "simulate-theta-400": (  # was stored as is
        f"{SIMULATE} --theta 400 --out {{out}}.h5",
        "theta must be in [-180, 180] deg, got 400.0",
        None,
    ),
    "simulate-k1-negative": (
        f"{SIMULATE.replace('0.017', '-0.017')} --theta 30 --out {{out}}.h5",
        "k1 must be >= 0 MPa",
        None,
    ),
    "simulate-out-not-h5": (f"{SIMULATE} --theta 30 --out {{out}}.csv", "--out must end in .h5", None),
    "sweep-shard-beyond-count": ("sweep --quiet --out {out}.h5 --shard 3/2", "--shard 3/2: need 0 <= i < n", None),
    "sweep-shard-not-i-of-n": ("sweep --quiet --out {out}.h5 --shard 3", "--shard must look like i/n", None),
    "sweep-ranks-per-sim-zero": (
        "sweep --quiet --out {out}.h5 --ranks-per-sim 0",
        "--ranks-per-sim 0 must divide the number of MPI ranks",
        None,
    ),
    "sweep-out-not-h5": ("sweep --quiet --out {out}.txt", "--out must end in .h5", None),
    "mesh-config-unknown": ("mesh --config {tmp}/none.toml", "config file '{tmp}/none.toml' does not exist", None),
    # -- DIC imports and figures
    "import-a-measurement": (f"{IMPORT} {{m}}", "is already a skinid measurement: use it directly", None),
    "import-empty-file": (
        f"{IMPORT} {{tmp}}/bad.txt",
        "format not recognised from the first line",
        file("bad.txt", ""),
    ),
    "import-alpha-nan": (f"{IMPORT.replace('0.05', 'nan')} " + str(DIC), "alpha must be two finite numbers", None),
    "import-t-beyond-one": (
        f"{IMPORT.replace('0.8', '1.5')} " + str(DIC),
        "--t: the load fraction t = 1.5 must be in (0, 1]",
        None,
    ),
    "show-t-without-alpha": (  # was ignored: the figure said nothing of t
        f"measurement show {DIC} --t 0.5 --out {{out}}.png",
        "--t is the load fraction of a design: give the design with --alpha",
        None,
    ),
    "show-measurement-with-alpha": (  # was ignored: the file's design was used
        "measurement show {m} --alpha 0.05 0.05 --out {out}.png",
        "is a skinid measurement: its design and load fraction are in it",
        None,
    ),
    "show-missing-file": (
        "measurement show {tmp}/none.csv --out {out}.png",
        "DIC file '{tmp}/none.csv' does not exist",
        None,
    ),
    "show-measurement-with-alpha-nan": (  # was plotted
        "measurement show {tmp}/bad.csv --out {out}.png",
        "alpha11 must be a finite number",
        measurement(lambda t: t.replace("# alpha11 = 0.05", "# alpha11 = nan")),
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_refused_in_one_line_before_computing(case, inputs, tmp_path, capsys):
    arguments, message, make = CASES[case]
    if make is not None:
        make(tmp_path, inputs)
    paths = {"data": inputs.data, "emu": inputs.emu, "m": inputs.m, "tmp": tmp_path, "out": tmp_path / "out"}
    before = snapshot(tmp_path, inputs.folder)
    code, err = run_here(shlex.split(arguments.format(**paths)), capsys)
    assert_refused(code, err, message.format(**paths))
    assert snapshot(tmp_path, inputs.folder) == before


@pytest.mark.parametrize(
    ("arguments", "prog"),
    [
        ("study noise --data {tmp}/none.h5 --designs 2", "skinid study noise"),
        (f"measurement show {DIC} --t 0.5", "skinid measurement show"),
    ],
)
def test_a_refusal_names_the_subcommand(arguments, prog, tmp_path, capsys):
    code, err = run_here([*shlex.split(arguments.format(tmp=tmp_path)), "--out", str(tmp_path / "out.png")], capsys)
    assert code == 2 and err.startswith(f"{prog}: error: "), err


def test_a_load_fraction_out_of_range_is_refused_before_the_export_is_read(tmp_path, capsys):
    from skinfem.cli import main

    code = main(shlex.split(IMPORT.replace("0.8", "0").format(out=tmp_path / "m")) + [str(DIC)])
    out, err = capsys.readouterr()
    assert code == 2 and "t = 0.0 must be in (0, 1]" in err
    assert out == ""  # no "read N rows of ..." line: the file was not read


# ---------------------------------------------------------------- outputs
# An existing output is refused before any computing unless --force (or --resume) is given, and so
# is an output whose folder cannot be written; the inputs must exist (paths are checked first) but
# are read later, so empty stand-ins do.

OUTPUTS = {  # command -> (its arguments before --out, the output's name)
    "simulate": (f"{SIMULATE} --theta 30", "run.h5"),
    "sweep": ("sweep --config small --quiet", "data.h5"),
    "merge": ("merge shard0.h5 shard1.h5", "data.h5"),
    "noise": ("noise --data data.h5 --length 1 --level 0.05", "noisy.h5"),
    "surrogate fit": ("surrogate fit --data data.h5", "emu"),
    "infer": ("infer --emulator emu --data data.h5 --material 0", "post"),
    "study test-set": ("study test-set --emulator emu --data data.h5 --designs 2", "study"),
    "study setups": ("study setups --emulator emu --data data.h5 --designs 2", "study"),
    "study noise": ("study noise --data data.h5 --designs 2", "study"),
    "check": ("check --config small --measurement m.csv --noise-sd 1e-4 1e-4 1e-4", "report"),
    "measurement import": (f"measurement import {DIC} --alpha 0.05 -0.02 --t 0.8", "m.csv"),
    "measurement show": (f"measurement show {DIC}", "m.png"),
}


def stand_in_inputs(folder: Path) -> None:
    """Empty files and a folder named as the inputs of :data:`OUTPUTS` (where no output is)."""
    for name in ("data.h5", "m.csv"):
        if not (folder / name).exists():
            (folder / name).write_bytes(b"")
    (folder / "emu").mkdir(exist_ok=True)


def run_output_case(arguments: str, out: Path, tmp_path: Path, capsys, monkeypatch) -> tuple[int, str]:
    """``skinid arguments --out out`` run in ``tmp_path`` (where the relative inputs are)."""
    monkeypatch.chdir(tmp_path)
    return run_here([*shlex.split(arguments), "--out", str(out)], capsys)


@pytest.mark.parametrize("command", list(OUTPUTS))
def test_an_existing_output_is_refused(command, tmp_path, capsys, monkeypatch):
    """Also: the sweep, refused after taking its lock, removes the lock."""
    arguments, name = OUTPUTS[command]
    out = tmp_path / name
    old_output(out)
    stand_in_inputs(tmp_path)
    before = snapshot(tmp_path)
    code, err = run_output_case(arguments, out, tmp_path, capsys, monkeypatch)
    assert_refused(code, err, f"error: {out} exists; pass --force to replace it")
    assert snapshot(tmp_path) == before  # no lock, temporary or partial file left


@pytest.mark.parametrize("command", ["simulate", "sweep", "surrogate fit", "infer", "noise"])
def test_an_output_in_a_file_is_refused(command, tmp_path, capsys, monkeypatch):
    arguments, name = OUTPUTS[command]
    stand_in_inputs(tmp_path)
    (tmp_path / "file").write_bytes(OLD_BYTES)
    before = snapshot(tmp_path)
    code, err = run_output_case(arguments, tmp_path / "file" / name, tmp_path, capsys, monkeypatch)
    assert_refused(code, err, f"'{tmp_path / 'file'}' is a file, not a folder")
    assert snapshot(tmp_path) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only folder: chmod cannot refuse it")
@pytest.mark.parametrize("command", ["simulate", "sweep", "surrogate fit", "study noise", "measurement import"])
def test_an_unwritable_folder_is_refused(command, tmp_path, capsys, monkeypatch):
    arguments, name = OUTPUTS[command]
    stand_in_inputs(tmp_path)
    folder = tmp_path / "read_only"
    folder.mkdir(mode=0o500)
    try:
        code, err = run_output_case(arguments, folder / "sub" / name, tmp_path, capsys, monkeypatch)
    finally:
        folder.chmod(0o700)
    assert_refused(code, err, f"'{folder}' is not writable")
    assert list(folder.iterdir()) == []


@pytest.mark.parametrize("command", ["sweep", "study test-set", "check"])
def test_force_and_resume_exclude_each_other(command, tmp_path, capsys, monkeypatch):
    arguments, name = OUTPUTS[command]
    stand_in_inputs(tmp_path)
    before = snapshot(tmp_path)
    code, err = run_output_case(f"{arguments} --force --resume", tmp_path / name, tmp_path, capsys, monkeypatch)
    assert_refused(code, err, "--resume completes an existing output and --force replaces it")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize(
    "fields, message",
    [
        ("fields.xdmf", "fields.h5 exists; pass --force to replace it"),  # the data file of fields.xdmf
        ("run.xdmf", "writes its data to"),  # the data file would be the --out file
    ],
)
def test_simulate_refuses_fields_that_exist_or_would_overwrite_out(fields, message, tmp_path, capsys, monkeypatch):
    old_output(tmp_path / "fields.h5")
    before = snapshot(tmp_path)
    code, err = run_output_case(
        f"{SIMULATE} --theta 30 --fields {tmp_path / fields}", tmp_path / "run.h5", tmp_path, capsys, monkeypatch
    )
    assert_refused(code, err, message)
    assert snapshot(tmp_path) == before


def test_surrogate_validate_refuses_to_replace_a_validation(tmp_path, capsys):
    old_output(tmp_path / "emu")
    (tmp_path / "emu" / "validation.json").write_bytes(OLD_BYTES)
    before = snapshot(tmp_path)
    code, err = run_here(["surrogate", "validate", "--emulator", str(tmp_path / "emu")], capsys)
    assert_refused(code, err, f"error: {tmp_path / 'emu' / 'validation.json'} exists; pass --force to replace it")
    assert snapshot(tmp_path) == before


# ---------------------------------------------------------------- two sweeps on one file


def test_a_second_sweep_to_the_same_output_is_refused(tmp_path, capsys):
    """Two identical sweeps started at once: the second finds the first's lock."""
    out, lock = tmp_path / "data.h5", tmp_path / "data.h5.lock"
    lock.write_text(f"{os.getpid()}\n")  # a sweep that runs: this process
    before = snapshot(tmp_path)
    code, err = run_here(["sweep", "--config", "small", "--out", str(out), "--resume", "--quiet"], capsys)
    assert_refused(code, err, f"{out} is being written by another sweep (PID {os.getpid()}")
    assert snapshot(tmp_path) == before


def test_a_stale_lock_is_reported_with_its_removal(tmp_path, capsys):
    import subprocess
    import sys

    out, lock = tmp_path / "data.h5", tmp_path / "data.h5.lock"
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait()
    lock.write_text(f"{ended.pid}\n")
    before = snapshot(tmp_path)
    code, err = run_here(["sweep", "--config", "small", "--out", str(out), "--quiet"], capsys)
    assert_refused(code, err, f"stale lock {lock} (PID {ended.pid} is not running)")
    assert f"rm '{lock}'" in err and snapshot(tmp_path) == before


# ---------------------------------------------------------------- in a new process: no PETSc list


@pytest.mark.parametrize(
    "arguments, message",
    [
        pytest.param(f"{SIMULATE} --theta 400 --out {{tmp}}/run.h5", "theta must be in [-180, 180] deg", id="simulate"),
        pytest.param(f"{CHECK} {{tmp}}/bad.csv", "strains in percent?", id="check"),
    ],
)
def test_a_refused_command_prints_no_petsc_options(arguments, message, tmp_path):
    """PETSc, loaded by the FE commands, would list at exit the options of the run that never
    happened ("WARNING! There are options you set that were not used!")."""
    measurement_of(grid(), strain=lambda xy: plausible_strain(xy, scale=100))(tmp_path, None)
    before = snapshot(tmp_path)
    res = skinid(*shlex.split(arguments.format(tmp=tmp_path, out=tmp_path / "out")))
    assert_refused(res.returncode, res.stderr, message)
    assert PETSC_WARNING not in res.stdout + res.stderr
    assert snapshot(tmp_path) == before


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="needs mpirun")
@pytest.mark.parametrize("case", ["corrupt mesh file", "mesh folder is a file"])
def test_a_bad_mesh_ends_every_rank_at_once_with_one_line(case, tmp_path):
    """Under mpirun -n 2 rank 0 reads (or writes) the mesh; when it cannot, every rank refuses
    together (it used to leave rank 1 waiting in the collective read forever)."""
    folder = tmp_path / "meshes"
    if case == "corrupt mesh file":
        assert skinid("mesh", "--config", "small", "--mesh-dir", folder).returncode == 0
        (msh,) = folder.glob("*.msh")
        msh.write_bytes(msh.read_bytes()[:3000])
        expected = "cannot be read"
    else:
        folder.write_text("not a folder")
        expected = "is a file, not a folder"
    args = ["--mu", 0.001, "--k1", 0.015, "--k2", 10, "--kappa", 0.28, "--theta", 30, "--alpha", 0.05, -0.05]
    command = skinid_command("simulate", "--mesh-dir", folder, *args, "--out", tmp_path / "x.h5", ranks=2)
    start = time.perf_counter()
    res = subprocess.run(command, capture_output=True, text=True, env=skinid_env(), timeout=120)
    assert res.returncode == 2 and time.perf_counter() - start < 60, res.stderr[-2000:]
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and expected in lines[0], res.stderr[-2000:]
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize(
    "arguments, message",
    [
        ("infer --emulator {tmp}/none --measurement {tmp}/m.csv --out {tmp}/p", "emulator directory '{tmp}/none'"),
        ("check --config small --measurement {tmp}/none.csv --out {tmp}/c", "measurement file '{tmp}/none.csv'"),
        ("study noise --data {tmp}/none.h5 --designs 0 --out {tmp}/s", "dataset '{tmp}/none.h5'"),
    ],
)
def test_a_missing_input_is_refused_before_torch_is_imported(arguments, message, tmp_path):
    """The inference commands import torch and Pyro (seconds); a mistyped path is refused first."""
    (tmp_path / "m.csv").write_text("")
    argv = shlex.split(arguments.format(tmp=tmp_path))
    script = (
        "import sys\nfrom skinfem.cli import main\n"
        f"code = main({argv!r})\nassert 'torch' not in sys.modules, 'torch imported'\nsys.exit(code)"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=skinid_env())
    assert_refused(res.returncode, res.stderr, f"{message.format(tmp=tmp_path)} does not exist")


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="needs mpirun")
def test_a_missing_input_under_mpi_is_one_line(tmp_path):
    res = skinid("check", "--config", "small", "--measurement", tmp_path / "none.csv", "--out", tmp_path / "c", ranks=2)
    assert_refused(res.returncode, res.stderr, f"measurement file '{tmp_path}/none.csv' does not exist")
