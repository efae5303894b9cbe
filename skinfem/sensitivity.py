"""Forward (direct) sensitivities of the equilibrium: du/dp without extra simulations.

At a converged state R(u; p) = 0, differentiating with respect to a parameter p gives

    K du/dp = -dR/dp,    K = dR/du (the tangent),

with homogeneous Dirichlet conditions (no boundary value depends on a material or effect
parameter). dR/dp comes from UFL: the parameter Constant is replaced by a ``ufl.variable``,
the energy's integrands are differentiated with ``ufl.diff`` and the result is differentiated
with respect to u (``ufl.derivative``), so the forms are exact and compiled once. The fiber
angle theta [deg] enters through a0 = (cos theta, sin theta, 0): its derivative is the
directional derivative along da0/dtheta = (-sin theta, cos theta, 0) pi/180.

One tangent assembly and one LU factorisation serve all parameters of a state; each
parameter costs one assembly of dR/dp and one pair of triangular solves, instead of one full
nonlinear simulation per parameter for a finite difference. The factorisation is made in the
Newton solver's own matrix and preconditioner, replacing the one it keeps: one factorisation is
held at a time (on ``check``'s edge refinement one takes 4.1 GB in MUMPS;
benchmarks/results/sensitivity_memory.json), and the next Newton solve that reuses its
factorisation starts from this state's. (GMRES preconditioned by the stale factorisation the
Newton solve keeps, instead of a new one, was measured twice and is slower: ~45 iterations per
parameter; docs/criticism.md §4.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from skinfem.config import PARAM_NAMES
from skinfem.fenics import JIT_OPTIONS, PETSc, dolfinx, ufl


def energy_derivative(energy: ufl.Form, constant, direction=None) -> ufl.Form:
    """d energy / d constant (a scalar form), along ``direction`` for a vector constant."""
    var = ufl.variable(constant)
    integrals = []
    for integral in ufl.replace(energy, {constant: var}).integrals():
        d = ufl.diff(integral.integrand(), var)
        integrals.append(integral.reconstruct(integrand=d if direction is None else ufl.dot(d, direction)))
    return ufl.Form(integrals)


class DisplacementSensitivity:
    """du/dp of a :class:`skinfem.model.SkinModel` at its current (converged) state.

    Args:
        model: the model; call after a converged solve (e.g. in ``simulate``'s ``on_frame``).

    Parameters are named like the forward models' vectors: skin parameters (``mu, k1, k2,
    kappa, theta``) and qualified effect parameters (``"muscle_stiffness.log_factor"``). The
    form of each is compiled on its first use. Units: du/dp in mm per unit of p (MPa, -, per
    degree for theta).
    """

    def __init__(self, model):
        self.model = model
        mesh = model.mesh
        self._da0 = dolfinx.fem.Constant(mesh, np.zeros(3, dtype=PETSc.ScalarType))
        self._constants = dict(zip(PARAM_NAMES, (model.mu, model.k1, model.k2, model.kappa, model.a0)))
        self._constants.update(model.effect_constants)
        self._forms: dict[str, dolfinx.fem.Form] = {}
        self._rhs = dolfinx.fem.petsc.create_vector(model.V)

    def _form(self, name: str):
        """The compiled form dR/dp of parameter ``name`` (cached)."""
        if name not in self._forms:
            if name not in self._constants:
                raise ValueError(f"no sensitivity for '{name}'; this model has: {', '.join(self._constants)}")
            direction = self._da0 if name == "theta" else None
            d_energy = energy_derivative(self.model.energy, self._constants[name], direction)
            v = ufl.TestFunction(self.model.V)
            self._forms[name] = dolfinx.fem.form(ufl.derivative(d_energy, self.model.u, v), jit_options=JIT_OPTIONS)
        return self._forms[name]

    def __call__(self, names: Sequence[str]) -> list:
        """One displacement-sensitivity Function per name, at the model's current state."""
        model = self.model
        forms = [self._form(name) for name in names]
        a0 = model.a0.value
        self._da0.value[:] = (-a0[1] * math.pi / 180, a0[0] * math.pi / 180, 0.0)
        inverse = self._factorise()
        out = []
        for form in forms:
            with self._rhs.localForm() as local:
                local.set(0.0)
            dolfinx.fem.petsc.assemble_vector(self._rhs, form)
            self._rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            self._rhs.scale(-1.0)
            for bc in model.bcs:
                bc.set(self._rhs.array_w, alpha=0.0)
            du = dolfinx.fem.Function(model.V)
            inverse.apply(self._rhs, du.x.petsc_vec)
            du.x.scatter_forward()
            out.append(du)
        return out

    def _factorise(self) -> PETSc.PC:
        """The tangent at the model's current state, assembled into the Newton solver's matrix and
        factorised in its preconditioner (module doc); the returned PC applies its inverse."""
        problem = self.model.problem
        tangent = problem.A
        tangent.zeroEntries()
        dolfinx.fem.petsc.assemble_matrix(tangent, problem.J, bcs=self.model.bcs)
        tangent.assemble()
        ksp = problem.solver.getKSP()
        ksp.setOperators(tangent)
        inverse = ksp.getPC()
        inverse.setReusePreconditioner(False)  # SNES sets it again at its next tangent
        inverse.setUp()
        return inverse
