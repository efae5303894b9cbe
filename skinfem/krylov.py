"""Linear solves on a kept LU factorisation: MUMPS LU as the right preconditioner of GMRES.

A sequence of linear systems whose matrices change a little from one to the next (the steps of
pseudo-time, the tangents of nearby equilibria) is solved by GMRES on each system's exact matrix,
preconditioned by the factorisation of an earlier one. GMRES is preconditioned from the right,
so it measures the true residual ||b - A x|| (in N for the tangent) and stops at ``rtol`` relative
to ||b|| or below ``atol``. The caller decides when a factorisation is stale (e.g. the previous
solve needed more than ``solver.refactor_krylov`` iterations); a solve that does not converge
within ``KRYLOV_BUDGET`` iterations on the kept factorisation factorises at once and solves
again. (The load ramp's Newton steps use the same scheme through SNES options:
:meth:`skinfem.model.SkinModel._krylov_options`.)
"""

from __future__ import annotations

from skinfem.fenics import PETSc

KRYLOV_BUDGET = 30  # GMRES iterations on a reused factorisation before refactorising (~2/3 of a factorisation's cost)


def kept_factorisation_solver(comm, refactor_krylov: int, rtol: float, atol: float) -> PETSc.KSP:
    """MUMPS LU alone (``refactor_krylov = 0``: every solve factorises) or as GMRES's right
    preconditioner (module doc)."""
    ksp = PETSc.KSP().create(comm)
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    if refactor_krylov == 0:
        ksp.setType("preonly")
    else:
        ksp.setType("gmres")
        ksp.setPCSide(PETSc.PC.Side.RIGHT)
        ksp.setGMRESRestart(KRYLOV_BUDGET)
        ksp.setTolerances(rtol=rtol, atol=atol, max_it=KRYLOV_BUDGET)
    return ksp


def solve(ksp: PETSc.KSP, matrix: PETSc.Mat, rhs: PETSc.Vec, solution: PETSc.Vec, refactor: bool) -> tuple[int, bool]:
    """Solve ``matrix`` solution = rhs, factorising ``matrix`` if ``refactor`` or if GMRES on
    the kept factorisation does not converge. Returns (GMRES iterations of the last attempt,
    whether it factorised)."""
    ksp.setOperators(matrix)
    ksp.getPC().setReusePreconditioner(not refactor)
    ksp.solve(rhs, solution)
    if not refactor and ksp.getConvergedReason() < 0:
        ksp.getPC().setReusePreconditioner(False)
        ksp.solve(rhs, solution)
        refactor = True
    its = ksp.getIterationNumber() if ksp.getType() != "preonly" else 0
    return its, refactor
