"""Peak memory and time of one FE run with derivatives: sensitivities on the Newton solve's kept
factorisation (the default) against their own LU of the tangent (as before).

    python benchmarks/sensitivity_memory.py [--config check] [--refine edge]
                                            [--results benchmarks/results/sensitivity_memory.json]

One run of the mixed design (0.05, -0.05), 2 load increments, at the criticism benchmark's
material, with the derivatives by every parameter of the check (skin and effects) at its thinned
point cloud, on ``--config``'s mesh after ``--refine`` (the check's better mesh, where memory
peaked; ``--refine none``: the mesh itself). Each variant runs in a fresh process, one after the
other, so that its peak resident memory (``ru_maxrss``) is its own. Recorded, not asserted.
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
VARIANTS = ("kept", "own")


def one_run(config_name: str, refine: str, variant: str) -> dict:
    """The run with derivatives in this process; ``variant`` "own" gives the sensitivities no
    kept factorisation (their own LU, the previous behaviour)."""
    from criticism import TRUTH
    from design_separation import check_points
    from mpi4py import MPI

    import skinfem.sensitivity
    from inference.criticism.discretisation import refined_config
    from inference.forward import FEForward, PointSet
    from skinfem.config import load_config

    if variant == "own":
        skinfem.sensitivity.kept_factorisation = lambda model: None
    config = load_config(config_name)
    if refine != "none":
        config = refined_config(config, refine)
    cloud, kept = check_points()
    observations = [PointSet(np.array([0.05, -0.05]), 1.0, cloud[kept])]
    forward = FEForward(config, observations, config.sweep.box, "meshes", 2, MPI.COMM_SELF, continuation=False)
    x = forward.null.copy()
    x[:5] = TRUTH
    start = time.perf_counter()
    ((fields, jacobian),) = forward.evaluate_with_jacobian([x], forward.names)
    return {
        "seconds": time.perf_counter() - start,
        "peak_memory_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2,
        "own_factorisations": forward.sensitivity.factorisations,
        "gmres_iterations": forward.sensitivity.krylov_iterations,
        "parameters": len(forward.names),
        "jacobian_rms": float(np.sqrt(np.mean(jacobian**2))),
        "jacobian": jacobian.tolist(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="check")
    parser.add_argument("--refine", default="edge")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "sensitivity_memory.json")
    parser.add_argument("--variant", choices=VARIANTS, help=argparse.SUPPRESS)  # one run, in a child process
    args = parser.parse_args()
    if args.variant:
        print(json.dumps(one_run(args.config, args.refine, args.variant)))
        return
    runs = {}
    warm_up = ("own", "none")  # compiles the forms on the unrefined mesh (FFCx caches them): not recorded
    for variant, refine in (warm_up, *((v, args.refine) for v in VARIANTS)):
        command = [sys.executable, __file__, "--config", args.config, "--refine", refine, "--variant", variant]
        out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        runs[variant] = json.loads(out.strip().splitlines()[-1])
    difference = np.abs(np.array(runs["kept"].pop("jacobian")) - np.array(runs["own"].pop("jacobian"))).max()
    results = {
        "command": f"python benchmarks/sensitivity_memory.py --config {args.config} --refine {args.refine}",
        "runs": runs,
        "max_jacobian_difference_over_rms": float(difference / runs["own"]["jacobian_rms"]),
    }
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
