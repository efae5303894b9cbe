"""Peak memory and time of one FE run with derivatives on a check's refined mesh.

    python benchmarks/sensitivity_memory.py --label NAME [--config check] [--refine edge]
                                            [--results benchmarks/results/sensitivity_memory.json]

One run of the mixed design (0.05, -0.05), 2 load increments, at the criticism benchmark's
material, with the derivatives by every parameter of the check (skin and effects) at its thinned
point cloud, on ``--config``'s mesh after ``--refine`` (the check's refined mesh, the run that
``--mesh-drift`` adds; ``--refine none``: the mesh itself). It runs in a fresh process after a
warm-up that compiles the forms, so that its peak resident memory (``ru_maxrss``) is its own.
The result is stored under ``NAME`` in the results file (other labels are kept: run it once per
build to compare builds); the Jacobian goes to ``out/sensitivity_memory/NAME.npy`` and its
largest difference from every other label's there is recorded. Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
JACOBIANS = HERE.parent / "out" / "sensitivity_memory"


def one_run(config_name: str, refine: str) -> tuple[dict, np.ndarray]:
    """The run with derivatives in this process: its record and its Jacobian."""
    from criticism import TRUTH
    from design_separation import check_points
    from mpi4py import MPI

    from inference.criticism.discretisation import refined_config
    from inference.forward import FEForward, PointSet
    from skinfem.config import load_config
    from skinfem.solver_work import WorkMeter

    config = load_config(config_name)
    if refine != "none":
        config = refined_config(config, refine)
    cloud, kept = check_points()
    observations = [PointSet(np.array([0.05, -0.05]), 1.0, cloud[kept])]
    forward = FEForward(config, observations, config.sweep.box, "meshes", 2, MPI.COMM_SELF, continuation=False)
    x = forward.null.copy()
    x[:5] = TRUTH
    meter, start = WorkMeter(MPI.COMM_SELF), time.perf_counter()
    ((_, jacobian),) = forward.evaluate_with_jacobian([x], forward.names)
    record = {
        "seconds": time.perf_counter() - start,
        "peak_memory_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2,
        "dofs": forward.model.V.dofmap.index_map.size_global * forward.model.V.dofmap.index_map_bs,
        "work": vars(meter.lap()),
        "parameters": len(forward.names),
        "jacobian_rms": float(np.sqrt(np.mean(jacobian**2))),
    }
    return record, jacobian


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--label", required=True, help="name of this build's record")
    parser.add_argument("--config", default="check")
    parser.add_argument("--refine", default="edge")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "sensitivity_memory.json")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)  # the run itself
    args = parser.parse_args()
    if args.child:
        record, jacobian = one_run(args.config, args.refine)
        JACOBIANS.mkdir(parents=True, exist_ok=True)
        np.save(JACOBIANS / f"{args.label}.npy", jacobian)
        print(json.dumps(record))
        return
    for refine in ("none", args.refine):  # the first compiles the forms (FFCx caches them): not recorded
        command = [sys.executable, __file__, "--config", args.config, "--refine", refine, "--label", args.label]
        out = subprocess.run([*command, "--child"], check=True, capture_output=True, text=True).stdout
    record = json.loads(out.strip().splitlines()[-1])
    mine = np.load(JACOBIANS / f"{args.label}.npy")
    record["max_jacobian_difference_over_rms"] = {
        other.stem: float(np.abs(np.load(other) - mine).max() / record["jacobian_rms"])
        for other in sorted(JACOBIANS.glob("*.npy"))
        if other.stem != args.label
    }
    results = json.loads(args.results.read_text()) if args.results.exists() else {}
    results.setdefault("runs", {})[args.label] = record
    results["command"] = f"python benchmarks/sensitivity_memory.py --config {args.config} --refine {args.refine}"
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
