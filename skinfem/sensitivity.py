"""Forward (direct) sensitivities of the equilibrium: du/dp without extra simulations.

At a converged state R(u; p) = 0, differentiating with respect to a parameter p gives

    K du/dp = -dR/dp,    K = dR/du (the tangent),

with homogeneous Dirichlet conditions (no boundary value depends on a material or effect
parameter). dR/dp comes from UFL: the parameter Constant is replaced by a ``ufl.variable``,
the energy's integrands are differentiated with ``ufl.diff`` and the result is differentiated
with respect to u (``ufl.derivative``), so the forms are exact and compiled once. The fiber
angle theta [deg] enters through a0 = (cos theta, sin theta, 0): its derivative is the
directional derivative along da0/dtheta = (-sin theta, cos theta, 0) pi/180.

One tangent assembly serves all parameters of a state; each parameter costs one assembly of
dR/dp and a few triangular solves, instead of one full nonlinear simulation per parameter for
a finite difference. The solves are GMRES (preconditioned from the right, so that it measures
the true residual) preconditioned by the LU factorisation the Newton solve keeps (of a tangent
of this load increment): no second factorisation, whose memory doubled the peak of a run with
derivatives (12 GB per rank on the `check` preset's edge refinement, docs/criticism.md §23).
Only where that GMRES does not converge, or no factorisation is kept, is the tangent factorised.
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
        self._K = dolfinx.fem.petsc.create_matrix(model.problem.J)
        self._krylov = PETSc.KSP().create(mesh.comm)
        self._krylov.setType("gmres")
        self._krylov.setPCSide(PETSc.PC.Side.RIGHT)
        self._krylov.setTolerances(rtol=KRYLOV_RTOL, atol=0.0, max_it=KRYLOV_MAX_IT)
        self._krylov.getPC().setType("python")
        self._ksp: PETSc.KSP | None = None  # its own LU, made only when needed
        self._rhs = dolfinx.fem.petsc.create_vector(model.V)
        self.factorisations = 0  # of its own (the kept one did not serve)
        self.krylov_iterations: list[int] = []  # of each solve on the kept factorisation

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
        self._K.zeroEntries()
        dolfinx.fem.petsc.assemble_matrix(self._K, model.problem.J, bcs=model.bcs)
        self._K.assemble()
        factor = kept_factorisation(model)
        if factor is not None:
            self._krylov.setOperators(self._K)
            self._krylov.getPC().setPythonContext(FactorPreconditioner(factor))
        fresh = False  # whether its own LU holds this tangent
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
            if factor is None or not self._krylov_solve(du):
                if not fresh:
                    self._factorise()
                    fresh = True
                self._ksp.solve(self._rhs, du.x.petsc_vec)
            du.x.scatter_forward()
            out.append(du)
        return out

    def _krylov_solve(self, du) -> bool:
        """GMRES on the tangent, preconditioned by the kept factorisation; whether it converged."""
        du.x.petsc_vec.set(0.0)
        self._krylov.solve(self._rhs, du.x.petsc_vec)
        self.krylov_iterations.append(self._krylov.getIterationNumber())
        return self._krylov.getConvergedReason() > 0

    def _factorise(self) -> None:
        """Its own MUMPS LU of the current tangent (created on first use)."""
        if self._ksp is None:
            self._ksp = PETSc.KSP().create(self.model.mesh.comm)
            self._ksp.setType("preonly")
            pc = self._ksp.getPC()
            pc.setType("lu")
            pc.setFactorSolverType("mumps")
        self._ksp.setOperators(self._K)  # a new factorisation for the new tangent
        self.factorisations += 1


KRYLOV_RTOL = 1e-10  # of the sensitivity solves' true residual, relative to dR/dp
KRYLOV_MAX_IT = 60  # beyond this a kept factorisation is too stale: factorise the tangent


class FactorPreconditioner:
    """petsc4py ``python`` preconditioner: y = F^-1 x with F an LU factorisation kept elsewhere."""

    def __init__(self, factor: PETSc.Mat):
        self.factor = factor

    def apply(self, pc: PETSc.PC, x: PETSc.Vec, y: PETSc.Vec) -> None:
        self.factor.solve(x, y)


def kept_factorisation(model) -> PETSc.Mat | None:
    """The LU factor the model's Newton solve holds (its GMRES preconditioner), or None when it
    holds none (not factorised yet, or freed, e.g. by pseudo-time continuation)."""
    pc = model.problem.solver.getKSP().getPC()
    if pc.getType() != "lu":
        return None
    try:
        factor = pc.getFactorMatrix()
    except PETSc.Error:
        return None
    return factor if factor.isAssembled() else None
