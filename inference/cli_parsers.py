"""Command line of inference: ``skinid infer``, ``noise``, ``study``, ``check``, ``measurement``.

The parsers only: :mod:`inference.__main__` runs the commands."""

from __future__ import annotations

import argparse
from pathlib import Path

from skinfem.cli import ROUTES, CommandParser, add_command, add_design, add_output, add_pca_scaling, add_renamed_option
from skinfem.mesh import DEFAULT_MESH_DIR


def _add_sampler(p: argparse.ArgumentParser) -> None:
    p.add_argument("--chains", type=int, default=4, help="NUTS chains")
    p.add_argument("--warmup", type=int, default=500, help="warm-up (adaptation) steps per chain")
    p.add_argument("--draws", type=int, default=1000, help="draws per chain after the warm-up")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--jobs", type=int, default=2, help="chains run in parallel (processes)")
    p.add_argument(
        "--gp-variance",
        choices=["exact", "mode"],
        default="mode",
        help="mode: the GP covariance fixed at the posterior mode (fast; coverage measured on it); "
        "exact: evaluated at every step",
    )
    p.add_argument(
        "--emulator-error",
        choices=["auto", "on", "scaled", "shift", "off"],  # "auto" + inference.studies.EMULATOR_ERRORS
        default="auto",
        help="carry the emulator's held-out error and PCA truncation in the likelihood (on), that "
        "error times a sampled material scale (scaled), the error as a shift of the parameters "
        "shared by every observation (shift), or the GP variance only (off); auto: shift when the "
        "emulator fitted it, else on",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def build_parser(prog: str) -> argparse.ArgumentParser:
    """The parser of ``skinid <command>`` for ``prog`` ending in infer, noise, check, measurement or study."""
    command = next(name for name in PARSERS if prog.endswith(name))
    parser = CommandParser(prog=prog, description=ROUTES[command][1])
    PARSERS[command](parser)
    return parser


def _infer_parser(parser: argparse.ArgumentParser) -> None:
    """``skinid infer``: the posterior of one material or of measurements."""
    parser.add_argument("--emulator", type=Path, required=True, help="emulator directory")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="dataset (.h5): observe one of its materials")
    src.add_argument("--measurement", type=Path, nargs="+", help="measurement CSV file(s)")
    parser.add_argument("--material", type=int, help="with --data: material index")
    parser.add_argument(
        "--designs",
        help="with --data: design indices ('2', '0,2,4') or eigen-strains ('--designs=0.05,-0.05') (default: all)",
    )
    parser.add_argument(
        "--frames",
        help="with --data: frame indices, e.g. --frames -1; a list needs the '=': --frames=-3,-2,-1 (default: -1)",
    )
    parser.add_argument(
        "--noise",
        choices=["halfcauchy", "known"],
        default="halfcauchy",
        help="halfcauchy: an unknown sd per strain component, sampled; known: the measurement files' "
        "sd_exx, sd_eyy, sd_exy columns",
    )
    add_output(parser, "output directory")
    _add_sampler(parser)


