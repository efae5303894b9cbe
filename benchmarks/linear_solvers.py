"""One tangent solve of the paper mesh: MUMPS LU against Krylov + algebraic multigrid.

    python benchmarks/linear_solvers.py [--config paper] [--out benchmarks/results/linear_solvers.json]

For the elastic membrane and its rigid limit (``membrane.model``), a paper simulation (mixed
design, box centre) is run and the tangent at its last frame is assembled (the exact Jacobian of
the model's energy, Dirichlet rows included). The system K x = b, b the residual-shaped load of a
unit random vector, is solved by MUMPS LU (factorisation and one triangular solve timed apart)
and by CG and GMRES preconditioned with PETSc's GAMG using the six rigid-body modes as the
near-nullspace (set-up and solve timed apart, relative tolerance 1e-8 of the true residual).
Single rank.
Recorded, not asserted: whether multigrid can replace the factorisation once the membrane's 10^7
stiffness contrast is gone.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
KRYLOV = {"cg + gamg": "cg", "gmres + gamg": "gmres"}


def rigid_body_modes(V):
    """PETSc near-nullspace of the 3 translations and 3 rotations on V's dof coordinates."""
    from skinfem.fenics import PETSc

    x = V.tabulate_dof_coordinates()[: V.dofmap.index_map.size_local]
    n = len(x)
    modes = np.zeros((6, n, 3))
    for k in range(3):
        modes[k, :, k] = 1.0
    modes[3, :, 0], modes[3, :, 1] = -x[:, 1], x[:, 0]
    modes[4, :, 1], modes[4, :, 2] = -x[:, 2], x[:, 1]
    modes[5, :, 2], modes[5, :, 0] = -x[:, 0], x[:, 2]
    basis = []
    for mode in modes:  # Gram-Schmidt: PETSc wants an orthonormal basis
        v = PETSc.Vec().createWithArray(mode.ravel().copy(), comm=MPI.COMM_SELF)
        for w in basis:
            v.axpy(-v.dot(w), w)
        v.normalize()
        basis.append(v)
    return PETSc.NullSpace().create(vectors=basis, comm=MPI.COMM_SELF)


def tangent(model):
    """The assembled Jacobian (PETSc Mat) of the model's energy at its current state."""
    from skinfem.fenics import JIT_OPTIONS, dolfinx, ufl

    residual = ufl.derivative(model.energy, model.u, ufl.TestFunction(model.V))
    jacobian = ufl.derivative(residual, model.u, ufl.TrialFunction(model.V))
    A = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(jacobian, jit_options=JIT_OPTIONS), bcs=model.bcs)
    A.assemble()
    return A


def timed_solve(A, b, options: dict, near_nullspace=None) -> dict:
    """Set-up and solve seconds, iterations and relative residual of one KSP configuration."""
    from skinfem.fenics import PETSc

    ksp = PETSc.KSP().create(MPI.COMM_SELF)
    prefix = f"probe_{id(ksp)}_"
    ksp.setOptionsPrefix(prefix)
    opts = PETSc.Options()
    for key, value in options.items():
        opts[prefix + key] = value
    if near_nullspace is not None:
        A.setNearNullSpace(near_nullspace)
    ksp.setOperators(A)
    ksp.setFromOptions()
    x = b.duplicate()
    start = time.perf_counter()
    ksp.setUp()
    setup = time.perf_counter() - start
    start = time.perf_counter()
    ksp.solve(b, x)
    solve = time.perf_counter() - start
    r = b.duplicate()
    A.mult(x, r)
    r.axpy(-1.0, b)
    return {
        "setup_s": round(setup, 3),
        "solve_s": round(solve, 3),
        "iterations": ksp.getIterationNumber(),
        "converged": ksp.getConvergedReason() > 0,
        "relative_residual": r.norm() / b.norm(),
    }


def probe(config, mesh_dir) -> dict:
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir)
    frames = model.simulate(SkinParams.from_array(config.sweep.box.mean(axis=1)), Design(0.05, -0.05))
    A = tangent(model)
    b = A.createVecLeft()
    b.setArray(np.random.default_rng(0).standard_normal(b.getLocalSize()))
    row = {
        "dofs": model.n_dofs,
        "simulation_s": round(frames.seconds, 1),
        "mumps lu": timed_solve(A, b, {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}),
    }
    modes = rigid_body_modes(model.V)
    for name, ksp_type in KRYLOV.items():
        row[name] = timed_solve(
            A,
            b,
            {
                "ksp_type": ksp_type,
                "ksp_rtol": 1e-8,
                "ksp_max_it": 2000,
                "ksp_norm_type": "unpreconditioned",
                "pc_type": "gamg",
                "pc_gamg_threshold": 0.01,
            },
            modes,
        )
    return row


def main() -> None:
    from skinfem.config import load_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="paper")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "linear_solvers.json")
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    args = parser.parse_args()
    config = load_config(args.config)
    result = {"command": f"python benchmarks/linear_solvers.py --config {args.config}", "config": config.name}
    for membrane in ("elastic", "rigid"):
        result[membrane] = probe(config.with_changes(membrane={"model": membrane}), args.mesh_dir)
        print(membrane, result[membrane], flush=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
