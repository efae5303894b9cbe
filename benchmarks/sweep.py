"""Sweep benchmark: wall time of the ``small`` preset sweep on 1 and 2 MPI ranks.

    python benchmarks/sweep.py [--config small] [--layouts 1x1 2x1 2x2]

A layout ``PxK`` runs ``mpirun -n P skinid sweep --ranks-per-sim K``. Results are merged into
benchmarks/results/sweep.json (recorded, not asserted), together with the projected time of
the ``study`` and ``paper`` sweeps from their measured time per simulation.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "sweep.json"
BIN = Path(sys.executable).parent


def run_layout(config: str, ranks: int, per_sim: int, mesh_dir: str) -> dict:
    from skinfem.io import StrainDataset

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.h5"
        cmd = [
            str(BIN / "skinid"),
            "sweep",
            "--config",
            config,
            "--out",
            str(out),
            "--ranks-per-sim",
            str(per_sim),
            "--mesh-dir",
            mesh_dir,
            "--quiet",
        ]
        if ranks > 1:
            cmd = [str(BIN / "mpirun"), "-n", str(ranks), *cmd]
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        start = time.perf_counter()
        subprocess.run(cmd, check=True, env=env, capture_output=True)
        wall = time.perf_counter() - start
        data = StrainDataset.open(out)
    n = data.status.size
    return {
        "ranks": ranks,
        "ranks_per_simulation": per_sim,
        "simulations": n,
        "failed": int((data.status == -1).sum()),
        "wall_seconds": wall,
        "wall_seconds_per_simulation": wall / n,
        "mean_simulation_seconds": float(data.seconds[data.status == 1].mean()),
    }


def projections() -> dict:
    """Projected sweep times from the recorded per-simulation times (forward.json)."""
    forward = json.loads((HERE / "results" / "forward.json").read_text())
    n_sims = 120 * 14
    paper_1 = forward["timing_paper_1rank"]["seconds_per_simulation"]
    paper_2 = forward["timing_paper_2rank"]["seconds_per_simulation"]
    study_1 = forward["convergence"]["runs"]["Q1 h=2"]["seconds"]
    return {
        "simulations": n_sims,
        "paper_hours_2_cores_two_groups_of_1": n_sims * paper_1 / 2 / 3600,
        "paper_hours_2_cores_one_group_of_2": n_sims * paper_2 / 3600,
        "paper_hours_per_core_count": {str(cores): n_sims * paper_1 / cores / 3600 for cores in (2, 16, 64, 256)},
        "study_hours_1_core": n_sims * study_1 / 3600,
        "note": "groups of 1 rank scale linearly while each group's memory (1.5 GB paper mesh) fits",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small")
    parser.add_argument("--layouts", nargs="+", default=["1x1", "2x1", "2x2"])
    parser.add_argument("--mesh-dir", default="meshes")
    args = parser.parse_args()
    rows = []
    for layout in args.layouts:
        ranks, per_sim = (int(v) for v in layout.split("x"))
        row = run_layout(args.config, ranks, per_sim, args.mesh_dir)
        rows.append(row)
        print(json.dumps(row), flush=True)
    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    data[args.config] = rows
    data["projections"] = projections()
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(data, indent=2) + "\n")
    print(json.dumps(data["projections"], indent=2))


if __name__ == "__main__":
    main()