def _noise_parser(parser: argparse.ArgumentParser) -> None:
    """``skinid noise``: a dataset with spatially correlated noise added."""
    parser.add_argument("--data", type=Path, required=True, help="clean dataset (.h5)")
    parser.add_argument("--length", type=float, required=True, help="correlation length [mm]")
    parser.add_argument(
        "--level", type=float, required=True, help="noise sd as a fraction of the max |strain| of the training data"
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    add_output(parser, "noisy dataset (.h5)")


def _check_parser(parser: argparse.ArgumentParser) -> None:
    """``skinid check``: model criticism of measurements against the FE model."""
    parser.add_argument("--measurement", type=Path, nargs="+", required=True, help="measurement CSV file(s)")
    parser.add_argument(
        "--config",
        help="preset or TOML of the mesh the check runs on (needed without --emulator; default: the "
        "emulator's dataset configuration; for measurements of real skin: check)",
    )
    start = parser.add_mutually_exclusive_group()
    start.add_argument(
        "--emulator",
        type=Path,
        help="emulator directory: its posterior mode is the start (default: the best of 5 spread points)",
    )
    start.add_argument(
        "--start",
        type=float,
        nargs=5,
        metavar=("MU", "K1", "K2", "KAPPA", "THETA"),
        help="skin parameters to start the calibration from (MPa, MPa, -, -, deg; "
        "default: the best of 5 spread points)",
    )
    add_output(parser, "report directory (its fe_runs/ keeps finished FE runs for --resume)", resumable=True)
    parser.add_argument(
        "--noise-sd",
        type=float,
        nargs=3,
        metavar=("XX", "YY", "XY"),
        help="measurement noise sd per component [strain] (default: the files' sd columns)",
    )
    parser.add_argument(
        "--noise-length", type=float, default=0.0, help="noise correlation length [mm] (0: independent points)"
    )
    parser.add_argument(
        "--noise-nugget", type=float, default=0.0, help="uncorrelated share of the noise variance in [0, 1]"
    )
    parser.add_argument(
        "--dic-window", type=float, default=1.0, help="the DIC strain window (virtual strain gauge) side [mm]"
    )
    parser.add_argument(
        "--spacing", type=float, default=1.0, help="thin the measured points to one per square of this side [mm]"
    )
    parser.add_argument(
        "--no-discretisation",
        action="store_true",
        help="skip the refined-mesh estimate of the check's discretisation error",
    )
    parser.add_argument(
        "--refine",
        choices=["auto", "uniform", "edge", "quadratic", "converged"],
        default="auto",
        help="the estimate's better mesh: every size halved, or only the membrane-edge "
        "cells (for fine or quadratic meshes), layers doubled in both; or a quadratic reference mesh "
        "for a linear mesh (Q2, 1 mm edge cells, 0.32 of its error; converged: 0.5 mm, dearer, 0.14). "
        "auto: edge for a quadratic mesh or one refined at the membrane edge, converged for a linear "
        "mesh with edge cells under 1 mm (paper), else uniform",
    )
    parser.add_argument(
        "--mesh-drift",
        action="store_true",
        help="let the mesh-error correction follow the parameters to first order (both meshes' exact "
        "sensitivities at the baseline; for candidates that move the model far, e.g. a thicker skin)",
    )
    effects = "pre_stretch, muscle_stiffness, skin_thickness, compressibility, bonding"  # skinfem.effects.EFFECTS
    parser.add_argument("--candidates", nargs="+", help=f"effects to test, of {effects} (default: all)")
    parser.add_argument("--add", nargs="+", default=[], help=f"effects to add, in order, of {effects}")
    parser.add_argument("--increments", type=int, help="load increments of the FE runs (default: config's)")
    parser.add_argument(
        "--confirm", type=int, default=2, help="top-ranked candidates recalibrated with full FE runs, per round"
    )
    parser.add_argument("--mesh-dir", type=Path, default=DEFAULT_MESH_DIR, help="mesh directory")
    parser.add_argument("--quiet", action="store_true", help="no progress lines (phases, calibration steps) on stderr")


def _measurement_parser(parser: argparse.ArgumentParser) -> None:
    """``skinid measurement import|show``: DIC exports."""
    sub = parser.add_subparsers(dest="action", required=True)
    p = add_command(sub, "import", "a DIC export -> a measurement CSV (membrane frame, mm, log strain)")
    p.add_argument("file", type=Path, help="DIC export (VIC, DaVis, DICe or a table)")
    _add_dic_import(p)
    add_design(p, "the membrane design (alpha11, alpha22)", required=True)
    p.add_argument("--t", type=float, required=True, help="load fraction of this image, in (0, 1]")
    p.add_argument("--no-check", action="store_true", help="skip the plausibility check (not recommended)")
    add_output(p, "measurement CSV to write")
    p = add_command(sub, "show", "plot an imported field (exx, eyy, exy maps, membrane outline)")
    p.add_argument("file", type=Path, help="DIC export, or a skinid measurement CSV")
    _add_dic_import(p)
    add_design(p, "the membrane design: report the plausibility check on the figure")
    p.add_argument("--t", type=float, help="with --alpha: load fraction of this image, in (0, 1] (default: 1)")
    add_output(p, "figure (.png)")


def _study_command(sub, name: str, help: str, data: str, emulator: bool = True) -> argparse.ArgumentParser:
    """One ``skinid study`` command with its inputs: the emulator (when it takes one) and a dataset."""
    p = add_command(sub, name, help)
    if emulator:
        p.add_argument("--emulator", type=Path, required=True, help="emulator directory")
    p.add_argument("--data", type=Path, required=True, help=data)
    return p


def _study_outputs(
    p: argparse.ArgumentParser, materials: str = "subset of materials (default: the test split)"
) -> None:
    """The options every study ends with: its materials, its (resumable) directory, the sampler."""
    p.add_argument("--materials", help=materials)
    add_output(p, "study directory", resumable=True)
    _add_sampler(p)


def _study_parser(parser: argparse.ArgumentParser) -> None:
    """``skinid study test-set|setups|coverage|noise``: many posteriors.

    Declarative, longer than a screen: one block of options per study.
    """
    sub = parser.add_subparsers(dest="study", required=True)
    p = _study_command(sub, "test-set", "posteriors of every test material for one setup", "dataset (.h5)")
    p.add_argument(
        "--designs",
        required=True,
        help="design indices ('2', '7,6,13') or eigen-strain pairs ('--designs=0.05,-0.05,-0.05,0.05')",
    )
    p.add_argument(
        "--frames",
        default="-1",
        help="frame indices, e.g. --frames -1; a list needs the '=': --frames=-3,-2,-1",
    )
    _study_outputs(p)
    p = _study_command(sub, "setups", "single vs multi-frame vs multi-membrane (the paper's Fig. 8)", "dataset (.h5)")
    add_renamed_option(
        p,
        "--designs",
        old="--design",
        required=True,
        help="the single design: index ('7') or eigen-strains ('--designs=0.05,-0.05')",
    )
    p.add_argument("--n", type=int, default=3, help="frames / membranes in the multi setups")
    p.add_argument(
        "--others",
        help="the multi-membrane setup's other designs, e.g. '0,13' or '-0.05,0.05,0.05,0.05' "
        "(default: the n - 1 designs farthest apart in alpha)",
    )
    _study_outputs(p)
    p = _study_command(
        sub,
        "coverage",
        "coverage of the 50 %% / 95 %% intervals and truth ranks over many held-out cases (inference.coverage)",
        "dataset (.h5) of test materials (its test split), on the emulator's mesh",
    )
    p.add_argument(
        "--setup",
        choices=["single", "frames", "membranes"],
        default="single",
        help="the last frame of one design, its last --n frames, or --n designs",
    )
    p.add_argument("--n", type=int, default=3, help="frames / membranes of the multi setups")
    p.add_argument(
        "--noise-sd",
        type=float,
        default=0.0,
        help="independent noise sd added and stated [strain] (0: noise-free, unknown noise)",
    )
    p.add_argument("--noise-seeds", type=int, default=1, help="noise draws per material and design")
    p.add_argument(
        "--starts",
        type=int,
        help="starting designs per material, rotating with the material (default: all; 1: independent cases)",
    )
    p.add_argument(
        "--data-from",
        choices=["fe", "model"],
        default="fe",
        help="the test materials' FE strains, or truths from the prior and PC weights from the posterior's own "
        "model (calibrated by construction: tests the sampler; needs --noise-sd > 0)",
    )
    _study_outputs(p)
    p = _study_command(
        sub,
        "noise",
        "the paper's 9 noise cases: PCA, GP R², test-set posteriors",
        "clean dataset (.h5)",
        emulator=False,
    )
    add_renamed_option(
        p,
        "--designs",
        old="--design",
        required=True,
        help="the design observed (last frame): index ('7') or eigen-strains ('--designs=0.05,-0.05')",
    )
    p.add_argument("--lengths", type=float, nargs="+", default=[0.1, 1.0, 5.0], help="noise correlation lengths [mm]")
    p.add_argument(
        "--levels",
        type=float,
        nargs="+",
        default=[0.01, 0.05, 0.10],
        help="noise sds as fractions of the max |strain| of the training data",
    )
    p.add_argument("--gp-fraction", type=float, default=0.1, help="share of training rows for the GPs")
    p.add_argument("--restarts", type=int, default=2, help="optimizer restarts per GP")
    add_pca_scaling(p)
    p.add_argument(
        "--n-components",
        type=int,
        help="PCs per component in every case (default: the clean case keeps 99 %% of the variance, "
        "the noisy cases as many)",
    )
    _study_outputs(p, "subset of test materials (default: the test split)")


PARSERS = {
    "infer": _infer_parser,
    "noise": _noise_parser,
    "check": _check_parser,
    "measurement": _measurement_parser,
    "study": _study_parser,
}


def _add_dic_import(p: argparse.ArgumentParser) -> None:
    """Options of ``skinid measurement import|show`` that say how to read a DIC export."""
    from inference.dic_readers import FORMATS

    p.add_argument("--format", choices=["auto", *FORMATS], default="auto", help="export format (auto: detect)")
    p.add_argument("--mm-per-px", type=float, help="image scale [mm/px] (needed for pixel coordinates)")
    p.add_argument(
        "--centre",
        type=float,
        nargs=2,
        default=[0.0, 0.0],
        metavar=("X", "Y"),
        help="membrane centre in the file's coordinates (file units)",
    )
    p.add_argument(
        "--rotation",
        type=float,
        default=0.0,
        help="angle [deg] from the file's x axis to the membrane's x (alpha11) axis, towards file y",
    )
    p.add_argument(
        "--flip-y",
        action="store_true",
        help="the file's y axis points down (image coordinates): mirror it into the membrane frame",
    )
    p.add_argument(
        "--strain",
        choices=["log", "green", "engineering"],
        help="strain measure, when the file does not state it (green = Lagrange)",
    )
    p.add_argument("--percent", action="store_true", help="strains are in percent")
    p.add_argument("--config", default="small", help="preset or TOML giving the membrane and block sizes")
    table = p.add_argument_group("--format table")
    table.add_argument("--delimiter", help="field separator, e.g. ';', ',', tab (default: detect)")
    table.add_argument("--decimal", choices=[".", ","], help="decimal mark (default: detect)")
    table.add_argument("--encoding", help="text encoding (default: BOM, UTF-8, else Latin-1)")
    table.add_argument(
        "--columns",
        nargs=5,
        metavar=("X", "Y", "EXX", "EYY", "EXY"),
        help="names of the coordinate and strain (tensor shear) columns",
    )
    table.add_argument("--units", choices=["mm", "px"], help="coordinate unit when the header does not say")
    table.add_argument("--missing", nargs="+", default=[], help="extra missing-value markers, e.g. 'n. def.'")
    table.add_argument("--skip", type=int, default=0, help="lines before the header to skip")
