"""Model-criticism benchmark on independent data: verdicts over noise seeds, and their cost.

    mpirun -n 2 python benchmarks/criticism.py [--config small] [--cases none pre_stretch ...]
                                               [--seeds 5] [--out out/criticism_bench]

Data the checked model did not make: quadratic elements (Q2) on a mesh graded differently from
``small`` (far size 4 mm, 3 muscle layers), one material (mu 1.2e-3 MPa, k1 0.017 MPa, k2 11,
kappa 0.285, theta 30 deg), two membranes ((0.05, 0.05), (0.05, -0.05)), measured like DIC
(1 mm strain window) at a jittered 1 mm point cloud with three holes over +-18 mm, plus
correlated noise (sd 1e-3, 2 mm, 30 % uncorrelated), one noise draw per seed. Cases: no hidden
effect, or one hidden effect (pre-stretch 1.08 x 1.02 at 30 deg, muscle 2x stiffer, skin 1.5x
thicker). Each (case, seed) is one ``skinid check`` with the discretisation estimate and the
true effect added as a version (``--add``), so that the RMSE after adding it is measured too.

Resumable: every finished check leaves ``<out>/<case>_<seed>/row.json``; a rerun skips them,
and ``--summarise`` tabulates the finished ones without running more.
Writes the confusion table (true effect vs verdict), the true effect's rank, RMSE before and
after adding it, seconds and FE runs to benchmarks/results/criticism.json. Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "criticism.json"
TRUTH = (1.2e-3, 0.017, 11.0, 0.285, 30.0)
DESIGNS = [(0.05, 0.05), (0.05, -0.05)]
NOISE = dict(sd=np.full(3, 1e-3), length=2.0, nugget=0.3)


def hidden_effects() -> dict[str, dict[str, float]]:
    from skinfem.effects import prestretch_log_strain

    return {
        "none": {},
        "pre_stretch": {f"pre_stretch.{k}": v for k, v in prestretch_log_strain(1.08, 1.02, 30.0).items()},
        "muscle_stiffness": {"muscle_stiffness.log_factor": float(np.log(2.0))},
        "skin_thickness": {"skin_thickness.log_factor": float(np.log(1.5))},
    }


def data_config(config):
    return config.with_changes(mesh={"h_far": 4.0, "muscle_layers": 3},
                               solver={"element_degree": 2, "quadrature_degree": 4})


def verdict_class(report: dict) -> str:
    best = next((c["effect"] for c in report["candidates"] if c["explains"]), None)
    if best is not None:
        return best
    return "no missing effect" if not report["versions"][0]["metrics"]["structured"] else "none explains"


def run_case(case: str, seed: int, fields, points, args, comm) -> dict:
    """One check; returns its row (rank 0) and writes it, with the report, to out/case_seed."""
    from inference.__main__ import main as skinid

    from inference.criticism import NoiseModel
    from inference.synthetic import write_noisy

    folder = args.out / f"{case}_{seed}"
    files = None
    if comm.rank == 0:
        files = write_noisy(fields, points, DESIGNS, NoiseModel(**NOISE), folder / "m", seed)
    files = comm.bcast(files)
    add = [] if case == "none" else ["--add", case]
    start = time.perf_counter()
    code = skinid(["check", "--config", args.config, "--measurement", *map(str, files), "--out", str(folder / "report"),
                   "--noise-length", "2", "--noise-nugget", "0.3", "--increments", "2", "--confirm", "1",
                   "--spacing", "2", "--mesh-dir", str(args.mesh_dir), *add])
    seconds = time.perf_counter() - start
    if comm.rank or code:
        return {}
    report = json.loads((folder / "report" / "report.json").read_text())
    effects = [c["effect"] for c in report["candidates"]]
    t = report["timings"]
    row = {"case": case, "seed": seed, "verdict": verdict_class(report),
           "rank_of_true_effect": effects.index(case) + 1 if case in effects else None,
           "rmse_baseline": report["versions"][0]["metrics"]["rmse"],
           "rmse_with_true_effect": report["versions"][-1]["metrics"]["rmse"] if add else None,
           "noise_rms": report["versions"][0]["metrics"]["noise_rms"],
           "discretisation_sigma": report["discretisation"]["sigma"],
           "failed_runs": len(report["failed_runs"]), "seconds": seconds,
           "fe_runs": t["compare_fe_runs"] + t["diagnose_fe_runs"] + t["add_fe_runs"]}
    (folder / "row.json").write_text(json.dumps(row, indent=2) + "\n")
    return row


def main() -> None:
    import skinfem.model  # noqa: F401  (PETSc initialises collectively: import on every rank first)
    from inference.synthetic import dic_points, measured_fields
    from skinfem.config import load_config
    from skinfem.params import SkinParams

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small", help="the checked mesh (preset or TOML)")
    parser.add_argument("--cases", nargs="+", default=list(hidden_effects()))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("out/criticism_bench"))
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--summarise", action="store_true", help="only tabulate the finished checks")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    points = dic_points(18.0, 1.0, np.random.default_rng(0))
    config = data_config(load_config(args.config))
    rows = []
    for case in args.cases:
        todo = [] if args.summarise else [s for s in range(args.seeds)
                                          if not (args.out / f"{case}_{s}" / "row.json").exists()]
        fields = None
        if todo and comm.rank == 0:
            fields = measured_fields(config, SkinParams(*TRUTH), DESIGNS, points, hidden_effects()[case],
                                     args.mesh_dir, increments=2)
        for seed in todo:
            run_case(case, seed, fields, points, args, comm)
        rows += [json.loads((args.out / f"{case}_{s}" / "row.json").read_text()) for s in range(args.seeds)
                 if (args.out / f"{case}_{s}" / "row.json").exists()]
    if comm.rank == 0:
        confusion: dict[str, dict[str, int]] = {}
        for row in rows:
            confusion.setdefault(row["case"], {}).setdefault(row["verdict"], 0)
            confusion[row["case"]][row["verdict"]] += 1
        command = (f"mpirun -n 2 python benchmarks/criticism.py --config {args.config} --cases {' '.join(args.cases)} "
                   f"--seeds {args.seeds}")
        RESULTS.write_text(json.dumps({"command": command,
                                       "checked_config": args.config, "data": "Q2, h 2/4 mm, 3 muscle layers",
                                       "noise": {"sd": NOISE["sd"].tolist(), "length_mm": 2.0, "nugget": 0.3},
                                       "confusion": confusion, "rows": rows}, indent=2) + "\n")
        for case, verdicts in confusion.items():
            print(f"{case:>17}: {verdicts}")


if __name__ == "__main__":
    main()
