"""Command line of the surrogate: ``skinid surrogate fit|validate`` (no FEniCSx needed)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from skinfem.cli import ROUTES, CommandParser, add_command, add_output, add_pca_scaling, refuse


def build_parser() -> CommandParser:
    parser = CommandParser(prog="skinid surrogate", description=ROUTES["surrogate"][1])
    sub = parser.add_subparsers(dest="action", required=True)
    p = add_command(sub, "fit", "fit PCA + GPs on a dataset's training materials")
    p.add_argument("--data", type=Path, required=True, help="dataset (.h5)")
    add_output(p, "emulator directory")
    p.add_argument(
        "--components", nargs="+", default=["xx", "yy"], choices=["xx", "yy", "xy"], help="strain components to emulate"
    )
    group = p.add_mutually_exclusive_group()
    group.add_argument("--variance", type=float, default=0.99, help="explained variance to keep")
    group.add_argument("--n-components", type=int, help="fixed number of PCs per component")
    add_pca_scaling(p)
    p.add_argument("--gp-fraction", type=float, default=0.1, help="share of training rows for the GPs (paper: 0.1)")
    p.add_argument("--max-gp-rows", type=int, help="cap on GP training rows")
    p.add_argument("--restarts", type=int, default=2, help="optimizer restarts per GP")
    p.add_argument("--seed", type=int, default=0, help="random seed (GP rows, optimizer starts)")
    p.add_argument(
        "--cv-folds",
        type=int,
        default=5,
        help="folds of training materials in the error model's cross-validation "
        "(as many as training materials: leave one material out)",
    )
    p.add_argument("--no-validate", action="store_true", help="skip validation on the test materials")
    p = add_command(sub, "validate", "R² per PC and field errors on held-out materials")
    p.add_argument(
        "--emulator",
        type=Path,
        required=True,
        help="emulator directory (validation.json and validation.png are written into it)",
    )
    p.add_argument("--data", type=Path, help="dataset (default: the one it was fitted on)")
    p.add_argument("--force", action="store_true", help="replace the emulator's validation if it has one")
    return parser


def print_report(report, directory: Path) -> None:
    """Scores of a :class:`surrogate.validation.ValidationReport` per component."""
    for c, r in report.components.items():
        r2 = ", ".join(f"{v:.4f}" for v in r.r2_per_pc)
        print(
            f"E_{c}: R² per PC [{r2}]; field RMSE {r.field_rmse:.2e} "
            f"({100 * r.field_rmse_relative:.2f} % of RMS strain; PCA floor {r.pca_floor_rmse:.2e})"
        )
    print(f"wrote {directory / 'validation.json'} and {directory / 'validation.png'}")


def check_fit_options(args) -> None:
    """Refuse fitting options out of range (before the dataset is read)."""
    if args.n_components is not None and args.n_components < 1:
        raise ValueError(f"--n-components must be >= 1, got {args.n_components}")
    if not 0 < args.variance < 1:
        raise ValueError(f"--variance must be in (0, 1), got {args.variance}")
    if not 0 < args.gp_fraction <= 1:
        raise ValueError(f"--gp-fraction must be in (0, 1], got {args.gp_fraction}")
    if args.max_gp_rows is not None and args.max_gp_rows < 2:
        raise ValueError(f"--max-gp-rows must be >= 2, got {args.max_gp_rows}")
    if args.restarts < 0:
        raise ValueError(f"--restarts must be >= 0, got {args.restarts}")
    if args.cv_folds < 2:
        raise ValueError(f"--cv-folds must be >= 2, got {args.cv_folds}")


def cmd_fit(args) -> None:
    """Fit, then write the emulator directory (with its validation) under a temporary name."""
    from skinfem.io import StrainDataset
    from skinfem.outputs import check_output, write_atomically
    from surrogate.emulator import fit_emulator
    from surrogate.validation import plot_explained_variance, validate_directory

    check_output(args.out, args.force, directory=True)
    check_fit_options(args)
    data = StrainDataset.open(args.data)
    start = time.perf_counter()
    emulator = fit_emulator(
        data,
        components=tuple(args.components),
        n_components=args.variance if args.n_components is None else args.n_components,
        pca_scaling=args.pca_scaling,
        gp_fraction=args.gp_fraction,
        max_gp_rows=args.max_gp_rows,
        restarts=args.restarts,
        seed=args.seed,
        cv_folds=args.cv_folds,
    )
    print(
        f"fitted {sum(emulator.n_weights.values())} GPs ({emulator.n_weights}) on "
        f"{emulator.provenance.n_gp_rows} of {emulator.provenance.n_training_rows} training rows "
        f"in {time.perf_counter() - start:.1f} s"
    )

    reports = []  # the validation report, unless --no-validate

    def write(tmp: Path) -> None:
        emulator.save(tmp)
        plot_explained_variance(emulator, tmp / "explained_variance.png")
        if not args.no_validate:
            reports.append(validate_directory(tmp, args.data))

    write_atomically(args.out, write)
    print(f"wrote {args.out}")
    for report in reports:
        print_report(report, args.out)


def cmd_validate(args) -> None:
    from skinfem.outputs import check_output
    from surrogate.validation import validate_directory

    check_output(args.emulator / "validation.json", args.force)
    print_report(validate_directory(args.emulator, args.data), args.emulator)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "surrogate":
        argv = argv[1:]
    args = build_parser().parse_args(argv)
    try:
        {"fit": cmd_fit, "validate": cmd_validate}[args.action](args)
    except (ValueError, FileNotFoundError) as exc:
        return refuse(f"skinid surrogate {args.action}", exc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
