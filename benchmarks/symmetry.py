"""The half-turn symmetry of the model as a linear-algebra lever: factorise half the unknowns.

    [mpirun -n 2] python benchmarks/symmetry.py [--config paper] [--out benchmarks/results/symmetry.json]

Mesh, membrane, boundary conditions and an in-plane fiber direction are unchanged by the rotation
by 180 degrees about the z axis, (x, y, z) -> (-x, -y, z), so the equilibrium satisfies
u(-x, -y, z) = (-u_x, -u_y, u_z)(x, y, z) and every Newton step could be solved for half the
unknowns: u = P y with P mapping each node of the half y > 0 (and x > 0 on y = 0) to itself and
to its image with signs (-1, -1, 1); on the axis x = y = 0 only u_z is free. The reduced tangent
is P^T K P (PETSc's MatPtAP). Here, at the last frame of a paper simulation (mixed design, box
centre): P is checked (the reduced solve of a symmetric load equals the full one), and the MUMPS
factorisation, a triangular solve (mean of 5) and the product P^T K P (reused pattern) are timed
for K and P^T K P. The saving per simulation is projected from the counts of
benchmarks/results/forward.json (factorisations, triangular solves, Jacobians per simulation on
the same number of ranks). Recorded, not asserted; not used by the model.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
IMAGE_SIGNS = (-1.0, -1.0, 1.0)  # u_x, u_y, u_z of a node's image under the half turn


def half_turn_map(V, tol: float = 1e-6):
    """P (PETSc Mat, full dofs x reduced dofs) with u = P y for every half-turn-symmetric u of
    the blocked (3 components) space V; tol [mm] matches a node with its image."""
    from skinfem.fenics import PETSc

    comm, index_map = V.mesh.comm, V.dofmap.index_map
    n = index_map.size_local
    x = V.tabulate_dof_coordinates()[:n]
    on_axis = np.all(np.abs(x[:, :2]) < tol, axis=1)
    leading = ~on_axis & ((x[:, 1] > tol) | ((np.abs(x[:, 1]) <= tol) & (x[:, 0] > tol)))
    free = np.where(leading, 3, np.where(on_axis, 1, 0))  # reduced unknowns per owned node
    first = np.concatenate([[0], np.cumsum(free)[:-1]]) + (comm.exscan(int(free.sum())) or 0)
    key = np.round(x / tol).astype(np.int64)
    kept = leading | on_axis
    table = {
        tuple(k): f
        for keys, firsts in zip(comm.allgather(key[kept]), comm.allgather(first[kept]))
        for k, f in zip(keys, firsts)
    }
    ones = np.ones(3 * n, dtype=PETSc.IntType)
    P = PETSc.Mat().createAIJ(((3 * n, None), (int(free.sum()), None)), nnz=(ones, ones), comm=comm)
    row0 = 3 * index_map.local_range[0]
    for i in range(n):
        if leading[i]:
            for c in range(3):
                P.setValue(row0 + 3 * i + c, first[i] + c, 1.0)
        elif on_axis[i]:
            P.setValue(row0 + 3 * i + 2, first[i], 1.0)
        else:
            image = table[tuple(np.round(x[i] * (-1, -1, 1) / tol).astype(np.int64))]
            for c, sign in enumerate(IMAGE_SIGNS):
                P.setValue(row0 + 3 * i + c, image + c, sign)
    P.assemble()
    return P


def timed_lu(A, repeat: int = 5) -> tuple[object, float, float]:
    """(KSP, factorisation seconds, seconds per triangular solve) of MUMPS LU of A."""
    from skinfem.fenics import PETSc

    ksp = PETSc.KSP().create(A.getComm())
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    ksp.setOperators(A)
    start = time.perf_counter()
    ksp.setUp()
    factor = time.perf_counter() - start
    b, x = A.createVecLeft(), A.createVecRight()
    b.setRandom()
    start = time.perf_counter()
    for _ in range(repeat):
        ksp.solve(b, x)
    return ksp, factor, (time.perf_counter() - start) / repeat


def projected_saving(forward: dict, ranks: int, full: dict, reduced: dict) -> dict | None:
    """Seconds saved per paper simulation on ``ranks`` ranks, from the counts of the forward
    timing (``timing_paper_<ranks>rank`` of forward.json; None if absent): each factorisation and
    triangular solve at the reduced cost, plus one P^T K P per Jacobian (one per Newton step)."""
    row = forward.get(f"timing_paper_{ranks}rank")
    if row is None:
        return None
    jacobians = sum(row["newton_iterations_per_increment"])
    saved = (
        row["factorizations"] * (full["factorisation_s"] - reduced["factorisation_s"])
        + row["triangular_solves"] * (full["solve_s"] - reduced["solve_s"])
        - jacobians * reduced["ptap_s"]
    )
    return {
        "factorizations": row["factorizations"],
        "triangular_solves": row["triangular_solves"],
        "jacobians": jacobians,
        "simulation_s": round(row["seconds_per_simulation"], 1),
        "saved_s": round(saved, 1),
    }


def main() -> None:
    from skinfem.config import load_config
    from skinfem.fenics import PETSc, dolfinx
    from skinfem.model import SkinModel
    from skinfem.parallel import abort_on_uncaught
    from skinfem.params import Design, SkinParams

    abort_on_uncaught("benchmarks/symmetry.py")  # e.g. a node without its image on one rank

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="paper")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "symmetry.json")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    model = SkinModel(load_config(args.config), comm)
    model.simulate(SkinParams(1.2e-3, 0.017, 12.0, 0.28, 30.0), Design(0.05, -0.05))
    K = dolfinx.fem.petsc.assemble_matrix(model.problem.J, bcs=model.bcs)
    K.assemble()
    P = half_turn_map(model.V)
    start = time.perf_counter()
    K_half = K.ptap(P)
    first_ptap = time.perf_counter() - start
    start = time.perf_counter()
    K.ptap(P, result=K_half)
    ptap = time.perf_counter() - start
    full_ksp, full_factor, full_solve = timed_lu(K)
    half_ksp, half_factor, half_solve = timed_lu(K_half)
    y = K_half.createVecRight()
    y.setRandom()
    b = K.createVecLeft()
    P.mult(y, b)  # a symmetric load
    x_full, x_half, b_half = K.createVecRight(), K_half.createVecRight(), K_half.createVecLeft()
    full_ksp.solve(b, x_full)
    P.multTranspose(b, b_half)
    half_ksp.solve(b_half, x_half)
    mapped = K.createVecRight()
    P.mult(x_half, mapped)
    mapped.axpy(-1.0, x_full)
    full = {"dofs": K.getSize()[0], "factorisation_s": round(full_factor, 3), "solve_s": round(full_solve, 4)}
    reduced = {
        "dofs": K_half.getSize()[0],
        "factorisation_s": round(half_factor, 3),
        "solve_s": round(half_solve, 4),
        "ptap_s": round(ptap, 3),
        "first_ptap_s": round(first_ptap, 3),
    }
    forward_path = HERE / "results" / "forward.json"
    forward = json.loads(forward_path.read_text()) if forward_path.exists() else {}
    launcher = f"mpirun -n {comm.size} " if comm.size > 1 else ""
    record = {
        "command": f"{launcher}python benchmarks/symmetry.py --config {args.config}",
        "ranks": comm.size,
        "full": full,
        "half_turn_reduced": reduced,
        "reduced_solve_difference": mapped.norm() / x_full.norm(),
        "projected": projected_saving(forward, comm.size, full, reduced),
    }
    if comm.rank == 0:
        results = json.loads(args.out.read_text()) if args.out.exists() else {}
        results[f"{args.config}_{comm.size}_ranks"] = record
        args.out.write_text(json.dumps(results, indent=1) + "\n")
        print(json.dumps(record, indent=1))
    for obj in (K, K_half, P, full_ksp, half_ksp):
        obj.destroy()
    PETSc.garbage_cleanup()


if __name__ == "__main__":
    main()
