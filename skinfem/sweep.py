"""Simulation sweeps: a Latin hypercube over the skin parameters x the membrane designs.

A sweep runs every (material, design) pair of a configuration and records the frames in one
dataset file (:mod:`skinfem.io`), simulation by simulation, so that a killed sweep loses no
finished simulation and ``resume=True`` runs only what is missing.

Parallel layout: ``MPI.COMM_WORLD`` is split into groups of ``ranks_per_sim`` ranks; each
group owns one :class:`~skinfem.model.SkinModel` and runs every G-th missing simulation
(static interleaving: simulations cost about the same, and no rank is lost to a dispatcher).
World rank 0 is the only writer of the dataset: it records its own group's results and the ones
the other group roots leave in the spool folder ``<out>.spool`` (one file per simulation, written
atomically as soon as it finishes), so a killed sweep loses no simulation that any group
finished: resuming records the spool's leftovers before it runs anything. ``shard=(i, n)``
restricts the sweep to the simulations whose flat index ``i_mat * n_des + i_des`` is ``i``
modulo ``n`` (a Slurm job array); :func:`merge_datasets` joins the shard files.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI
from scipy.stats import qmc

from skinfem.config import Config
from skinfem.io import (
    STATUS_FAILED,
    STATUS_NOT_RUN,
    STATUS_OK,
    StrainDataset,
    create_dataset,
    create_dataset_like,
    write_simulation,
)
from skinfem.mesh import DEFAULT_MESH_DIR, ensure_mesh
from skinfem.outputs import check_output, check_writable, release_lock, remove_output, take_lock, write_atomically
from skinfem.parallel import CollectiveError, on_root


def latin_hypercube(bounds: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` points of a seeded Latin hypercube in the box ``bounds`` (d, 2).

    Every dimension is cut into ``n`` equal strata with exactly one point in each.
    """
    bounds = np.asarray(bounds, dtype=float)
    unit = qmc.LatinHypercube(d=len(bounds), rng=np.random.default_rng(seed)).random(n)
    return bounds[:, 0] + unit * (bounds[:, 1] - bounds[:, 0])


def test_split(n_materials: int, n_test: int, seed: int) -> np.ndarray:
    """Seeded train/test split by material: (n_materials,) int8, 1 for the ``n_test`` held out."""
    rng = np.random.default_rng([seed, 1])
    split = np.zeros(n_materials, dtype=np.int8)
    split[rng.choice(n_materials, size=n_test, replace=False)] = 1
    return split


test_split.__test__ = False  # not a pytest test


