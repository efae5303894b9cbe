"""Is a hidden effect that the check does not see compensated, or missed by where its fit starts?

    mpirun -n 2 python benchmarks/criticism_basin.py --case skin_thickness --seeds 0 1 2 3 4
                                                     [--folder out/crit_check_limit]
                                                     [--config check] [--refine edge]
                                                     [--results benchmarks/results/criticism_basin.json]

For checks that :mod:`criticism` (``benchmarks/criticism.py --start centre``) has run and kept
in ``<folder>/<case>_<seed>``: the check's baseline and mesh-error correction are rebuilt from its
kept FE runs (the same measurement files and options, so the runs are read, not repeated), and
the model with the case's true effect added is calibrated twice, on the same whitened data and
carried mesh error:

- *from the baseline* (the check's own version: the effect at its null value, the skin
  parameters at the baseline's compensated values),
- *from the truth* (the skin parameters and the effect at the values that made the data;
  the mesh-error amplitude at the baseline's).

If the fit from the truth stays near the truth at a clearly lower chi^2, the check's fit was
held in the baseline's basin by its start; if it leaves the truth for a point of about the
baseline's chi^2, the data on this mesh prefer the compensated material, and the effect is not
identifiable there. Also recorded: chi^2 at the true point itself. Recorded, not asserted;
results keyed by case and seed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent


def fit_summary(cal) -> dict:
    """chi^2, FE runs and the fitted free parameters of a calibration."""
    return {
        "chi2": cal.chi2,
        "fe_runs": cal.fe_runs,
        "rejected_steps": len(cal.rejected),
        "estimates": {n: {"value": e.value, "sd": e.sd} for n, e in cal.estimates().items()},
    }


def basin(case: str, case_folder: Path, args, comm) -> dict:
    """Both fits of ``case``'s true effect for one kept check (see the module docstring)."""
    from criticism import TRUTH, check_argv, hidden_effects, true_effects

    from inference.__main__ import check_inputs
    from inference.cli_parsers import build_parser
    from inference.criticism.calibration import calibrate
    from inference.criticism.check import CheckTimings, PhaseWork, compare, refined_forward, starting_point
    from inference.criticism.data import Data
    from inference.criticism.diagnosis import check_noise_statement, extend
    from inference.forward import FEForward
    from skinfem.effects import get_effect

    files = sorted((case_folder / "m").glob("m_*.csv"))
    argv = check_argv(files, case_folder, [], args)[1:]  # the check's own options, so its FE runs are read
    settings, config, bounds, _, measurements, noise = check_inputs(build_parser("skinid check").parse_args(argv))
    cache = case_folder / "report" / "fe_runs"
    forward = FEForward(config, measurements, bounds, args.mesh_dir, settings.increments, comm, cache, settings.gauge)
    data = Data.from_points(measurements, noise)
    start, _ = starting_point(forward, data, settings, None, measurements)
    refined = refined_forward(forward, measurements, bounds, (args.mesh_dir, comm, cache), settings)
    model, data, baseline, _ = compare(forward, refined, data, start, settings, CheckTimings(), PhaseWork())
    baseline, data, statement = check_noise_statement(model, baseline, data, settings.membrane(config))
    (effect,) = true_effects(case)
    hidden = hidden_effects()[case]
    from_baseline = extend(model, baseline, data, effect, max_iterations=settings.max_iterations)
    truth = baseline.x.copy()
    truth[:5] = TRUTH
    truth[model.index(list(hidden))] = list(hidden.values())
    added = model.index(get_effect(effect).qualified_names())
    (at_truth,) = model.evaluate_many([truth])
    from_truth = calibrate(
        model, data, truth, baseline.free + added, label=f"truth + {effect}", max_iterations=settings.max_iterations
    )
    return {
        "noise_factor": statement.factor,
        "baseline": fit_summary(baseline),
        "chi2_at_truth": None if at_truth is None else float(np.nansum(data.whitened_residual(at_truth) ** 2)),
        "from_baseline": fit_summary(from_baseline),
        "from_truth": fit_summary(from_truth),
        "n_data": int(data.n),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="skin_thickness")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--folder", type=Path, default=Path("out/crit_check_limit"))
    parser.add_argument("--config", default="check")
    parser.add_argument("--refine", default="edge")
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--mesh-drift", action="store_true", help="as the checks were run with it")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "criticism_basin.json")
    parser.set_defaults(start="centre", confirm=1)  # the checks this rebuilds: box-centre start, one full fit
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    results = json.loads(args.results.read_text()) if args.results.exists() else {}
    for seed in args.seeds:
        key = f"{args.case}_{seed}"
        if key in results:
            continue
        row = basin(args.case, args.folder / key, args, comm)
        if comm.rank == 0:
            results[key] = {"config": args.config, "refine": args.refine, "data_folder": str(args.folder), **row}
            args.results.write_text(json.dumps(results, indent=2) + "\n")
            b, t = row["from_baseline"]["chi2"], row["from_truth"]["chi2"]
            print(f"{key}: chi2 from the baseline {b:.1f}, from the truth {t:.1f} (at it {row['chi2_at_truth']:.1f})")


if __name__ == "__main__":
    main()
