"""Forward models for model criticism: parameter vector -> strain fields of the observations.

A forward model maps x = (mu, k1, k2, kappa, theta [deg], effect parameters...) — the names
in ``forward.names``, with prior ranges ``forward.bounds`` — to the skin log strain of every
observation, (n_obs, n_points, 3), or None where the model has no solution (Newton failed).
Two implementations share this interface:

- :class:`FEForward`: the finite-element model (:class:`skinfem.model.SkinModel`) built with
  every candidate effect of :mod:`skinfem.effects` (at their null values it *is* the
  baseline), on any mesh, measured at the observations' points by the DIC operator of
  :mod:`skinfem.dic`. It runs one simulation per distinct membrane design and picks the
  observed load fractions. Simulations (one per parameter point and design) are spread over
  MPI ranks, each rank owning a serial model, so that even a single point's designs run in
  parallel; results are cached by parameter vector, in memory and, with
  ``cache_dir``, on disk (one ``.npy`` per point, written atomically once its batch of
  simulations is done), so a killed check resumes without repeating finished simulations.
- :class:`TaylorForward`: the first-order Taylor expansion of another forward model about a
  point (exact for linear effects, microseconds per call): the fast emulator the false-alarm
  study runs thousands of criticism passes on.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

from skinfem.config import N_SKIN, PARAM_NAMES, Config
from skinfem.continuation import Continuation, ConvergedStates, transfer
from skinfem.dic import StrainGauge, SurfaceStrainGauge
from skinfem.effects import EFFECTS, effect_parameters
from skinfem.model import Factorisation
from skinfem.parallel import collective
from skinfem.pseudo_time import FarStart
from skinfem.sensitivity import DisplacementSensitivity

log = logging.getLogger(__name__)

MAX_CUTBACKS = 3  # load-step halvings before an FE run of a check counts as failed
CONTINUATION_ITERATIONS = 8  # Newton iterations from a nearby point's states before ramping instead
TRANSFER_ITERATIONS = 12  # Newton iterations of a later frame from another mesh's states before pseudo-time


class ForwardModel:
    """Interface: ``names``, ``bounds`` (p, 2), ``null`` (p,) and ``evaluate_many``; models with
    exact derivatives also implement ``evaluate_with_jacobian`` (``exact_jacobian = True``)."""

    names: list[str]
    bounds: np.ndarray
    null: np.ndarray
    runs: int = 0
    exact_jacobian: bool = False

    def evaluate_many(self, points: Sequence[np.ndarray]) -> list[np.ndarray | None]:
        """Fields (n_obs, n_points, 3) at each parameter vector (p,); None where it failed."""
        raise NotImplementedError

    def evaluate_with_jacobian(
        self, points: Sequence[np.ndarray], names: Sequence[str]
    ) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """(fields, d fields / d x[names] (n_obs, n_points, 3, k)) at each point; None where it failed."""
        raise NotImplementedError

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate_many([x])[0]

    def index(self, names: Sequence[str]) -> list[int]:
        """Positions of parameter ``names`` in x; ValueError naming an unknown one."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise ValueError(f"unknown parameter(s) {', '.join(missing)}; known: {', '.join(self.names)}")
        return [self.names.index(n) for n in names]


