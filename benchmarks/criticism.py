"""Model-criticism benchmark on independent data: verdicts over noise seeds, and their cost.

    mpirun -n 2 python benchmarks/criticism.py [--config small] [--cases none pre_stretch ...]
                                               [--seeds 5] [--out out/criticism_bench]
                                               [--data q2 | q2-edge] [--refine uniform | edge]
                                               [--start spread | centre] [--results FILE]

Data the checked model did not make: quadratic elements (Q2) on a mesh graded differently from
``small`` (far size 4 mm, 3 muscle layers; ``--data q2-edge``: also two skin layers and 0.5 mm
cells at the membrane edge, finer than the quadratic check mesh
``benchmarks/configs/small_q2.toml``), one material (mu 1.2e-3 MPa, k1 0.017 MPa, k2 11,
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


DATA_MESHES = {  # changes to the small preset
    "q2": {"h_far": 4.0, "muscle_layers": 3},
    "q2-edge": {"h_far": 4.0, "muscle_layers": 3, "skin_layers": 2, "h_edge": 0.5},
}


def data_config(name: str):
    from skinfem.config import load_config

    return load_config("small").with_changes(mesh=DATA_MESHES[name],
                                             solver={"element_degree": 2, "quadrature_degree": 4})


def data_fields(config, case: str, points, mesh_dir, comm) -> list:
    """Noise-free data of every design (one design per rank at a time), on every rank."""
    from inference.synthetic import measured_fields
    from skinfem.parallel import collective
    from skinfem.params import SkinParams

    mine = collective(comm, lambda: dict(zip(
        range(comm.rank, len(DESIGNS), comm.size),
        measured_fields(config, SkinParams(*TRUTH), DESIGNS[comm.rank::comm.size], points, hidden_effects()[case],
                        mesh_dir, increments=2))))
    merged = {j: f for part in comm.allgather(mine) for j, f in part.items()}
    return [merged[j] for j in range(len(DESIGNS))]


def box_centre(config: str) -> list[float]:
    """Centre of the checked configuration's prior box of the skin parameters."""
    from skinfem.config import PARAM_NAMES, load_config

    bounds = load_config(config).sweep.bounds
    return [float(np.mean(bounds[name])) for name in PARAM_NAMES]


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
    given = [] if args.start == "spread" else ["--start", *map(str, box_centre(args.config))]
    start = time.perf_counter()
    code = skinid(["check", "--config", args.config, "--measurement", *map(str, files), "--out", str(folder / "report"),
                   "--noise-length", "2", "--noise-nugget", "0.3", "--increments", "2", "--confirm", "1",
                   "--spacing", "2", "--mesh-dir", str(args.mesh_dir), "--refine", args.refine, "--resume", *given,
                   *add])
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
           "discretisation_amplitude": report["discretisation"]["amplitude"],
           "failed_runs": len(report["failed_runs"]), "seconds": seconds,
           "fe_runs": t["compare_fe_runs"] + t["diagnose_fe_runs"] + t["add_fe_runs"],
           "fe_runs_continued": t["fe_runs_continued"], "refined_seconds": t["refined_s"],
           "estimates_baseline": report["versions"][0]["estimates"],
           "estimates_with_true_effect": report["versions"][-1]["estimates"] if add else None}
    (folder / "row.json").write_text(json.dumps(row, indent=2) + "\n")
    return row


def main() -> None:
    import skinfem.model  # noqa: F401  (PETSc initialises collectively: import on every rank first)
    from inference.synthetic import dic_points

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small", help="the checked mesh (preset or TOML)")
    parser.add_argument("--cases", nargs="+", default=list(hidden_effects()))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("out/criticism_bench"))
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--summarise", action="store_true", help="only tabulate the finished checks")
    parser.add_argument("--data", choices=list(DATA_MESHES), default="q2", help="the data's discretisation")
    parser.add_argument("--refine", choices=["uniform", "edge"], default="uniform",
                        help="the check's refined mesh for its discretisation estimate")
    parser.add_argument("--start", choices=["spread", "centre"], default="spread",
                        help="calibration start: best of 5 spread points, or the box centre")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    points = dic_points(18.0, 1.0, np.random.default_rng(0))
    config = data_config(args.data)
    fields = {}
    for seed in [] if args.summarise else range(args.seeds):  # seed by seed: a stopped run has every case
        for case in args.cases:
            if not (args.out / f"{case}_{seed}" / "row.json").exists():
                if case not in fields:
                    fields[case] = data_fields(config, case, points, args.mesh_dir, comm)
                run_case(case, seed, fields[case], points, args, comm)
    rows = [json.loads((args.out / f"{case}_{s}" / "row.json").read_text()) for case in args.cases
            for s in range(args.seeds) if (args.out / f"{case}_{s}" / "row.json").exists()]
    if comm.rank == 0:
        confusion: dict[str, dict[str, int]] = {}
        for row in rows:
            confusion.setdefault(row["case"], {}).setdefault(row["verdict"], 0)
            confusion[row["case"]][row["verdict"]] += 1
        command = (f"mpirun -n 2 python benchmarks/criticism.py --config {args.config} --cases {' '.join(args.cases)} "
                   f"--seeds {args.seeds} --data {args.data} --refine {args.refine} --start {args.start}")
        args.results.write_text(json.dumps({"command": command, "checked_config": args.config,
                                       "data": f"Q2, small preset with {DATA_MESHES[args.data]}",
                                       "noise": {"sd": NOISE["sd"].tolist(), "length_mm": 2.0, "nugget": 0.3},
                                       "confusion": confusion, "rows": rows}, indent=2) + "\n")
        for case, verdicts in confusion.items():
            print(f"{case:>17}: {verdicts}")


if __name__ == "__main__":
    main()
