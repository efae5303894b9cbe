"""The forward model: skin + muscle block actuated by a bonded active membrane.

``SkinModel(config).simulate(params, design)`` ramps the membrane eigen-strain
t (alpha11, alpha22) over ``solver.increments`` equal steps t = 1/n, ..., 1 and returns the
skin log strain at every step. Forms are compiled once per model; material parameters and
the load are DOLFINx Constants, so one model serves a whole sweep.

Formulation (see README "Forward model"):
- displacement-only Lagrange elements of ``solver.element_degree`` on hexahedra;
- total energy  int_skin Psi_HGO + int_muscle Psi_NH + int_membrane Psi_mem  with
  residual and Jacobian from ``ufl.derivative``;
- bottom clamped, lateral faces on rollers, top free except the membrane;
- Newton (PETSc SNES, full steps); each linear step is GMRES preconditioned by a MUMPS LU
  factorisation of an earlier tangent, refactorised only when GMRES needs more than
  ``solver.refactor_krylov`` iterations per Newton step (factorisation costs ~45 triangular
  solves on the paper mesh); GMRES (right-preconditioned: it sees the true residual) stops
  at a relative ``solver.krylov_rtol`` or once its residual is below a tenth of the Newton
  tolerance ``solver.atol``; the initial guess of each increment is the quadratic through
  the three previous converged states (linear after the first increment), which saves the
  third Newton iteration of most increments; an increment that fails is retried from the
  same predictor with a fresh factorisation, then with one at every Newton step (a large
  first Newton step can make the factorisation stale within one solve, so that GMRES
  stalls although Newton converges), then halved (cut-back) up to ``solver.max_cutbacks``
  times; frames are still reported at the requested t.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from mpi4py import MPI

from skinfem.config import Config, SolverConfig
from skinfem.effects import Effect, ModelTerms, get_effect
from skinfem.fenics import JIT_OPTIONS, PETSc, dolfinx, ufl
from skinfem.materials import LaminaStiffness, hgo_energy, membrane_energy, neo_hookean_energy
from skinfem.memory import limit_factor_memory, raise_if_out_of_memory
from skinfem.mesh import DEFAULT_MESH_DIR, TAGS, ensure_mesh, file_sha256, read_mesh
from skinfem.params import Design, SkinParams
from skinfem.pseudo_time import FarStart, pseudo_transient
from skinfem.strain import ObservedCells, SkinStrainSampler, SurfaceStrainSampler, top_skin_cells

DIVERGED_LINE_SEARCH = PETSc.SNES.ConvergedReason.DIVERGED_LINE_SEARCH
DIVERGED_LINEAR_SOLVE = PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE


class Factorisation(IntEnum):
    """When a Newton solve factorises the tangent (its GMRES preconditioner)."""

    REUSE = 0  # keep the last factorisation
    FIRST_STEP = 1  # factorise at the first Newton step, then reuse it
    EVERY_STEP = 2  # factorise at every Newton step (Newton–LU)


class ConvergenceError(RuntimeError):
    """Newton did not converge even after the allowed cut-backs."""


@dataclass
class StrainFrames:
    """Skin log strain at the requested load fractions of one simulation.

    Attributes:
        t: (n_frames,) load fractions in (0, 1].
        strain: (n_frames, n_cells, 3) log strain components (xx, yy, xy), dimensionless.
        xy: (n_cells, 2) reference centroids of the observed skin cells [mm].
        volume: (n_cells,) reference cell volumes [mm^3].
        newton_iterations: Newton iterations of every accepted increment.
        cutbacks: number of halved increments.
        seconds: wall time of the simulation [s].
    """

    t: np.ndarray
    strain: np.ndarray
    xy: np.ndarray
    volume: np.ndarray
    newton_iterations: list[int] = field(default_factory=list)
    cutbacks: int = 0
    seconds: float = 0.0


@dataclass
class _Ramp:
    """State of a load ramp (:meth:`SkinModel.simulate`): the load fraction reached, the next
    increment, up to two earlier converged states (t, dofs) for the predictor, the next solve's
    factorisation policy, and the Newton iterations and cut-backs so far."""

    step: float
    t: float = 0.0
    history: list[tuple[float, np.ndarray]] = field(default_factory=list)
    policy: Factorisation = Factorisation.FIRST_STEP  # new parameters: a fresh factorisation
    iterations: list[int] = field(default_factory=list)
    cutbacks: int = 0


def extrapolate(t_new: float, states: Sequence[tuple[float, np.ndarray]]) -> np.ndarray:
    """Value at load fraction ``t_new`` of the Lagrange polynomial through ``states``, a list
    of (t, u) pairs with distinct t (degree len(states) - 1; exact for such polynomials)."""
    prediction = np.zeros_like(states[0][1])
    for i, (t_i, u_i) in enumerate(states):
        weight = np.prod([(t_new - t_j) / (t_i - t_j) for j, (t_j, _) in enumerate(states) if j != i])
        prediction += weight * u_i
    return prediction


class SkinModel:
    """Finite-element model of the layered block with the active membrane.

    Args:
        config: validated configuration (mesh, materials, solver).
        comm: MPI communicator the model is distributed over.
        mesh_dir: where meshes are read from / generated into.
        effects: names of :mod:`skinfem.effects` to include (or :class:`~skinfem.effects.Effect`
            instances, e.g. a defect built for synthetic data); their parameters start at the
            null values (the baseline) and are set with :meth:`set_effects`.
    """

    def __init__(
        self,
        config: Config,
        comm: MPI.Comm = MPI.COMM_WORLD,
        mesh_dir=DEFAULT_MESH_DIR,
        effects: Sequence[str | Effect] = (),
    ):
        t0 = time.perf_counter()
        self.config = config
        self.comm = comm
        self.mesh_path = ensure_mesh(config, mesh_dir, comm)
        self.mesh_sha256 = comm.bcast(file_sha256(self.mesh_path) if comm.rank == 0 else None)
        data = read_mesh(self.mesh_path, comm)
        self.mesh, self.cell_tags, self.facet_tags = data.mesh, data.cell_tags, data.facet_tags
        self.V = dolfinx.fem.functionspace(self.mesh, ("Lagrange", config.solver.element_degree, (3,)))
        self.u = dolfinx.fem.Function(self.V, name="displacement")
        # strain is measured from the unloaded equilibrium u_ref (zero unless pre-stressed)
        self.u_ref = dolfinx.fem.Function(self.V, name="reference_displacement")
        c = lambda value: dolfinx.fem.Constant(self.mesh, PETSc.ScalarType(value))  # noqa: E731
        self.mu, self.k1, self.k2, self.kappa = c(1.0), c(0.0), c(1.0), c(0.0)
        self.a0 = dolfinx.fem.Constant(self.mesh, np.array([1.0, 0.0, 0.0], dtype=PETSc.ScalarType))
        self.alpha11, self.alpha22 = c(0.0), c(0.0)
        self.has_membrane = config.membrane.model == "elastic"
        terms = self._model_terms(effects)
        self.energy = self._energy(terms)
        self.bcs = self._boundary_conditions()
        self.problem = self._nonlinear_problem()
        self.factorizations = 0  # of the current simulation
        self._rebuild_pending = True  # the next Newton solve factorises at its first step (none yet)
        self.far_starts: list[FarStart] = []  # of the last solve_frames
        self.strain_sampler = self._observed_strain(terms)
        self.setup_seconds = time.perf_counter() - t0

    def _observed_strain(self, terms: ModelTerms) -> ObservedCells:
        """The sampler of ``observable.kind`` on the top skin cells; with effects, the strain
        is measured from the skin's unloaded equilibrium u_ref."""
        config = self.config
        depth = config.mesh.skin_thickness / config.mesh.skin_layers
        cells = top_skin_cells(self.mesh, self.cell_tags, TAGS["skin"], depth)
        if config.observable.kind == "surface":
            return SurfaceStrainSampler(
                self.u, cells, config.solver.quadrature_degree, self.u_ref if self.effects else None
            )
        F_seen = ufl.Identity(3) + ufl.grad(self.u)
        if self.effects:  # the skin's gradient relative to its unloaded equilibrium
            F_seen = self._skin_gradient(terms, self.u) * ufl.inv(self._skin_gradient(terms, self.u_ref))
        return SkinStrainSampler(self.u, cells, config.solver.quadrature_degree, F_seen)

    @staticmethod
    def _skin_gradient(terms: ModelTerms, w) -> ufl.core.expr.Expr:
        """Deformation gradient of displacement ``w`` in the mapped skin: I + grad(w) G^-1."""
        return ufl.Identity(3) + ufl.grad(w) * ufl.inv(terms.skin_map)

    def _energy(self, terms: ModelTerms) -> ufl.Form:
        """Total energy: HGO skin (with the effects' map, pre-stretch and stiffness), neo-Hookean
        muscle and, for an elastic membrane, the membrane with its eigen-strain."""
        config = self.config
        dx = ufl.Measure(
            "dx",
            domain=self.mesh,
            subdomain_data=self.cell_tags,
            metadata={"quadrature_degree": config.solver.quadrature_degree},
        )
        F = ufl.Identity(3) + ufl.grad(self.u)
        F_elastic, weight = F, 1.0  # baseline: stress-free skin of mesh thickness
        if self.effects:
            G, F0 = terms.skin_map, terms.skin_prestretch
            F_elastic = self._skin_gradient(terms, self.u) * F0
            weight = terms.skin_stiffness * ufl.det(G) / ufl.det(F0)
        skin = config.skin
        energy = (
            weight
            * hgo_energy(
                F_elastic,
                self.mu,
                self.k1,
                self.k2,
                self.kappa,
                self.a0,
                terms.skin_bulk_ratio * self.mu,
                skin.fiber_invariant,
            )
            * dx(TAGS["skin"])
        )
        muscle_K = config.muscle.bulk_ratio * terms.muscle_mu
        energy += neo_hookean_energy(F, terms.muscle_mu, muscle_K) * dx(TAGS["muscle"])
        if self.has_membrane:
            energy += membrane_energy(F, self.alpha11, self.alpha22, terms.lamina) * dx(TAGS["membrane"])
        return energy

    def _nonlinear_problem(self) -> dolfinx.fem.petsc.NonlinearProblem:
        """Newton (SNES, full steps) on the energy's residual and exact Jacobian; linear steps
        by MUMPS LU, or GMRES preconditioned by a kept factorisation (module doc)."""
        solver = self.config.solver
        residual = ufl.derivative(self.energy, self.u, ufl.TestFunction(self.V))
        jacobian = ufl.derivative(residual, self.u, ufl.TrialFunction(self.V))
        self._prefix = f"skinid_{id(self)}_"
        problem = dolfinx.fem.petsc.NonlinearProblem(
            residual,
            self.u,
            bcs=self.bcs,
            J=jacobian,
            petsc_options_prefix=self._prefix,
            jit_options=JIT_OPTIONS,
            petsc_options={
                "snes_type": "newtonls",
                "snes_linesearch_type": "basic",
                "snes_rtol": solver.rtol,
                "snes_atol": solver.atol,
                "snes_stol": 1e-9,
                "snes_max_it": solver.max_iterations,
                "pc_type": "lu",
                "pc_factor_mat_solver_type": "mumps",
                **(self._krylov_options(solver) if solver.refactor_krylov else {"ksp_type": "preonly"}),
            },
        )
        problem.solver.setConvergenceHistory(reset=True)  # each solve's residual norms
        self._limit_factor_memory(problem)
        return problem

    @staticmethod
    def _limit_factor_memory(problem: dolfinx.fem.petsc.NonlinearProblem) -> None:
        """Make the LU factor of the tangent now, with this rank's memory limit (:mod:`skinfem.memory`)."""
        ksp = problem.solver.getKSP()
        ksp.setOperators(problem.A)
        limit_factor_memory(ksp.getPC())

    def _model_terms(self, effects: Sequence[str | Effect]) -> ModelTerms:
        """Baseline energy terms, edited by each effect; effect parameters become Constants."""
        config, mesh = self.config, self.mesh
        terms = ModelTerms(
            skin_map=ufl.Identity(3),
            skin_prestretch=ufl.Identity(3),
            skin_bulk_ratio=config.skin.bulk_ratio,
            muscle_mu=config.muscle.mu,
            lamina=LaminaStiffness.from_config(config.membrane) if config.membrane.model == "elastic" else None,
            x=ufl.SpatialCoordinate(mesh),
        )
        self.effects = [get_effect(e)() if isinstance(e, str) else e for e in dict.fromkeys(effects)]
        self.effect_constants: dict[str, dolfinx.fem.Constant] = {}
        for effect in self.effects:
            p = {}
            for q in effect.parameters:
                p[q.name] = dolfinx.fem.Constant(mesh, PETSc.ScalarType(q.null))
                self.effect_constants[f"{effect.name}.{q.name}"] = p[q.name]
            effect.apply(terms, p)
        self.prestressed = any(e.prestressed for e in self.effects)
        return terms

    def set_effects(self, values: dict[str, float]) -> None:
        """Set effect parameters by qualified name (``"pre_stretch.eps_xx"``); others keep theirs.

        Raises:
            ValueError: an unknown name (the message lists the model's effect parameters) or a
                non-finite value.
        """
        for name, value in values.items():
            if name not in self.effect_constants:
                known = ", ".join(self.effect_constants) or "none (model built without effects)"
                raise ValueError(f"unknown effect parameter '{name}'; this model has: {known}")
            if not np.isfinite(value):
                raise ValueError(f"effect parameter {name} must be finite, got {value}")
            self.effect_constants[name].value = value

    # -- boundary conditions -------------------------------------------------------------
    def _boundary_conditions(self):
        mesh, V = self.mesh, self.V
        fdim = mesh.topology.dim - 1
        half = self.config.mesh.length / 2
        z_bottom = -(self.config.mesh.skin_thickness + self.config.mesh.muscle_thickness)
        tol = 1e-8 * half
        locate = dolfinx.mesh.locate_entities_boundary
        bottom = locate(mesh, fdim, lambda x: np.isclose(x[2], z_bottom, atol=tol))
        x_sides = locate(mesh, fdim, lambda x: np.isclose(np.abs(x[0]), half, atol=tol))
        y_sides = locate(mesh, fdim, lambda x: np.isclose(np.abs(x[1]), half, atol=tol))
        zero = PETSc.ScalarType(0)
        topo = dolfinx.fem.locate_dofs_topological
        bcs = [
            dolfinx.fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), topo(V, fdim, bottom), V),
            dolfinx.fem.dirichletbc(zero, topo(V.sub(0), fdim, x_sides), V.sub(0)),
            dolfinx.fem.dirichletbc(zero, topo(V.sub(1), fdim, y_sides), V.sub(1)),
        ]
        if self.config.membrane.model == "rigid":
            footprint = self.facet_tags.find(TAGS["footprint"])
            self._driver = []
            for i, alpha in ((0, self.alpha11), (1, self.alpha22)):
                Vi, _ = V.sub(i).collapse()
                g = dolfinx.fem.Function(Vi)
                dofs = topo((V.sub(i), Vi), fdim, footprint)
                bcs.append(dolfinx.fem.dirichletbc(g, dofs, V.sub(i)))
                self._driver.append((g, i, alpha))
        return bcs

    def set_load(self, t: float, design: Design) -> None:
        """The membrane's eigen-strain (or the rigid driver's displacement) at load fraction ``t`` of ``design``."""
        self.alpha11.value = t * design.alpha11
        self.alpha22.value = t * design.alpha22
        if not self.has_membrane:
            for g, i, alpha in self._driver:
                value = float(alpha.value)
                g.interpolate(lambda x, i=i, value=value: value * x[i])

    def set_params(self, params: SkinParams) -> None:
        """Load the skin parameters into the compiled forms (theta in degrees)."""
        self.mu.value = params.mu
        self.k1.value = params.k1
        self.k2.value = params.k2
        self.kappa.value = params.kappa
        th = params.theta_rad
        self.a0.value[:] = (np.cos(th), np.sin(th), 0.0)

    # -- solving ---------------------------------------------------------------------------
    @staticmethod
    def _krylov_options(solver: SolverConfig) -> dict:
        """GMRES on the exact tangent, preconditioned (from the right, so that GMRES measures
        the true residual in N) by a factorization kept across solves; a linear residual below
        a tenth of the Newton tolerance cannot hold up convergence."""
        return {
            "ksp_type": "gmres",
            "ksp_pc_side": "right",
            "ksp_rtol": solver.krylov_rtol,
            "ksp_atol": 0.1 * solver.atol,
            "ksp_gmres_restart": 100,
            "ksp_max_it": 100,
            "snes_lag_preconditioner_persists": True,
        }

    def set_snes_option(self, name: str, value) -> None:
        """Set one option of this model's SNES: through the options database, which SNES rereads,
        and out of it again, so that later rereads keep the value instead of repeating it."""
        key = f"{self._prefix}{name}"
        options = PETSc.Options()
        options[key] = value
        self.problem.solver.setFromOptions()
        del options[key]

    def _set_lag(self, lag: int) -> None:
        """PETSc's preconditioner lag: 1 rebuild at every Jacobian, -2 at the next one only and
        then never."""
        self.set_snes_option("snes_lag_preconditioner", lag)

    def release_factorisation(self) -> None:
        """Free the kept LU factors, most of a model's memory (several GB for a quadratic mesh
        of 10^5 dofs), e.g. while a model of another mesh runs on the same rank; the next Newton
        solve factorises again."""
        self.problem.solver.getKSP().getPC().reset()
        self._limit_factor_memory(self.problem)
        self._rebuild_pending = True

    def _newton(self, policy: Factorisation) -> tuple[bool, int, float]:
        """One SNES solve of R(u) = 0 from the current state, factorising the
        tangent as ``policy`` says (with ``solver.refactor_krylov = 0`` at every Newton step
        regardless). Returns (converged, Newton iterations, GMRES iterations per Newton step)."""
        snes = self.problem.solver
        reuse = self.config.solver.refactor_krylov > 0
        if self._rebuild_pending:  # PETSc factorises at this solve's first step anyway
            policy = max(policy, Factorisation.FIRST_STEP)
        if reuse and policy != Factorisation.REUSE:
            self._set_lag(1 if policy == Factorisation.EVERY_STEP else -2)
        self.problem.solve()
        reason = snes.getConvergedReason()
        if reason == DIVERGED_LINEAR_SOLVE:
            raise_if_out_of_memory(snes.getKSP().getPC())
        its = snes.getIterationNumber()  # 0: converged at the start, no Jacobian built
        if reuse and policy == Factorisation.EVERY_STEP:  # lag back from 1; "never" needs a rebuild first
            self._set_lag(-2)
        self._rebuild_pending = reuse and (
            policy == Factorisation.EVERY_STEP or (policy != Factorisation.REUSE and its == 0)
        )
        # a step whose linear solve or line search failed had its tangent factorised but is not counted by SNES
        failed_step = reason in (DIVERGED_LINE_SEARCH, DIVERGED_LINEAR_SOLVE)
        if not reuse or policy == Factorisation.EVERY_STEP:
            self.factorizations += its + failed_step
        elif policy == Factorisation.FIRST_STEP and its + failed_step > 0:
            self.factorizations += 1
        ok = reason > 0 and np.all(np.isfinite(self.u.x.array))
        ok = bool(self.comm.allreduce(ok, op=MPI.LAND))
        return ok, its, snes.getLinearSolveIterations() / max(its, 1)

    def _newton_escalating(
        self, policy: Factorisation, most: Factorisation = Factorisation.EVERY_STEP
    ) -> tuple[bool, int, float]:
        """:meth:`_newton` from the current state; after a failure once more from the same start
        with each more frequent factorisation up to ``most`` (default Newton–LU): a stale
        factorisation, or one made stale by a large first Newton step, can stall GMRES
        (DIVERGED_LINEAR_SOLVE) where Newton itself converges. Returns the last attempt's result."""
        start = self.u.x.array.copy()
        while True:
            converged, its, krylov = self._newton(policy)
            if converged or policy >= most or self.config.solver.refactor_krylov == 0:
                return converged, its, krylov
            self.u.x.array[:] = start
            policy = Factorisation(policy + 1)

    def _solve_far_start(self) -> bool:
        """Equilibrium from a current state far from it (e.g. another mesh's fields) by
        pseudo-transient continuation (:mod:`skinfem.pseudo_time`), whose states descend the
        energy where those of a residual homotopy pass through saddle points and where Newton
        stalls (docs/criticism.md §3). Records a :class:`~skinfem.pseudo_time.FarStart`;
        returns whether it converged (the state is then the equilibrium, else undefined)."""
        solver = self.config.solver
        self.release_factorisation()  # one factorisation held at a time: pseudo-time makes its own
        solve = pseudo_transient(
            self.problem, solver.atol, refactor_krylov=solver.refactor_krylov, krylov_rtol=solver.krylov_rtol
        )
        self.factorizations += solve.factorisations
        self.far_starts.append(solve)
        return solve.converged

    def load_fractions(self) -> np.ndarray:
        """(increments,) the load fractions t of the saved frames: 1/n, 2/n, ..., 1."""
        n = self.config.solver.increments
        return np.arange(1, n + 1) / n

    def simulate(
        self,
        params: SkinParams,
        design: Design,
        on_frame: Callable[[float], None] | None = None,
        on_reference: Callable[[], None] | None = None,
    ) -> StrainFrames:
        """Ramp the membrane eigen-strain and return the skin log strain at every frame.

        ``on_frame(t)`` is called (collectively) after each frame converged, e.g. to write
        ParaView fields; ``on_reference()`` after the unloaded equilibrium of a pre-stressed
        model converged (e.g. for its sensitivities).

        Raises:
            ConvergenceError: an increment failed after ``solver.max_cutbacks`` halvings.
        """
        start = time.perf_counter()
        self.set_params(params)
        self.factorizations = 0
        self.u.x.array[:] = 0.0
        if not self._reference_equilibrium(
            design, None, lambda: self._newton_escalating(Factorisation.FIRST_STEP)[0], on_reference
        ):
            raise ConvergenceError(f"Newton failed on the unloaded pre-stressed state for {params}")
        targets = self.load_fractions()
        ramp = _Ramp(step=targets[0])
        frames = []
        for target in targets:
            self._ramp_to(target, ramp, design, params)
            frames.append(self.strain_sampler())
            if on_frame is not None:
                on_frame(float(target))
        seconds = time.perf_counter() - start
        if self.comm.rank != 0:
            return StrainFrames(targets, None, None, None, ramp.iterations, ramp.cutbacks, seconds)
        return StrainFrames(
            t=targets,
            strain=np.stack(frames),
            xy=self.strain_sampler.xy,
            volume=self.strain_sampler.volume,
            newton_iterations=ramp.iterations,
            cutbacks=ramp.cutbacks,
            seconds=seconds,
        )

    def _reference_equilibrium(
        self,
        design: Design,
        guess: np.ndarray | None,
        newton: Callable[[], bool],
        on_reference: Callable[[], None] | None,
    ) -> bool:
        """The unloaded equilibrium of a pre-stressed model into ``u_ref`` (zero otherwise), by
        ``newton()`` from ``guess`` (None: the current state). Returns whether it converged."""
        self.u_ref.x.array[:] = 0.0
        if not self.prestressed:
            return True
        if guess is not None:
            self.u.x.array[:] = guess
        self.set_load(0.0, design)
        if not newton():
            return False
        self.u_ref.x.array[:] = self.u.x.array
        if on_reference is not None:
            on_reference()
        return True

    def _ramp_to(self, target: float, ramp: _Ramp, design: Design, params: SkinParams) -> None:
        """Increase the load fraction from ``ramp.t`` to ``target`` in increments of at most
        ``ramp.step``: each started from the quadratic predictor, doubled after a success (up to
        the first frame's step), halved after a failure (ConvergenceError after
        ``solver.max_cutbacks``)."""
        x = self.u.x.array
        base_step = self.load_fractions()[0]
        while ramp.t < target - 1e-12:
            ramp.step = min(ramp.step, target - ramp.t)
            t_new = ramp.t + ramp.step
            saved = x.copy()
            x[:] = extrapolate(t_new, [(ramp.t, saved), *ramp.history])
            self.set_load(t_new, design)
            converged, its, krylov = self._newton_escalating(ramp.policy)
            if converged:
                ramp.history = [(ramp.t, saved), *ramp.history[:1]]
                ramp.t = t_new
                ramp.iterations.append(its)
                ramp.step = min(2 * ramp.step, base_step)
                stale = krylov > self.config.solver.refactor_krylov
                ramp.policy = Factorisation.FIRST_STEP if stale else Factorisation.REUSE
                continue
            x[:] = saved
            ramp.policy = Factorisation.FIRST_STEP
            ramp.cutbacks += 1
            ramp.step /= 2
            if ramp.cutbacks > self.config.solver.max_cutbacks:
                raise ConvergenceError(
                    f"Newton failed at load fraction t = {t_new:.4g} for {params} and {design} "
                    f"after {ramp.cutbacks - 1} cut-backs"
                )

    def solve_frames(
        self,
        params: SkinParams,
        design: Design,
        guesses: Sequence[tuple[float, np.ndarray]],
        reference_guess: np.ndarray | None = None,
        on_frame: Callable[[float], None] | None = None,
        on_reference: Callable[[], None] | None = None,
        max_iterations: int = 8,
        factorisation: Factorisation = Factorisation.REUSE,
    ) -> bool:
        """Parameter continuation: solve the equilibria at the load fractions of ``guesses``
        ((t, dof array) pairs, increasing t) directly, each Newton started from its guess —
        e.g. the converged state of nearby parameters moved along its sensitivities — instead
        of ramping the load from zero. ``reference_guess`` starts the unloaded equilibrium of a
        pre-stressed model (zero if None).

        ``factorisation`` is the first attempt's policy: ``REUSE`` (the previous solve's
        factorisation preconditions GMRES) for guesses from nearby parameters (a fresh one for
        the unloaded reference: the kept factorisation is of a loaded frame, a preconditioner
        so poor there that GMRES ran out of iterations before the retry); ``EVERY_STEP``
        marks guesses far from equilibrium, such as another mesh's fields, where Newton stalls:
        the first frame (and the unloaded reference) is then solved by pseudo-transient
        continuation (:meth:`_solve_far_start`), cheaper than a ramp on a fine mesh. A failed
        ``REUSE`` attempt is retried once with a fresh factorisation, not escalated to Newton–LU
        (up to ``max_iterations`` factorisations): that is left to the load ramp the caller
        falls back to. The correction made to one frame's guess is added to the next frame's
        guess (the guesses share their error, e.g. another mesh's interpolation), so with
        ``EVERY_STEP`` later frames take Newton with GMRES on a fresh factorisation, escalated
        up to Newton–LU and then the far-start solve if that fails.

        Equilibrium does not depend on the load path, so where it is unique the states equal
        :meth:`simulate`'s to the Newton tolerance. The factorisation of the previous solve
        preconditions the first Newton step (refreshed as in :meth:`simulate`). Callbacks as in
        :meth:`simulate`.

        Returns:
            False as soon as a solve fails (Newton within ``max_iterations``; the state is then
            undefined: ramp with :meth:`simulate`), True when every frame converged.

        (Over 60 lines only by this docstring: the code is one loop over the frames.)
        """
        self.set_snes_option("snes_max_it", max_iterations)
        most = max(factorisation, Factorisation.FIRST_STEP)

        def newton(policy: Factorisation, corrected: bool = False) -> tuple[bool, float]:  # (converged, GMRES/step)
            if factorisation != Factorisation.EVERY_STEP:
                converged, _, krylov = self._newton_escalating(policy, most)
                return converged, krylov
            if corrected:  # near equilibrium: GMRES first, the far-start solve only if that fails
                start = self.u.x.array.copy()
                converged, _, krylov = self._newton_escalating(policy, most)
                if converged:
                    return True, krylov
                self.u.x.array[:] = start
            return self._solve_far_start(), 1.0

        try:
            self.set_params(params)
            self.factorizations, self.far_starts = 0, []
            start = np.zeros_like(self.u.x.array) if reference_guess is None else reference_guess
            reference = max(factorisation, Factorisation.FIRST_STEP)  # the kept factorisation is a loaded frame's
            if not self._reference_equilibrium(design, start, lambda: newton(reference)[0], on_reference):
                return False
            policy, correction = factorisation, None  # correction: last converged frame less its guess
            for t, guess in guesses:
                self.u.x.array[:] = guess if correction is None else guess + correction
                self.set_load(t, design)
                converged, krylov = newton(policy, correction is not None)
                if not converged:
                    return False
                correction = self.u.x.array - guess
                stale = krylov > self.config.solver.refactor_krylov
                fresh = Factorisation.FIRST_STEP if stale else Factorisation.REUSE
                policy = max(min(factorisation, Factorisation.FIRST_STEP), fresh)  # far start: the first frame only
                if on_frame is not None:
                    on_frame(float(t))
            return True
        finally:
            self.set_snes_option("snes_max_it", self.config.solver.max_iterations)

    @property
    def n_dofs(self) -> int:
        imap = self.V.dofmap.index_map
        return imap.size_global * self.V.dofmap.index_map_bs