def parameter_space(skin_bounds: np.ndarray, effects: Sequence[str]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, bounds (p, 2) and null vector of skin parameters + the effects' parameters.

    The skin parameters' null entries are the box centres (they have no null value).
    """
    extra = effect_parameters(list(effects))
    names = list(PARAM_NAMES) + [name for name, _ in extra]
    bounds = np.vstack([np.asarray(skin_bounds, float)] + [[q.low, q.high] for _, q in extra])
    null = np.concatenate([bounds[:N_SKIN].mean(axis=1), [q.null for _, q in extra]])
    return names, bounds, null


def prestressing_parameters(names: Sequence[str]) -> list[str]:
    """The parameters in ``names`` of the effects that pre-stress the unloaded skin (e.g. the
    pre-stretch's). With all of them at zero every fiber of the unloaded skin sits at the
    tension-only switch, and their derivatives there are one-sided (docs/criticism.md §4)."""
    return [n for n in names if "." in n and EFFECTS[n.split(".")[0]].prestressed]


@dataclass(frozen=True)
class PointSet:
    """Where one observation is measured: membrane design, load fraction, points [mm]."""

    alpha: np.ndarray  # (2,)
    t: float
    xy: np.ndarray  # (n, 2)


@dataclass(frozen=True)
class FailedRun:
    """A parameter point whose FE simulation did not converge (a rejected step, not a crash)."""

    x: np.ndarray
    message: str


@dataclass(frozen=True)
class TransferredRun:
    """One simulation started from another mesh's fields (:meth:`FEForward.continue_from`)."""

    design: tuple[float, float]  # (alpha11, alpha22)
    seconds: float
    factorizations: int  # factorisations of the tangent, a ramp's included
    continued: bool  # False: the far-start solve did not converge and the load was ramped
    far_starts: list[FarStart]  # each equilibrium solved from the interpolated fields

    @classmethod
    def from_json(cls, d: dict) -> TransferredRun:
        """From :func:`dataclasses.asdict` of one as a report.json holds it."""
        far_starts = [FarStart.from_json(f) for f in d["far_starts"]]
        return cls(tuple(d["design"]), d["seconds"], d["factorizations"], d["continued"], far_starts)


class _FrameRecord:
    """What one simulation of design ``j`` of ``forward`` at ``x`` records as it converges: the
    observed frames' fields and derivatives by ``names`` (``out``, (n_obs, n_max, 3, 1 + k)) and
    the converged states for continuation (``states``), from the model's frame and reference
    callbacks (:meth:`measure`, :meth:`at_reference`)."""

    def __init__(self, forward: FEForward, x: np.ndarray, names: tuple[str, ...], j: int):
        self.forward, self.names, self.j = forward, names, j
        self.t_grid = forward.model.load_fractions()
        self.indices = forward.index(names)
        self.moving = forward.moving_reference(x, names)
        self.d_reference = [None] * len(names)  # d u_ref / d p of the pre-stressed reference (None: zero)
        self.out = np.zeros((len(forward.picks), max(forward.counts), 3, 1 + len(names)))
        self.states = ConvergedStates(np.array(x, dtype=float), None, {})

    def frames(self) -> list[float]:
        """The load fractions observed in design ``j``, ascending."""
        return sorted({float(self.t_grid[k]) for jj, k in self.forward.picks if jj == self.j})

    def at_reference(self) -> None:
        """The unloaded reference converged: keep it, and its derivatives where it moves."""
        forward = self.forward
        self.states.reference = forward.model.u_ref.x.array.copy()
        if self.moving:
            for k, d_ref in zip(self.moving, forward.sensitivity([self.names[k] for k in self.moving])):
                self.d_reference[k] = d_ref
                self.states.sensitivities[self.indices[k]] = (d_ref.x.array.copy(), {})

    def measure(self, t: float) -> None:
        """Load fraction ``t`` converged: measure the observations made there, keep the state."""
        forward, model = self.forward, self.forward.model
        k = int(np.argmin(np.abs(self.t_grid - t)))
        observed = [o for o, pick in enumerate(forward.picks) if pick == (self.j, k)]
        if not observed:
            return
        du = forward.sensitivity(self.names) if self.names else []
        for o in observed:
            gauge, n = forward.gauges[o], forward.counts[o]
            self.out[o, :n, :, 0] = gauge()
            for i, derivative in enumerate(gauge.derivatives(du, self.d_reference)):
                self.out[o, :n, :, 1 + i] = derivative
        self.states.frames[float(self.t_grid[k])] = model.u.x.array.copy()
        for i, d_frame in zip(self.indices, du):
            self.states.sensitivities.setdefault(i, (None, {}))[1][float(self.t_grid[k])] = d_frame.x.array.copy()

    def clear(self) -> None:
        """Forget a failed continuation's records before the load ramp."""
        self.out[:] = 0.0
        self.states.frames.clear()
        self.states.sensitivities.clear()


def _warn_of_ramp(design, far_starts: list[FarStart]) -> None:
    """Warn that the solve from another mesh's fields failed and ``design`` is ramped (slow on a
    fine mesh), with how it went (the last of ``far_starts``: every failed transferred solve
    records one; an earlier one, e.g. the unloaded reference's, converged)."""
    log.warning(
        "design (%g, %g): the solve from another mesh's fields did not converge (%s); ramping the load",
        design.alpha11,
        design.alpha22,
        far_starts[-1].describe(),
    )


class FEForward(ForwardModel):
    """The FE model with every candidate effect, measured by DIC at the observations' points.

    Evaluations return (n_obs, n_max, 3): the strain of the DIC gauge
    (:class:`skinfem.dic.SurfaceStrainGauge`) at each observation's points, zero-padded to the
    largest point count. A point whose simulation does not converge returns None (listed in
    ``failures``); any other error on any rank is raised on every rank as
    :class:`skinfem.parallel.CollectiveError`.

    Args:
        config: the model configuration (mesh, element, solver) the check runs on.
        observations: designs alpha, load fractions t and points of what to predict.
        skin_bounds: (5, 2) prior box of the skin parameters.
        gauge: the DIC strain window.
        increments: load increments per simulation (default: the configuration's); every
            observed t must be a multiple of 1/increments. Equilibrium does not depend on the
            path, so fewer increments give the same fields faster.
        comm: ranks to spread simulations (parameter points x designs) over; each rank runs
            its own serial model.
        cache_dir: folder of finished simulations to reuse and extend (None: memory only).
            Entries are keyed by the configuration, the designs, frames, points and gauge and
            the parameter vector, so a changed setup never reads stale fields.
        continuation: start each simulation from the last converged states of its design at
            nearby parameters, moved along their sensitivities (:mod:`skinfem.continuation`),
            and ramp the load from zero only when that fails; the fields agree with a ramped
            simulation's to the Newton tolerance.

    Raises:
        ValueError: an observed load fraction is not on the increment grid, or a point's
            window leaves the mesh.

    ``evaluate_with_jacobian`` adds exact derivatives by any parameters: forward sensitivities
    (:mod:`skinfem.sensitivity`) of the state and of the pre-stressed reference, measured by the
    linearised DIC gauge — one simulation per point instead of one per parameter.
    """

    exact_jacobian = True

    def __init__(
        self,
        config: Config,
        observations: Sequence[PointSet],
        skin_bounds: np.ndarray,
        mesh_dir: Path | str = "meshes",
        increments: int | None = None,
        comm: MPI.Comm = MPI.COMM_WORLD,
        cache_dir: Path | str | None = None,
        gauge: StrainGauge = StrainGauge(),
        continuation: bool = True,
    ):
        from skinfem.mesh import ensure_mesh
        from skinfem.model import SkinModel

        if increments is not None:
            config = config.with_changes(solver={"increments": int(increments)})
        # a failed point is a rejected step: give up after a few halvings, not the sweep's many
        config = config.with_changes(solver={"max_cutbacks": min(config.solver.max_cutbacks, MAX_CUTBACKS)})
        self.config = config
        self.names, self.bounds, self.null = parameter_space(skin_bounds, list(EFFECTS))
        self.comm = comm
        ensure_mesh(config, mesh_dir, comm)  # built once on rank 0, before any rank reads it
        self.model = collective(
            comm, lambda: SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=list(EFFECTS))
        )
        t_grid = self.model.load_fractions()
        self.designs = sorted({tuple(np.round(o.alpha, 12)) for o in observations})
        self.picks = []  # (design index, frame index) per observation
        for o in observations:
            k = int(np.argmin(np.abs(t_grid - o.t)))
            if abs(t_grid[k] - o.t) > 1e-9:
                raise ValueError(
                    f"observation at t = {o.t} is not on the load grid of {len(t_grid)} increments "
                    f"(t = k/{len(t_grid)}); choose increments so that t * increments is an integer"
                )
            self.picks.append((self.designs.index(tuple(np.round(o.alpha, 12))), k))
        self.counts = [len(o.xy) for o in observations]
        self.gauges = [SurfaceStrainGauge(self.model.u, o.xy, gauge, self.model.u_ref) for o in observations]
        self.sensitivity = DisplacementSensitivity(self.model)
        self._cache: dict[bytes, np.ndarray | None] = {}
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        points = b"".join(np.ascontiguousarray(o.xy, float).tobytes() for o in observations)
        setup = f"{config.to_toml()}\n{self.names}\n{self.designs}\n{self.picks}\n{gauge}\n{points.hex()}"
        self._setup_hash = hashlib.sha256(setup.encode()).hexdigest()
        self.reused = 0  # simulations read from cache_dir instead of run
        self.continuation = Continuation() if continuation else None
        self.continued = 0  # simulations started from a nearby point's states instead of ramped
        self.transferred = False  # states come from another mesh (continue_from): solved by pseudo-time
        self.transferred_runs: list[TransferredRun] = []  # this rank's, in the order run
        self.failures: list[FailedRun] = []
        self.seconds = 0.0

    def _simulate(self, x: np.ndarray, names: tuple[str, ...], j: int) -> tuple[np.ndarray, bool]:
        """(n_obs, n_max, 3, 1 + k): the fields of the observations of design ``j``, then their
        exact derivatives by ``names``; zero for the other designs' observations. Continued from
        the last converged states of design ``j`` when possible, else ramped from zero; the
        flag says which."""
        from skinfem.params import Design, SkinParams

        model = self.model
        model.set_effects(dict(zip(self.names[N_SKIN:], map(float, x[N_SKIN:]))))
        params, design = SkinParams.from_array(x[:N_SKIN]), Design(*self.designs[j])
        record = _FrameRecord(self, x, names, j)
        started = time.perf_counter()
        start = self.continuation.predict(j, x, record.frames()) if self.continuation is not None else None
        continued = start is not None and model.solve_frames(
            params, design, start[1], start[0], record.measure, record.at_reference, *self._continuation_solver()
        )
        factorizations = model.factorizations
        if not continued:
            if start is not None and self.transferred:  # the costly case: a full ramp on a fine mesh
                _warn_of_ramp(design, model.far_starts)
            record.clear()
            model.simulate(params, design, on_frame=record.measure, on_reference=record.at_reference)
            factorizations += model.factorizations
        if start is not None and self.transferred:
            seconds = time.perf_counter() - started
            run = TransferredRun(self.designs[j], seconds, factorizations, continued, list(model.far_starts))
            self.transferred_runs.append(run)
        if self.continuation is not None:
            self.continuation.record(j, record.states)
        return record.out, continued

    def continue_from(self, other: FEForward, x: np.ndarray) -> None:
        """Start this model's next simulations, at or near ``x``, from ``other``'s last converged
        states (another mesh of the same setup, e.g. the refined mesh of a discretisation
        estimate), each rank from the designs it runs: Newton from the interpolated fields
        instead of a load ramp. A design ``other`` holds no states for (its fields came from
        ``cache_dir``, e.g. in a resumed check) is first solved by ``other`` at ``x``: one run on
        its mesh instead of a ramp on this one. Nothing is solved when this model already holds
        its fields at ``x`` (:meth:`holds`; a resumed check's estimate). ``other``'s factorisation
        is then freed, so that the two meshes' factors are not held at once.

        The first frame of a design is then solved by pseudo-transient continuation, later ones
        by Newton (up to ``TRANSFER_ITERATIONS``) from their guess plus the first frame's
        correction (:meth:`skinfem.model.SkinModel.solve_frames`): from another mesh's fields
        Newton stalls or needs many steps (quadratic check mesh to its edge refinement: 3
        without progress for the biaxial design, 8 for the mixed one), while on a refined mesh
        a load ramp costs more (benchmarks/results/far_start_transfer.json)."""
        if self.continuation is None or other.continuation is None or self.holds(x):
            return
        other._solve_designs_without_states(x)

        def interpolate():
            for j in other.continuation.designs():
                self.continuation.record(j, transfer(other.continuation.states(j), other.model.V, self.model.V))

        collective(self.comm, interpolate)
        other.release_factorisation()  # one mesh's factors held at a time on each rank
        self.transferred = True

    def release_factorisation(self) -> None:
        """Free this rank's model's kept LU factors (:meth:`skinfem.model.SkinModel.release_factorisation`);
        its next simulation factorises again."""
        self.model.release_factorisation()

    def holds(self, x: np.ndarray) -> bool:
        """Whether the fields at ``x`` are known without a simulation: in memory (also from a run
        with derivatives) or in ``cache_dir``, alone or from a run with derivatives by every
        parameter (the estimate's with ``--mesh-drift``), then read into memory, not read again
        by the next evaluation. Collective: every rank gets rank 0's answer."""
        return any(not self._recall([self._encode(x, names)]) for names in ((), tuple(self.names)))

    def _recall(self, keys: list[bytes]) -> list[bytes]:
        """Move into memory what ``keys`` already have (a run with more derivatives, or an entry of
        ``cache_dir``, counted as reused); returns the keys still to simulate. Collective."""
        todo = [key for key in dict.fromkeys(keys) if key not in self._cache]
        self._cache.update(self._from_richer_runs(todo))
        todo = [key for key in todo if key not in self._cache]
        stored = self._from_disk(todo)
        self._cache.update(stored)
        self.reused += len(stored) * len(self.designs)
        return [key for key in todo if key not in stored]

    def _solve_designs_without_states(self, x: np.ndarray) -> None:
        """Run at ``x`` each design that this rank runs for a single point (``j`` = rank mod
        ranks) and holds no converged states for; a failed run leaves it without (then ramped)."""
        key = self._encode(x, ())
        mine = range(self.comm.rank, len(self.designs), self.comm.size)
        missing = [j for j in mine if j not in self.continuation.designs()]
        start = time.perf_counter()
        collective(self.comm, lambda: [self._run(key, j) for j in missing])
        self.runs += self.comm.allreduce(len(missing))
        self.seconds += time.perf_counter() - start

    def moving_reference(self, x: np.ndarray, names: Sequence[str]) -> list[int]:
        """Positions in ``names`` of the parameters whose derivative moves the unloaded reference
        at ``x``: all of them under a pre-stress; without one (every pre-stressing effect at
        zero) the reference is the stress-free u = 0 whatever the other parameters, and only
        the pre-stressing effects' own parameters move it."""
        prestressing = prestressing_parameters(self.names)
        if any(x[self.names.index(n)] != 0.0 for n in prestressing):
            return list(range(len(names)))
        return [k for k, name in enumerate(names) if name in prestressing]

    def _continuation_solver(self) -> tuple[int, Factorisation]:
        """(Newton iterations, first factorisation) of a continued solve before it is ramped:
        from another mesh's states pseudo-time first, else from a nearby
        point's states GMRES on the previous factorisation (SkinModel.solve_frames)."""
        if self.transferred:
            return TRANSFER_ITERATIONS, Factorisation.EVERY_STEP
        return CONTINUATION_ITERATIONS, Factorisation.REUSE

    def _cache_file(self, key: bytes, suffix: str = ".npy") -> Path:
        return self.cache_dir / f"{hashlib.sha256(self._setup_hash.encode() + key).hexdigest()[:32]}{suffix}"

    def _from_disk(self, keys: list[bytes]) -> dict[bytes, np.ndarray | None]:
        """Cached fields (None: a cached failure) of ``keys`` (read on rank 0, shared with all; a
        damaged file is skipped, so the point is simulated again and rewritten, and no rank is
        left waiting for rank 0)."""
        found = {}
        if self.cache_dir is not None and self.comm.rank == 0:
            for key in keys:
                if self._cache_file(key).exists():
                    try:
                        found[key] = np.load(self._cache_file(key))
                    except (ValueError, OSError, EOFError):  # a damaged entry: the point runs again
                        continue
                elif self._cache_file(key, ".failed").exists():
                    found[key] = None
        return self.comm.bcast(found)

    def _to_disk(self, key: bytes, fields: np.ndarray | None, message: str = "") -> None:
        if self.cache_dir is None:
            return
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        path = self._cache_file(key, ".npy" if fields is not None else ".failed")
        partial = path.with_suffix(f".{os.getpid()}.part")
        with open(partial, "wb") as f:
            if fields is None:
                f.write(message.encode())
            else:
                np.save(f, fields)
        partial.replace(path)  # atomic: a kill leaves either no entry or a whole one

    def _run(self, key: bytes, j: int) -> tuple[np.ndarray | None, str, bool]:
        """Design ``j``'s part of one point and whether it was continued (see
        :meth:`_simulate`), or (None, why, False) if Newton failed."""
        from skinfem.model import ConvergenceError

        x, names = self._decode(key)
        try:
            fields, continued = self._simulate(x, names, j)
            return fields, "", continued
        except ConvergenceError as exc:
            return None, str(exc), False

    @staticmethod
    def _encode(x: np.ndarray, names: Sequence[str]) -> bytes:
        return np.asarray(x, dtype=float).tobytes() + "|".join(names).encode()

    def _decode(self, key: bytes) -> tuple[np.ndarray, tuple[str, ...]]:
        n = 8 * len(self.names)
        text = key[n:].decode()
        return np.frombuffer(key[:n]), tuple(text.split("|")) if text else ()

    def _evaluate(self, points: Sequence[np.ndarray], names: Sequence[str]) -> list[np.ndarray | None]:
        """Cached, rank-spread simulations: (n_obs, n_max, 3, 1 + k) per point, None if failed."""
        keys = [self._encode(x, names) for x in points]
        todo = self._recall(keys)
        start = time.perf_counter()
        units = [(key, j) for key in todo for j in range(len(self.designs))]  # one simulation each
        mine = collective(self.comm, lambda: {u: self._run(*u) for u in units[self.comm.rank :: self.comm.size]})
        parts = {u: result for part in self.comm.allgather(mine) for u, result in part.items()}
        for key in todo:
            results = [parts[key, j] for j in range(len(self.designs))]
            failed = [message for fields, message, _ in results if fields is None]
            fields = None if failed else sum(f for f, _, _ in results)  # each design fills its observations
            self.continued += sum(continued for _, _, continued in results)
            self._cache[key] = fields
            if failed:
                self.failures.append(FailedRun(self._decode(key)[0].copy(), failed[0]))
            if self.comm.rank == 0:
                self._to_disk(key, fields, failed[0] if failed else "")
        self.runs += len(todo) * len(self.designs)
        self.seconds += time.perf_counter() - start
        return [self._cache[key] for key in keys]

    def _from_richer_runs(self, keys: list[bytes]) -> dict[bytes, np.ndarray | None]:
        """Fields of ``keys`` from runs in memory at the same point with more derivatives: the
        same simulation, its columns picked (the fields, then each name's derivative); a
        failed run there is a failure here too."""
        found = {}
        for key in keys:
            x, names = self._decode(key)
            for other, fields in self._cache.items():
                other_x, other_names = self._decode(other)
                if np.array_equal(other_x, x) and set(names) <= set(other_names):
                    columns = [0] + [1 + other_names.index(name) for name in names]
                    found[key] = None if fields is None else fields[..., columns]
                    break
        return found

    def evaluate_many(self, points: Sequence[np.ndarray]) -> list[np.ndarray | None]:
        return [None if f is None else f[..., 0] for f in self._evaluate(points, ())]

    def evaluate_with_jacobian(
        self, points: Sequence[np.ndarray], names: Sequence[str]
    ) -> list[tuple[np.ndarray, np.ndarray] | None]:
        self.index(names)  # validates the names
        return [None if f is None else (f[..., 0], f[..., 1:]) for f in self._evaluate(points, tuple(names))]


class TaylorForward(ForwardModel):
    """f(x) ~= f(x0) + J (x - x0) with J from central differences of ``base`` (2p runs).

    Args:
        base: the forward model to expand.
        x0: (p,) expansion point.
        steps: (p,) difference steps (default 1 % of each prior range).
    """

    def __init__(self, base: ForwardModel, x0: np.ndarray, steps: np.ndarray | None = None):
        self.names, self.bounds, self.null = base.names, base.bounds, base.null
        self.base = base
        self.x0 = np.asarray(x0, dtype=float)
        steps = 0.01 * np.ptp(self.bounds, axis=1) if steps is None else np.asarray(steps, float)
        eye = np.diag(steps)
        fields = base.evaluate_many([self.x0] + [self.x0 + e for e in eye] + [self.x0 - e for e in eye])
        if any(f is None for f in fields):
            raise ValueError("the forward model failed near the expansion point; choose another point or steps")
        p = len(self.x0)
        self.f0 = fields[0]
        self.jac = np.stack([(fields[1 + i] - fields[1 + p + i]) / (2 * steps[i]) for i in range(p)], -1)

    exact_jacobian = True

    def evaluate_many(self, points: Sequence[np.ndarray]) -> list[np.ndarray]:
        self.runs += len(points)
        return [self.f0 + self.jac @ (np.asarray(x, float) - self.x0) for x in points]

    def evaluate_with_jacobian(
        self, points: Sequence[np.ndarray], names: Sequence[str]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        columns = self.jac[..., self.index(names)]
        return [(fields, columns) for fields in self.evaluate_many(points)]
