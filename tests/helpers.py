"""Small finite-element solves used by the verification tests."""

from __future__ import annotations

import numpy as np

from skinfem.fenics import dolfinx, ufl


def solve_energy(mesh, energy_of_F, bcs_of_V, prefix: str):
    """Minimise int Psi(F) dx over P1 displacements with the given Dirichlet conditions.

    Args:
        energy_of_F: F -> UFL strain energy density.
        bcs_of_V: V -> list of DirichletBC.
    Returns:
        (u, V): the converged displacement and its space.
    """
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    F = ufl.Identity(3) + ufl.grad(u)
    energy = energy_of_F(F) * ufl.dx(metadata={"quadrature_degree": 2})
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    problem = dolfinx.fem.petsc.NonlinearProblem(
        residual,
        u,
        bcs=bcs_of_V(V),
        petsc_options_prefix=prefix,
        petsc_options={
            "snes_rtol": 1e-12,
            "snes_atol": 1e-14,
            "ksp_type": "preonly",
            "pc_type": "lu",
        },
    )
    problem.solve()
    assert problem.solver.getConvergedReason() > 0, "Newton did not converge"
    return u, V


def component_bc(V, component: int, where, value: float):
    """u_component = value on the dofs whose coordinates satisfy ``where(x)``."""
    Vi, _ = V.sub(component).collapse()
    dofs = dolfinx.fem.locate_dofs_geometrical((V.sub(component), Vi), where)
    g = dolfinx.fem.Function(Vi)
    g.x.array[:] = value
    return dolfinx.fem.dirichletbc(g, dofs, V.sub(component))


def at_point(p):
    return lambda x: np.isclose(x[0], p[0]) & np.isclose(x[1], p[1]) & np.isclose(x[2], p[2])
