"""Model-criticism benchmark: wall time and FE runs of compare, diagnose and add.

    mpirun -n 2 python benchmarks/criticism.py --emulator out/small/emu [--increments 2]

Writes synthetic measurements of the small preset (truth mu = 0.0012 MPa, k1 = 0.017 MPa,
k2 = 11, kappa = 0.285, theta = 30 deg; hidden pre-stretch 1.08 x 1.02 at 30 deg; noise sd 2e-4,
2 mm correlation, 30 % uncorrelated) for two membrane designs, runs the check with
``--add pre_stretch`` and records, per step, seconds and FE runs. The paper-preset cost is
projected from the same numbers of FE runs and the measured paper simulation time
(benchmarks/results/forward.json, 2 ranks, 10 increments) scaled by the small mesh's measured
time ratio of a simulation with ``--increments`` to one with 10:
a check at that size takes about an hour on 2 cores (FE runs are independent and spread over ranks).
Results go to benchmarks/results/criticism.json.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "criticism.json"


def main() -> None:
    import skinfem.model  # noqa: F401  (PETSc initialises collectively: import on every rank first)
    from inference.check import CheckSettings, run_check
    from inference.criticism import NoiseModel
    from inference.observations import from_measurements
    from inference.synthetic import synthetic_measurements
    from skinfem.config import config_from_toml
    from skinfem.effects import prestretch_log_strain
    from skinfem.params import Design, SkinParams
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser()
    parser.add_argument("--emulator", type=Path, required=True)
    parser.add_argument("--increments", type=int, default=2)
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    emulator = Emulator.load(args.emulator)
    config = config_from_toml(emulator.meta["dataset_config"])
    noise = NoiseModel(np.full(3, 2e-4), 2.0, 0.3)
    pre = {f"pre_stretch.{k}": v for k, v in prestretch_log_strain(1.08, 1.02, 30.0).items()}
    designs = [(0.05, 0.05), (0.05, -0.05)]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = comm.bcast(tmp)
        if comm.rank == 0:
            synthetic_measurements(config, SkinParams(0.0012, 0.017, 11.0, 0.285, 30.0), designs, noise, tmp, pre,
                                   seed=5, mesh_dir=args.mesh_dir, increments=args.increments)
        comm.Barrier()
        obs = from_measurements(sorted(Path(tmp).glob("m_*.csv")), emulator.xy, config.mesh.length / 2)
        start = time.perf_counter()
        result = run_check(emulator, obs, noise, CheckSettings(add=["pre_stretch"], increments=args.increments),
                           args.mesh_dir, comm)
        total = time.perf_counter() - start
    if comm.rank:
        return
    t = result.timings
    # the paper run was timed with 10 increments: scale it by the small mesh's measured ratio
    from skinfem.model import SkinModel

    seconds = {}
    for n in (config.solver.increments, args.increments):
        model = SkinModel(config.with_changes(solver={"increments": n}), MPI.COMM_SELF, mesh_dir=args.mesh_dir)
        model.simulate(SkinParams(0.0012, 0.017, 11.0, 0.285, 30.0), Design(*designs[1]))
        seconds[n] = model.simulate(SkinParams(0.0012, 0.017, 11.0, 0.285, 30.0), Design(*designs[1])).seconds
    ratio = seconds[args.increments] / seconds[config.solver.increments]
    forward = json.loads((HERE / "results" / "forward.json").read_text())["timing_paper_2rank"]
    paper_per_run = forward["seconds_per_simulation"] * ratio
    steps = {step: {"seconds": t[f"{step}_s"], "fe_runs": t[f"{step}_fe_runs"]} for step in ("compare", "diagnose", "add")}
    steps["add"]["reused_from_diagnose"] = {"seconds": t["add_reused_from_diagnose_s"],
                                            "fe_runs": t["add_reused_from_diagnose_fe_runs"]}
    for step, row in steps.items():
        # one FE run after another, each on 2 ranks; the points of one Jacobian (p + 1 per
        # design) are independent, so k such groups divide this by up to min(k, p + 1)
        row["paper_projection_hours_serial"] = row["fe_runs"] * paper_per_run / 3600
    record = {
        "config": config.name,
        "ranks": comm.size,
        "designs": designs,
        "increments": args.increments,
        "skin_cells": int(len(emulator.xy)),
        "seconds_total": total,
        "seconds_per_fe_run_per_rank": result.fe_seconds_per_run,
        "steps": steps,
        "small_seconds_per_simulation_by_increments": seconds,
        "paper_seconds_per_fe_run_2_ranks": paper_per_run,
        "verdict": result.diagnosis.text,
        "versions": [{"label": v.calibration.label, "rmse": v.metrics["rmse"], "chi2_per_dof": v.metrics["chi2_per_dof"],
                      "ppc_p": v.metrics["ppc_p"]} for v in result.versions],
    }
    RESULTS.write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
