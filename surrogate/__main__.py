"""Command line of the surrogate: ``skinid surrogate fit|validate`` (no FEniCSx needed)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="skinid surrogate", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="action", required=True)
    p = sub.add_parser("fit", help="fit PCA + GPs on a dataset's training materials")
    p.add_argument("--data", type=Path, required=True, help="dataset (.h5)")
    p.add_argument("--out", type=Path, required=True, help="emulator directory")
    p.add_argument("--components", nargs="+", default=["xx", "yy"], choices=["xx", "yy", "xy"])
    group = p.add_mutually_exclusive_group()
    group.add_argument("--variance", type=float, default=0.99, help="explained variance to keep (default 0.99)")
    group.add_argument("--n-components", type=int, help="fixed number of PCs per component")
    p.add_argument("--gp-fraction", type=float, default=0.1, help="share of training rows for the GPs (paper: 0.1)")
    p.add_argument("--max-gp-rows", type=int, help="cap on GP training rows")
    p.add_argument("--restarts", type=int, default=2, help="optimizer restarts per GP")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-validate", action="store_true", help="skip validation on the test materials")
    p = sub.add_parser("validate", help="R² per PC and field errors on held-out materials")
    p.add_argument("--emulator", type=Path, required=True, help="emulator directory")
    p.add_argument("--data", type=Path, help="dataset (default: the one it was fitted on)")
    return parser


def print_report(report: dict, directory: Path) -> None:
    for c, r in report["components"].items():
        r2 = ", ".join(f"{v:.4f}" for v in r["r2_per_pc"])
        print(
            f"E_{c}: R² per PC [{r2}]; field RMSE {r['field_rmse']:.2e} "
            f"({100 * r['field_rmse_relative']:.2f} % of RMS strain; PCA floor {r['pca_floor_rmse']:.2e})"
        )
    print(f"wrote {directory / 'validation.json'} and {directory / 'validation.png'}")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "surrogate":
        argv = argv[1:]
    args = build_parser().parse_args(argv)
    try:
        from skinfem.io import StrainDataset
        from surrogate.emulator import fit_emulator
        from surrogate.validation import plot_explained_variance, validate_directory

        if args.action == "fit":
            data = StrainDataset.open(args.data)
            start = time.perf_counter()
            emulator = fit_emulator(
                data,
                components=tuple(args.components),
                n_components=args.n_components or args.variance,
                gp_fraction=args.gp_fraction,
                max_gp_rows=args.max_gp_rows,
                restarts=args.restarts,
                seed=args.seed,
            )
            emulator.save(args.out)
            plot_explained_variance(emulator, args.out / "explained_variance.png")
            print(
                f"fitted {sum(emulator.n_weights.values())} GPs ({emulator.n_weights}) on "
                f"{emulator.provenance.n_gp_rows} of {emulator.provenance.n_training_rows} training rows "
                f"in {time.perf_counter() - start:.1f} s\nwrote {args.out}"
            )
            if not args.no_validate:
                print_report(validate_directory(args.out, args.data), args.out)
        else:
            print_report(validate_directory(args.emulator, args.data), args.emulator)
    except (ValueError, FileNotFoundError) as exc:
        print(f"skinid surrogate {args.action}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
