"""Cost and agreement of the discretisation estimate's refined run, by refined mesh.

    mpirun -n 2 python benchmarks/refined_estimate.py [--config check]
                                                      [--variants all but-skin none] [--out FILE]

The check's two-mesh estimate (docs/criticism.md section 2) runs the calibrated point once on
a refined mesh, started from the check mesh's fields interpolated onto it. For the quadratic
check mesh this run dominated a check (section 10). Here: one material near the calibrated
point of that check, the two designs of benchmarks/criticism.py (one per rank) at t = 1, the
DIC point cloud of that benchmark, the check mesh's run (ramped, then recorded for
continuation) and, per variant of the edge refinement (edge cells halved; layers through the
thickness: ``all`` doubled, all ``but-skin``, only the ``muscle`` or ``membrane`` layers,
``none``), the refined run: dofs,
seconds, whether Newton from the interpolated fields converged, the shift's RMS relative to
the field, how far each variant's shift is from the ``all`` variant's, and each rank's Newton
iterations (seconds, iteration, residual norm).
Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
CALIBRATED = (1.33e-3, 0.0183, 8.38, 0.280, 29.8)  # the quadratic check's baseline (criticism_q2.json)
DESIGNS = [(0.05, 0.05), (0.05, -0.05)]
LAYERS = {
    "all": ("skin_layers", "muscle_layers", "membrane_layers"),
    "but-skin": ("muscle_layers", "membrane_layers"),
    "muscle": ("muscle_layers",),
    "membrane": ("membrane_layers",),
    "none": (),
}


def variant_config(config, variant: str):
    """The check's edge refinement of ``config`` with the layer counts of ``variant`` doubled
    (the others kept)."""
    from inference.criticism.discretisation import refined_config

    m = config.mesh
    return refined_config(config, "edge").with_changes(
        mesh={name: (2 if name in LAYERS[variant] else 1) * getattr(m, name) for name in LAYERS["all"]}
    )


def main() -> None:
    """The benchmark's steps in order (options, variants, the results file): longer than a screen on purpose."""
    import skinfem.model  # noqa: F401  (PETSc initialises collectively: import on every rank first)
    from inference.forward import FEForward, PointSet
    from inference.synthetic import dic_points
    from skinfem.config import load_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="check")
    parser.add_argument("--variants", nargs="+", choices=list(LAYERS), default=list(LAYERS))
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--out", type=Path, default=HERE / "results" / "refined_estimate.json")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    config = load_config(args.config)
    xy = dic_points(18.0, 1.0, np.random.default_rng(0))
    observations = [PointSet(np.array(alpha), 1.0, xy) for alpha in DESIGNS]
    bounds = config.sweep.box
    forward = FEForward(config, observations, bounds, args.mesh_dir, 2, comm)
    x = forward.null.copy()
    x[:5] = CALIBRATED
    start = time.perf_counter()
    field = forward(x)
    check_seconds = time.perf_counter() - start
    rms = float(np.sqrt(np.mean(field**2)))
    rows, shifts = [], {}
    for variant in args.variants:
        fine = FEForward(variant_config(config, variant), observations, bounds, args.mesh_dir, 2, comm)
        fine.continue_from(forward, x)
        newton = []  # (seconds since start, Newton iteration, residual norm) on this rank
        fine.model.problem.solver.setMonitor(
            lambda snes, its, norm: newton.append((round(time.perf_counter() - start, 1), its, float(norm)))
        )
        start = time.perf_counter()
        refined = fine(x)
        seconds = time.perf_counter() - start
        row = {
            "layers doubled": variant,
            "dofs": fine.model.n_dofs,
            "seconds": round(seconds, 1),
            "continued": fine.continued,
            "runs": fine.runs,
            "converged": refined is not None,
            "newton_per_rank": comm.gather(newton),
        }
        if refined is not None:
            shifts[variant] = refined - field
            row["shift_relative_rms"] = float(np.sqrt(np.mean(shifts[variant] ** 2)) / rms)
        rows.append(row)
        if comm.rank == 0:
            print({k: v for k, v in row.items() if k != "newton_per_rank"}, flush=True)
        del fine
    for row in rows:
        variant = row["layers doubled"]
        if "all" in shifts and variant in shifts and variant != "all":
            row["shift_change_from_all"] = float(
                np.linalg.norm(shifts[variant] - shifts["all"]) / np.linalg.norm(shifts["all"])
            )
    if comm.rank == 0:
        command = f"mpirun -n {comm.size} python benchmarks/refined_estimate.py --variants {' '.join(args.variants)}"
        args.out.write_text(
            json.dumps(
                {
                    "command": command,
                    "config": args.config,
                    "check_dofs": forward.model.n_dofs,
                    "check_seconds": round(check_seconds, 1),
                    "field_rms": rms,
                    "variants": rows,
                },
                indent=2,
            )
            + "\n"
        )


if __name__ == "__main__":
    main()
