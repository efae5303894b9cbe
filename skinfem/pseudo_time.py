"""Pseudo-transient continuation: equilibrium from a start far from it.

A start far from equilibrium (another mesh's fields interpolated onto a refined one, or zero
displacement at the full load) is solved by following the energy's gradient flow
D du/dtau = -R(u) in pseudo-time tau with implicit Euler steps, each linearised once:

    (K(u) + D / dt) du = -R(u),    u <- u + du,

with D = |diag K(u0)| (the tangent's diagonal at the start, so that dt is dimensionless and the
membrane, 10^7 times stiffer than the skin, is damped in proportion). While dt is small the
steps follow the flow, which descends the energy to a stable equilibrium; as the residual falls
dt grows and the steps become Newton steps. A residual homotopy R(u) = (1 - s) R(u0) instead
passes through saddle points — the lamina compressed by the homotopy's constant loads — where
its Newton stalls (docs/criticism.md §3; ``benchmarks/homotopy_spectrum.py``; the homotopy's
cost on the starts of ``benchmarks/far_start.py``: ``benchmarks/results/homotopy.json``).

Step control: a step is accepted when its residual norm is finite and at most ``RISE`` times
the previous one; dt then grows by twice the residual's fall (switched evolution relaxation),
at least ``MIN_GROWTH`` x and at most ``GROWTH`` x, or by ``GROWTH`` x when the last two steps were
*linear*: their residual within ``LINEARITY`` of the one their linearisation predicts,
|R(u) + K du| = |D du| / dt. Such a flow is held back by dt alone — by modes that the damping
D slows far more than K resists them (presumably the skin moving with the stiff membrane) —,
not by the nonlinearity that a slow growth guards against. A rejected step is undone and dt divided by ``SHRINK``.

Linear solves: with ``refactor_krylov = 0`` one MUMPS LU factorisation per step; otherwise, as
in the load ramp, GMRES (right-preconditioned, so it measures the true residual [N]) on the
step's exact matrix, preconditioned by the factorisation of an earlier step's, which is renewed
before a step when the previous solve needed more than ``refactor_krylov`` iterations, and at once
when GMRES does not converge within ``KRYLOV_BUDGET``. Between steps the matrix changes by the new
tangent and a dt that grows 2-10x, so an old factorisation often still preconditions it well.
The SNES's own factorisation is freed first (its next solve factorises again): one is held at a
time. Units: residuals in N, dofs in mm, dt dimensionless.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skinfem.fenics import PETSc, dolfinx
from skinfem.memory import limit_factor_memory, raise_if_out_of_memory

FIRST_STEP = 10.0  # dt of the first step (benchmarks/far_start.py: 1, 3 and 10 all converge there)
BUDGET = 80  # steps (factorisations) before giving up (benchmarks/far_start.py: up to 70)
RISE = 2.0
MIN_GROWTH = 2.0
GROWTH = 10.0
SHRINK = 4.0
LINEARITY = 0.1  # relative gap between a step's residual and its linearisation's that counts as linear
KRYLOV_BUDGET = 30  # GMRES iterations on a reused factorisation before refactorising (~2/3 of a factorisation's cost)


@dataclass(frozen=True)
class PseudoTimeStep:
    """One pseudo-time step: its dt, the residual norm [N] it reached and the one its
    linearisation predicted (|D du| / dt), whether it was kept, the GMRES iterations of its
    linear solve (0 for a direct solve) and whether it factorised."""

    dt: float
    residual: float
    predicted: float
    accepted: bool
    krylov_iterations: int = 0
    factorised: bool = True

    @property
    def linear(self) -> bool:
        """Kept, with the residual its linearisation predicted (within ``LINEARITY``)."""
        return self.accepted and abs(self.residual - self.predicted) <= LINEARITY * self.predicted


def next_step(steps: list[PseudoTimeStep], norm: float) -> float:
    """The dt after ``steps`` (module doc), ``norm`` [N]: the residual before the last step."""
    last = steps[-1]
    if not last.accepted:
        return last.dt / SHRINK
    if len(steps) > 1 and steps[-2].linear and last.linear:
        return last.dt * GROWTH
    return last.dt * min(GROWTH, max(MIN_GROWTH, 2.0 * norm / last.residual))


@dataclass(frozen=True)
class FarStart:
    """One equilibrium solved from a start far from it (:func:`pseudo_transient`): whether it
    converged, the residual norm [N] at the start (NaN for a non-finite start) and every step."""

    converged: bool
    start_residual: float
    steps: tuple[PseudoTimeStep, ...] = ()

    @property
    def factorisations(self) -> int:
        return sum(step.factorised for step in self.steps)

    @classmethod
    def from_json(cls, d: dict) -> FarStart:
        """From :func:`dataclasses.asdict` of one as strict JSON holds it (NaN written as null)."""
        steps = tuple(PseudoTimeStep(**{k: np.nan if v is None else v for k, v in s.items()}) for s in d["steps"])
        start = np.nan if d["start_residual"] is None else d["start_residual"]
        return cls(d["converged"], start, steps)

    def describe(self) -> str:
        """One line, e.g. "pseudo-time 19 steps, 5 factorisations (0.0145 -> 3.74e-11 N)"."""
        head = f"pseudo-time {len(self.steps)} steps, {self.factorisations} factorisations"
        if not np.isfinite(self.start_residual):
            return f"{head} (the start's residual is not finite)"
        kept = [step.residual for step in self.steps if step.accepted]
        reached = f"{kept[-1]:.3g} N" if kept else "none kept"
        return f"{head} ({self.start_residual:.3g} -> {reached})"


def pseudo_transient(
    problem: dolfinx.fem.petsc.NonlinearProblem,
    atol: float,
    first_step: float | None = None,
    budget: int | None = None,
    refactor_krylov: int = 0,
    krylov_rtol: float = 1e-8,
) -> FarStart:
    """Pseudo-transient continuation of ``problem`` (its SNES's residual and tangent, Dirichlet
    conditions included) from the current state of its solution function to a residual norm
    below ``atol`` [N] (module doc; not relative to the start's, which is large and arbitrary).
    Collective; every rank gets the same result. ``first_step`` and ``budget`` default to
    ``FIRST_STEP`` and ``BUDGET``; ``refactor_krylov`` and ``krylov_rtol`` as in
    :class:`skinfem.config.SolverConfig` (0: a factorisation per step). The state is the last
    accepted one. The caller frees Newton's factorisation first
    (:meth:`skinfem.model.SkinModel.release_factorisation`): one is held at a time."""
    first_step = FIRST_STEP if first_step is None else first_step
    budget = BUDGET if budget is None else budget
    snes, x, residual, tangent = problem.solver, problem.x, problem.b, problem.A
    u = problem.u
    dolfinx.fem.petsc.assign(u, x)
    snes.computeFunction(x, residual)
    snes.computeJacobian(x, tangent, tangent)
    damping = tangent.getDiagonal()
    damping.abs()
    shift, du, previous, linearised = damping.duplicate(), x.duplicate(), x.duplicate(), x.duplicate()
    ksp = _linear_solver(tangent, refactor_krylov, krylov_rtol, 0.1 * atol)
    norm = start = residual.norm()
    dt, steps, stale = first_step, [], True
    try:
        while norm >= atol and len(steps) < budget and np.isfinite(norm):
            if steps:
                snes.computeJacobian(x, tangent, tangent)
            damping.copy(shift)
            shift.scale(1.0 / dt)
            tangent.setDiagonal(shift, addv=PETSc.InsertMode.ADD_VALUES)
            krylov, factorised = _solve(ksp, tangent, residual, du, stale)
            stale = refactor_krylov == 0 or krylov > refactor_krylov
            x.copy(previous)
            x.axpy(-1.0, du)
            snes.computeFunction(x, residual)
            new = residual.norm()
            linearised.pointwiseMult(shift, du)
            accepted = bool(np.isfinite(new) and new <= RISE * norm)
            steps.append(PseudoTimeStep(dt, float(new), linearised.norm(), accepted, krylov, factorised))
            dt = next_step(steps, norm)
            if accepted:
                norm = new
            else:
                previous.copy(x)
                snes.computeFunction(x, residual)
    finally:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        dolfinx.fem.petsc.assign(x, u)
        for v in (damping, shift, du, previous, linearised):
            v.destroy()
        ksp.destroy()
    return FarStart(bool(norm < atol), float(start), tuple(steps))


def _linear_solver(tangent: PETSc.Mat, refactor_krylov: int, krylov_rtol: float, krylov_atol: float) -> PETSc.KSP:
    """MUMPS LU of ``tangent`` alone (``refactor_krylov = 0``) or as GMRES's right preconditioner
    (module doc), its memory limited to this rank's share (:mod:`skinfem.memory`)."""
    ksp = PETSc.KSP().create(tangent.comm)
    ksp.setOperators(tangent)
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    limit_factor_memory(ksp.getPC())
    if refactor_krylov == 0:
        ksp.setType("preonly")
    else:
        ksp.setType("gmres")
        ksp.setPCSide(PETSc.PC.Side.RIGHT)
        ksp.setGMRESRestart(KRYLOV_BUDGET)
        ksp.setTolerances(rtol=krylov_rtol, atol=krylov_atol, max_it=KRYLOV_BUDGET)
    return ksp


def _solve(ksp: PETSc.KSP, matrix: PETSc.Mat, rhs: PETSc.Vec, solution: PETSc.Vec, refactor: bool) -> tuple[int, bool]:
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
    if ksp.getConvergedReason() < 0:
        raise_if_out_of_memory(ksp.getPC())
    its = ksp.getIterationNumber() if ksp.getType() != "preonly" else 0
    return its, refactor
