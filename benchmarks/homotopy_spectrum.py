"""Stability along the residual homotopy's path: the tangent's smallest eigenvalues.

    python benchmarks/homotopy_spectrum.py [--material stiff] [--design 0.2 -0.2]
        [--fractions 0.25 0.5 0.75 0.875 0.9375 0.96875 0.984375 1]
        [--out benchmarks/results/homotopy_spectrum.json]

A residual homotopy step that fails stalls on a plateau of its residual (docs/criticism.md §3;
the homotopy was replaced by pseudo-transient continuation for that reason, benchmarks/far_start.py).
Here the path itself is inspected on ``small``: from zero displacement at the full load of
``--design``, the homotopy R(u) = (1 - s) R(0) is solved by Newton–LU (backtracked, every step
factorised, up to 30 steps) at each fraction s in
turn, each from the previous state. Per s: converged, Newton steps, residual norms at the start
and end [N], the three smallest eigenvalues of the tangent on the free (non-Dirichlet) dofs
[N/mm] (negative: the state is not a stable equilibrium of its loads), and the largest difference
from the ramped equilibrium of :meth:`SkinModel.simulate`, relative to its largest displacement.
The ramped equilibrium's own smallest eigenvalues are recorded too. Uses the model's internal
load and Newton methods (benchmark only). Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from far_start import MATERIALS

HERE = Path(__file__).resolve().parent
NEWTON_STEPS = 30


def smallest_eigenvalues(model, free: np.ndarray, k: int = 3) -> list[float]:
    """The ``k`` smallest eigenvalues [N/mm] of the model's tangent at its state, on ``free`` dofs
    (dense: for meshes of a few thousand dofs)."""
    from skinfem.fenics import dolfinx

    A = dolfinx.fem.petsc.assemble_matrix(model.problem.J, bcs=model.bcs)
    A.assemble()
    K = A.convert("dense").getDenseArray()[np.ix_(free, free)]
    A.destroy()
    return [float(v) for v in np.linalg.eigvalsh(0.5 * (K + K.T))[:k]]


def newton_toward(model, rhs) -> tuple[bool, int]:
    """Newton–LU (a factorisation at every step) from the model's state towards R(u) = ``rhs``
    (None: 0), the model's SNES options otherwise. Returns (converged, Newton steps)."""
    from skinfem.fenics import PETSc, dolfinx

    snes, x = model.problem.solver, model.problem.x
    model.set_snes_option("snes_lag_preconditioner", 1)
    dolfinx.fem.petsc.assign(model.u, x)
    snes.solve(rhs, x)
    x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    dolfinx.fem.petsc.assign(x, model.u)
    converged = snes.getConvergedReason() > 0 and np.all(np.isfinite(model.u.x.array))
    return bool(converged), snes.getIterationNumber()


def main() -> None:
    from skinfem.config import load_config
    from skinfem.fenics import dolfinx
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small")
    parser.add_argument("--material", choices=list(MATERIALS), default="stiff")
    parser.add_argument("--design", nargs=2, type=float, default=[0.2, -0.2])
    parser.add_argument(
        "--fractions", nargs="+", type=float, default=[0.25, 0.5, 0.75, 0.875, 0.9375, 0.96875, 0.984375, 1]
    )
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--out", type=Path, default=HERE / "results" / "homotopy_spectrum.json")
    args = parser.parse_args()
    model = SkinModel(load_config(args.config), mesh_dir=args.mesh_dir)
    params, design = SkinParams.from_array(np.array(MATERIALS[args.material])), Design(*args.design)
    dirichlet = np.concatenate([bc.dof_indices()[0] for bc in model.bcs])
    free = np.setdiff1d(np.arange(model.u.x.array.size), dirichlet)
    model.simulate(params, design)
    ramped = model.u.x.array.copy()
    record = {"ramped_equilibrium_smallest_eigenvalues": smallest_eigenvalues(model, free), "path": []}
    model.u.x.array[:] = 0.0
    model.set_load(1.0, design)
    residual0 = model.problem.b.duplicate()
    dolfinx.fem.petsc.assign(model.u, model.problem.x)
    snes = model.problem.solver
    snes.computeFunction(model.problem.x, residual0)
    model.set_snes_option("snes_linesearch_type", "bt")
    model.set_snes_option("snes_max_it", NEWTON_STEPS)
    for s in args.fractions:
        rhs = residual0.copy()
        rhs.scale(1.0 - s)
        start = model.u.x.array.copy()
        converged, steps = newton_toward(model, None if s == 1 else rhs)
        norms = snes.getConvergenceHistory()[0]
        row = {
            "s": s,
            "converged": converged,
            "newton_steps": steps,
            "residual_start_end": [float(norms[0]), float(norms[-1])],
            "smallest_eigenvalues": smallest_eigenvalues(model, free),
            "difference_from_ramp": float(np.abs(model.u.x.array - ramped).max() / np.abs(ramped).max()),
        }
        record["path"].append(row)
        print(row, flush=True)
        if not converged:
            model.u.x.array[:] = start
    record.update(
        command=f"python benchmarks/homotopy_spectrum.py --material {args.material} --design {args.design[0]} "
        f"{args.design[1]} --fractions {' '.join(map(str, args.fractions))}",
        config=args.config,
        dofs=model.n_dofs,
    )
    args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
