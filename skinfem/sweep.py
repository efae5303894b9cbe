"""Simulation sweeps: a Latin hypercube over the skin parameters x the membrane designs.

A sweep runs every (material, design) pair of a configuration and records the frames in one
dataset file (:mod:`skinfem.io`), simulation by simulation, so that a killed sweep loses no
finished simulation and ``resume=True`` runs only what is missing.

Parallel layout: ``MPI.COMM_WORLD`` is split into groups of ``ranks_per_sim`` ranks; each
group owns one :class:`~skinfem.model.SkinModel` and runs every G-th missing simulation
(static interleaving: simulations cost about the same, and no rank is lost to a dispatcher).
World rank 0 is the only writer: it records its own group's results and the ones the other
group roots send it. ``shard=(i, n)`` restricts the sweep to the simulations whose flat index
``i_mat * n_des + i_des`` is ``i`` modulo ``n`` (a Slurm job array); :func:`merge_datasets`
joins the shard files.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI
from scipy.stats import qmc

from skinfem.config import PARAM_NAMES, Config
from skinfem.io import (
    STATUS_FAILED,
    STATUS_NOT_RUN,
    STATUS_OK,
    StrainDataset,
    create_dataset,
    create_dataset_like,
    write_atomically,
    write_simulation,
)
from skinfem.mesh import DEFAULT_MESH_DIR, ensure_mesh

_RESULT_TAG = 71


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
        bounds = np.array([sweep.bounds[name] for name in PARAM_NAMES], dtype=float)
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


def _collective(comm: MPI.Comm, check) -> None:
    """Run ``check()`` on rank 0 and raise its ValueError on every rank."""
    message = None
    if comm.rank == 0:
        try:
            check()
        except (ValueError, FileNotFoundError) as exc:
            message = str(exc)
    message = comm.bcast(message)
    if message is not None:
        raise ValueError(message)


def _check_resumable(path: Path, config: Config, mesh_sha256: str, plan: SweepPlan) -> None:
    data = StrainDataset.open(path)
    if data.config.to_toml() != config.to_toml():
        raise ValueError(
            f"'{path}' was made with another configuration; resume it with the same --config "
            "or choose a new --out"
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
    retry_failed: bool = False,
    shard: tuple[int, int] = (0, 1),
    ranks_per_sim: int = 1,
    mesh_dir: Path | str = DEFAULT_MESH_DIR,
    comm: MPI.Comm = MPI.COMM_WORLD,
    progress: bool = True,
) -> SweepReport | None:
    """Run (the missing part of) a configuration's sweep into the dataset ``out``.

    Collective over ``comm``. Returns the report on rank 0, ``None`` elsewhere.

    Raises:
        ValueError: ``out`` exists without ``resume``, belongs to another configuration or
            mesh, or ``comm.size`` is not a multiple of ``ranks_per_sim``.
    """
    from skinfem.model import ConvergenceError, SkinModel
    from skinfem.params import Design, SkinParams

    start = time.perf_counter()
    out = Path(out)
    plan = SweepPlan.from_config(config)
    if ranks_per_sim < 1 or comm.size % ranks_per_sim:
        raise ValueError(
            f"--ranks-per-sim {ranks_per_sim} must divide the number of MPI ranks ({comm.size})"
        )

    def check_out() -> None:
        if out.suffix not in (".h5", ".hdf5"):
            raise ValueError(f"--out must end in .h5, got '{out}'")
        if out.exists() and not resume:
            raise ValueError(f"'{out}' exists; add --resume to complete it or choose a new --out")

    _collective(comm, check_out)
    ensure_mesh(config, mesh_dir, comm)
    n_groups = comm.size // ranks_per_sim
    group_id = comm.rank // ranks_per_sim
    group = comm.Split(group_id, comm.rank)
    model = SkinModel(config, group, mesh_dir=mesh_dir)

    def prepare_file() -> None:
        if out.exists():
            _check_resumable(out, config, model.mesh_sha256, plan)
            return
        sampler = model.strain_sampler

        def create(tmp: Path) -> None:
            create_dataset(
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
            )

        write_atomically(out, create)

    _collective(comm, prepare_file)
    status = comm.bcast(StrainDataset.open(out).status if comm.rank == 0 else None)
    todo = pending_simulations(status, shard, retry_failed)
    mine = todo[group_id::n_groups]

    bar = None
    if comm.rank == 0 and progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), desc=f"sweep {out.name}", unit="sim", file=sys.stderr)
    results: list[tuple[int, int, int, float]] = []  # rank 0: (i, j, status, seconds) written
    requests: list[MPI.Request] = []

    def record(result: tuple) -> None:
        i, j, strain, st, message, its, seconds = result
        if st == STATUS_OK and not np.all(np.isfinite(strain)):
            strain, st, message = None, STATUS_FAILED, "non-finite strain"
        write_simulation(out, i, j, strain, st, message, its, seconds)
        results.append((i, j, st, seconds))
        if bar is not None:
            bar.update()
            if st == STATUS_FAILED:
                bar.set_postfix(failed=sum(r[2] == STATUS_FAILED for r in results))

    def receive(wait_for_all: bool) -> None:
        while len(results) < len(todo) and (
            wait_for_all or comm.iprobe(source=MPI.ANY_SOURCE, tag=_RESULT_TAG)
        ):
            record(comm.recv(source=MPI.ANY_SOURCE, tag=_RESULT_TAG))

    for i, j in mine:
        try:
            frames = model.simulate(SkinParams.from_array(plan.params[i]), Design(*plan.designs[j]))
            its = sum(frames.newton_iterations)
            result = (i, j, frames.strain, STATUS_OK, "", its, frames.seconds)
        except ConvergenceError as exc:
            result = (i, j, None, STATUS_FAILED, str(exc), 0, 0.0)
        if group.rank != 0:
            continue
        if comm.rank == 0:
            record(result)
            receive(wait_for_all=False)
        else:
            requests.append(comm.isend(result, dest=0, tag=_RESULT_TAG))
    if comm.rank == 0:
        receive(wait_for_all=True)
    MPI.Request.waitall(requests)
    comm.barrier()
    if bar is not None:
        bar.close()
    if comm.rank != 0:
        return None
    return SweepReport(
        path=out,
        n_run=len(results),
        n_failed=sum(r[2] == STATUS_FAILED for r in results),
        n_total=status.size,
        n_done_before=int(np.count_nonzero(status)),
        wall_seconds=time.perf_counter() - start,
        sim_seconds=[r[3] for r in results if r[2] == STATUS_OK],
    )


def merge_datasets(paths: list[Path | str], out: Path | str) -> StrainDataset:
    """Join shard files of one sweep into ``out`` (written atomically).

    Raises:
        ValueError: the shards differ in configuration, mesh, materials, designs, frames or
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
                        f"cannot merge: simulation ({i}, {j}) differs between "
                        f"'{previous.path}' and '{shard.path}'"
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