@dataclass(frozen=True)
class SweepPlan:
    """What a configuration's sweep simulates.

    Attributes:
        params: (n_mat, 5) mu [MPa], k1 [MPa], k2 [-], kappa [-], theta [deg].
        designs: (n_des, 2) eigen-strains (alpha11, alpha22).
        split: (n_mat,) 0 train, 1 test.
        bounds: (5, 2) the parameter box.
    """

    params: np.ndarray
    designs: np.ndarray
    split: np.ndarray
    bounds: np.ndarray

    @classmethod
    def from_config(cls, config: Config) -> SweepPlan:
        sweep = config.sweep
        bounds = sweep.box
        return cls(
            params=latin_hypercube(bounds, sweep.n_materials, sweep.seed),
            designs=np.array(sweep.designs, dtype=float).reshape(-1, 2),
            split=test_split(sweep.n_materials, sweep.n_test, sweep.seed),
            bounds=bounds,
        )


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` -> (i, n) with 0 <= i < n (Slurm: ``--shard $SLURM_ARRAY_TASK_ID/n``)."""
    try:
        i, n = (int(part) for part in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like i/n (e.g. 3/16), got '{text}'") from None
    if not (n >= 1 and 0 <= i < n):
        raise ValueError(f"--shard {text}: need 0 <= i < n")
    return i, n


def pending_simulations(
    status: np.ndarray, shard: tuple[int, int] = (0, 1), retry_failed: bool = False
) -> list[tuple[int, int]]:
    """(i_mat, i_des) pairs still to run in this shard, material-major order."""
    i, n = shard
    todo = status == STATUS_NOT_RUN
    if retry_failed:
        todo |= status == STATUS_FAILED
    flat = np.flatnonzero(todo.ravel())
    flat = flat[flat % n == i]
    return [divmod(int(k), status.shape[1]) for k in flat]


@dataclass
class SweepReport:
    """Outcome of :func:`run_sweep` (meaningful on world rank 0)."""

    path: Path
    n_run: int
    n_failed: int
    n_total: int
    n_done_before: int
    wall_seconds: float
    sim_seconds: list[float]

    def __str__(self) -> str:
        per = np.mean(self.sim_seconds) if self.sim_seconds else float("nan")
        return (
            f"ran {self.n_run} simulations ({self.n_failed} failed) in {self.wall_seconds:.1f} s, "
            f"{per:.2f} s per simulation; {self.n_done_before} were already done; "
            f"{self.n_total} in the dataset\nwrote {self.path}"
        )


class SweepError(CollectiveError, ValueError):
    """A sweep's output or input refused, raised on every rank."""


def _on_root(comm: MPI.Comm, check: Callable[[], None]) -> None:
    """Run ``check()`` on rank 0; any error it raises is raised on every rank as SweepError."""
    try:
        on_root(comm, check)
    except CollectiveError as exc:
        raise SweepError(str(exc)) from None


def _check_resumable(path: Path, config: Config, mesh_sha256: str, plan: SweepPlan) -> None:
    data = StrainDataset.open(path)
    if data.config.to_toml() != config.to_toml():
        raise ValueError(
            f"'{path}' was made with another configuration; resume it with the same --config or choose a new --out"
        )
    if data.mesh_sha256 != mesh_sha256:
        raise ValueError(f"'{path}' was made on another mesh (sha256 {data.mesh_sha256[:12]}...)")
    if not (np.array_equal(data.params, plan.params) and np.array_equal(data.split, plan.split)):
        raise ValueError(f"'{path}' has other materials than this configuration's design")


def run_sweep(
    config: Config,
    out: Path | str,
    *,
    resume: bool = False,
    force: bool = False,
    retry_failed: bool = False,
    shard: tuple[int, int] = (0, 1),
    ranks_per_sim: int = 1,
    mesh_dir: Path | str = DEFAULT_MESH_DIR,
    comm: MPI.Comm = MPI.COMM_WORLD,
    progress: bool = True,
) -> SweepReport | None:
    """Run (the missing part of) a configuration's sweep into the dataset ``out``.

    Collective over ``comm``. World rank 0 holds the lock file ``<out>.lock`` while the sweep
    runs (removed when it ends, also on error). Returns the report on rank 0, ``None`` elsewhere.

    Args:
        resume: complete an existing ``out`` (of the same configuration and mesh).
        force: replace an existing ``out`` (when the new file is created, after the mesh and
            the model are ready).

    Raises:
        ValueError: ``out`` exists without ``resume`` or ``force``, belongs to another
            configuration or mesh, its folder cannot be written, another sweep holds its lock
            (or a stale lock is left), or ``comm.size`` is not a multiple of ``ranks_per_sim``;
            the checks of ``out`` run on rank 0 and fail on every rank (:class:`SweepError`).
    """
    out = Path(out)
    if ranks_per_sim < 1 or comm.size % ranks_per_sim:
        raise ValueError(f"--ranks-per-sim {ranks_per_sim} must divide the number of MPI ranks ({comm.size})")

    def check_name() -> None:
        if out.suffix not in (".h5", ".hdf5"):
            raise ValueError(f"--out must end in .h5, got '{out}'")
        check_writable(out)

    _on_root(comm, check_name)
    _on_root(comm, lambda: take_lock(out))
    try:
        _on_root(comm, lambda: check_output(out, force, resume=resume))
        return _sweep(
            config,
            out,
            force=force,
            retry_failed=retry_failed,
            shard=shard,
            ranks_per_sim=ranks_per_sim,
            mesh_dir=mesh_dir,
            comm=comm,
            progress=progress,
        )
    finally:
        if comm.rank == 0:
            release_lock(out)


@dataclass(frozen=True)
class SimulationResult:
    """One finished simulation of a sweep, as its group root hands it to the writer (rank 0).

    Attributes:
        i, j: material and design index.
        strain: (n_frames, n_cells, 3) log strain, None if it failed.
        status: ``STATUS_OK`` or ``STATUS_FAILED`` (:mod:`skinfem.io`).
        message: why it failed ("" if not).
        iterations: Newton iterations of all increments.
        seconds: wall time of the simulation [s].
    """

    i: int
    j: int
    strain: np.ndarray | None
    status: int
    message: str = ""
    iterations: int = 0
    seconds: float = 0.0

    def write_to(self, out: Path) -> None:
        """Record it in the dataset ``out``."""
        write_simulation(out, self.i, self.j, self.strain, self.status, self.message, self.iterations, self.seconds)

    def spool(self, folder: Path) -> None:
        """Leave it in ``folder`` as ``<i>_<j>.npz`` (written atomically) for the writer."""
        fields = {"strain": self.strain} if self.strain is not None else {}

        def write(tmp: Path) -> None:
            index = np.array([self.i, self.j, self.status, self.iterations])
            np.savez(tmp, index=index, seconds=self.seconds, message=self.message, **fields)

        write_atomically(folder / f"{self.i}_{self.j}.npz", write)

    @classmethod
    def unspool(cls, path: Path) -> SimulationResult:
        """The result :meth:`spool` left at ``path``."""
        with np.load(path) as f:
            i, j, status, iterations = (int(v) for v in f["index"])
            strain = f["strain"] if "strain" in f else None
            return cls(i, j, strain, status, str(f["message"]), iterations, float(f["seconds"]))


def _simulate(model, plan: SweepPlan, i: int, j: int) -> SimulationResult:
    """Material i at design j (collective over the model's group; the strain is on its root
    only); a Newton failure is a failed result, not an error."""
    from skinfem.model import ConvergenceError
    from skinfem.params import Design, SkinParams

    try:
        frames = model.simulate(SkinParams.from_array(plan.params[i]), Design(*plan.designs[j]))
    except ConvergenceError as exc:
        return SimulationResult(i, j, None, STATUS_FAILED, str(exc))
    iterations = sum(frames.newton_iterations)
    if frames.strain is not None and not np.all(np.isfinite(frames.strain)):  # None off the group root
        return SimulationResult(i, j, None, STATUS_FAILED, "non-finite strain", iterations, frames.seconds)
    return SimulationResult(i, j, frames.strain, STATUS_OK, "", iterations, frames.seconds)


def spool_folder(out: Path) -> Path:
    """Where the group roots other than world rank 0 leave finished simulations for ``out``."""
    return out.with_name(out.name + ".spool")


def _record_spooled(out: Path, record: Callable[[SimulationResult], None]) -> None:
    """Pass each result waiting in ``out``'s spool to ``record``, removing its file afterwards
    (the hidden files of a write in progress are not results yet)."""
    for path in sorted(spool_folder(out).glob("[0-9]*_[0-9]*.npz")):
        record(SimulationResult.unspool(path))
        path.unlink()


class _Writer:
    """World rank 0's side of a sweep: writes its own group's results to ``out`` and those the
    other group roots leave in the spool, with an optional progress bar."""

    def __init__(self, out: Path, expected: int, progress: bool):
        self.out = out
        self.results: list[SimulationResult] = []
        self.bar = None
        if progress:
            from tqdm import tqdm

            self.bar = tqdm(total=expected, desc=f"sweep {out.name}", unit="sim", file=sys.stderr)

    def record(self, r: SimulationResult) -> None:
        r.write_to(self.out)
        self.results.append(r)
        if self.bar is not None:
            self.bar.update()
            if r.status == STATUS_FAILED:
                self.bar.set_postfix(failed=sum(q.status == STATUS_FAILED for q in self.results))

    def collect(self) -> None:
        """Record the spooled results, each file removed once it is in ``out``."""
        _record_spooled(self.out, self.record)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _sweep(
    config: Config,
    out: Path,
    *,
    force: bool,
    retry_failed: bool,
    shard: tuple[int, int],
    ranks_per_sim: int,
    mesh_dir: Path | str,
    comm: MPI.Comm,
    progress: bool,
) -> SweepReport | None:
    """The sweep of :func:`run_sweep` once ``out`` is checked and locked."""
    from skinfem.model import SkinModel

    start = time.perf_counter()
    plan = SweepPlan.from_config(config)
    ensure_mesh(config, mesh_dir, comm)
    n_groups = comm.size // ranks_per_sim
    group_id = comm.rank // ranks_per_sim
    group = comm.Split(group_id, comm.rank)
    model = SkinModel(config, group, mesh_dir=mesh_dir)
    _on_root(comm, lambda: _prepare_file(out, config, model, plan, force))
    status = comm.bcast(StrainDataset.open(out).status if comm.rank == 0 else None)
    todo = pending_simulations(status, shard, retry_failed)
    writer = _Writer(out, len(todo), progress) if comm.rank == 0 else None
    for i, j in todo[group_id::n_groups]:
        result = _simulate(model, plan, i, j)
        if writer is not None:
            writer.record(result)
            writer.collect()
        elif group.rank == 0:
            result.spool(spool_folder(out))
    comm.barrier()
    if writer is None:
        return None
    writer.collect()
    writer.close()
    remove_output(spool_folder(out))
    done = writer.results
    return SweepReport(
        path=out,
        n_run=len(done),
        n_failed=sum(r.status == STATUS_FAILED for r in done),
        n_total=status.size,
        n_done_before=int(np.count_nonzero(status)),
        wall_seconds=time.perf_counter() - start,
        sim_seconds=[r.seconds for r in done if r.status == STATUS_OK],
    )


def _prepare_file(out: Path, config: Config, model, plan: SweepPlan, force: bool) -> None:
    """Check an existing ``out`` for resuming and record what its killed sweep left in the spool,
    or create the empty dataset (atomically) with an empty spool."""
    if out.exists() and not force:
        _check_resumable(out, config, model.mesh_sha256, plan)
        _record_spooled(out, lambda r: r.write_to(out))
        return
    remove_output(spool_folder(out))
    sampler = model.strain_sampler
    write_atomically(
        out,
        lambda tmp: create_dataset(
            tmp,
            config,
            plan.params,
            plan.designs,
            model.load_fractions(),
            sampler.xy,
            sampler.volume,
            plan.split,
            model.mesh_sha256,
            bounds=plan.bounds,
        ),
    )


def merge_datasets(paths: list[Path | str], out: Path | str) -> StrainDataset:
    """Join shard files of one sweep into ``out`` (written atomically).

    Raises:
        ValueError: the shards differ in configuration, mesh, added noise, materials, designs, frames or
            cells, or two shards both ran the same simulation with different results.
    """
    if not paths:
        raise ValueError("nothing to merge")
    shards = [StrainDataset.open(p) for p in paths]
    first = shards[0]
    for other in shards[1:]:
        for what, a, b in (
            ("configuration", first.config.to_toml(), other.config.to_toml()),
            ("mesh", first.mesh_sha256, other.mesh_sha256),
            ("added noise", first.added_noise, other.added_noise),
        ):
            if a != b:
                raise ValueError(f"cannot merge: '{other.path}' has another {what} than '{first.path}'")
        for what in ("params", "designs", "t", "xy", "split"):
            if not np.array_equal(getattr(first, what), getattr(other, what)):
                raise ValueError(f"cannot merge: '{other.path}' has other {what} than '{first.path}'")

    owner = np.full(first.status.shape, -1)
    for k, shard in enumerate(shards):
        for i, j in zip(*np.nonzero(shard.status)):
            if owner[i, j] >= 0:
                previous = shards[owner[i, j]]
                same = previous.status[i, j] == shard.status[i, j] and np.array_equal(
                    previous.strain(i, j), shard.strain(i, j), equal_nan=True
                )
                if not same:
                    raise ValueError(
                        f"cannot merge: simulation ({i}, {j}) differs between '{previous.path}' and '{shard.path}'"
                    )
                continue
            owner[i, j] = k

    def write(tmp: Path) -> None:
        create_dataset_like(tmp, first)
        for i, j in zip(*np.nonzero(owner >= 0)):
            shard = shards[owner[i, j]]
            write_simulation(
                tmp,
                i,
                j,
                shard.strain(i, j),
                int(shard.status[i, j]),
                shard.messages[i, j],
                int(shard.newton_iterations[i, j]),
                float(shard.seconds[i, j]),
            )

    write_atomically(out, write)
    return StrainDataset.open(out)
