"""The LU factors' memory limit: one clear line instead of the system's out-of-memory kill."""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

from skinfem import memory
from tests.cli_helpers import MPIRUN, skinid_command, skinid_env

SIMULATE = ["--mu", 0.001, "--k1", 0.015, "--k2", 10, "--kappa", 0.28, "--theta", 30, "--alpha", 0.05, -0.05]


def one_line_refusal(tmp_path, mesh_dir, ranks: int) -> str:
    out = tmp_path / "run.h5"
    command = skinid_command(
        "simulate", "--config", "small", "--mesh-dir", mesh_dir, *SIMULATE, "--out", out, ranks=ranks
    )
    env = {**skinid_env(), memory.SHARE_VARIABLE: "60"}  # MB: less than the process holds at start
    start = time.perf_counter()
    res = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert res.returncode == 2 and time.perf_counter() - start < 120, res.stderr[-2000:]
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr[-2000:]
    assert not out.exists()
    return lines[0]


def test_factors_over_the_share_stop_the_command_with_what_they_need(tmp_path, mesh_dir):
    line = one_line_refusal(tmp_path, mesh_dir, ranks=1)
    needed = float(line.split("need about ")[1].split(" MB")[0])
    assert 5 < needed < 500, line  # the small mesh's factors: tens of MB
    assert "(60 MB for 1 rank(s) here" in line and "the analysis needs more than the limit" in line


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="needs mpirun")
def test_factors_over_the_share_end_every_rank_at_once_with_one_line(tmp_path, mesh_dir):
    assert "(60 MB for 2 rank(s) here" in one_line_refusal(tmp_path, mesh_dir, ranks=2)


def test_the_limit_leaves_the_solution_unchanged(small_config, mesh_dir, monkeypatch):
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    def strain(limit_mb):
        monkeypatch.setattr(memory, "factor_memory_limit_mb", lambda: limit_mb)
        model = SkinModel(small_config, mesh_dir=mesh_dir)
        model.simulate(SkinParams(1e-3, 0.015, 10.0, 0.28, 30.0), Design(0.05, 0.05))
        model.release_factorisation()  # the next factor is a new one: limited as well
        frames = model.simulate(SkinParams(1e-3, 0.015, 10.0, 0.28, 30.0), Design(0.05, -0.05))
        limit = model.problem.solver.getKSP().getPC().getFactorMatrix().getMumpsIcntl(memory.MEMORY_LIMIT_ICNTL)
        return frames.strain, limit

    limited, limit = strain(4000)
    free, no_limit = strain(None)
    assert (limit, no_limit) == (4000, 0)  # MUMPS's default 0: no limit
    np.testing.assert_array_equal(limited, free)


def test_the_pseudo_time_solver_is_limited_too(monkeypatch):
    from skinfem.fenics import PETSc
    from skinfem.pseudo_time import _linear_solver, _solve

    n = 100_000
    matrix = PETSc.Mat().createAIJ([n, n], nnz=3, comm=PETSc.COMM_SELF)
    for i in range(n):
        columns = [j for j in (i - 1, i, i + 1) if 0 <= j < n]
        matrix.setValues(i, columns, [2.0 if j == i else -1.0 for j in columns])
    matrix.assemble()
    rhs, solution = matrix.createVecs()
    rhs.set(1.0)
    monkeypatch.setattr(memory, "factor_memory_limit_mb", lambda: 1)
    with pytest.raises(memory.FactorMemoryError, match="need about"):
        _solve(_linear_solver(matrix, 0, 1e-8, 0.0), matrix, rhs, solution, refactor=True)
    monkeypatch.setattr(memory, "factor_memory_limit_mb", lambda: 100)
    _solve(_linear_solver(matrix, 0, 1e-8, 0.0), matrix, rhs, solution, refactor=True)
    x = solution.getArray()
    i = np.arange(1, n + 1)
    np.testing.assert_allclose(x, i * (n + 1 - i) / 2, rtol=1e-6)  # -u'' = 1, u(0) = u(n+1) = 0


@pytest.mark.parametrize(
    "variables, ranks",
    [({"MPI_LOCALNRANKS": "4"}, 4), ({"OMPI_COMM_WORLD_LOCAL_SIZE": "3"}, 3), ({}, 1)],
    ids=["mpich", "open mpi", "no launcher"],
)
def test_ranks_on_this_machine_come_from_the_launcher(variables, ranks, monkeypatch):
    for name in memory.LOCAL_RANKS_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    for name, value in variables.items():
        monkeypatch.setenv(name, value)
    assert memory.local_ranks() == ranks


def test_a_check_whose_factors_do_not_fit_stops_with_one_line(tmp_path, mesh_dir):
    from inference.observations import write_measurement
    from tests.test_bad_inputs import grid, plausible_strain

    xy = grid()
    write_measurement(tmp_path / "m.csv", xy, plausible_strain(xy), (0.05, -0.05), 1.0, np.full((len(xy), 3), 1e-3))
    command = skinid_command(
        "check",
        "--config",
        "small",
        "--mesh-dir",
        mesh_dir,
        "--out",
        tmp_path / "out",
        "--measurement",
        tmp_path / "m.csv",
    )
    env = {**skinid_env(), memory.SHARE_VARIABLE: "60"}
    res = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    errors = [line for line in res.stderr.splitlines() if "error" in line]
    assert res.returncode == 2 and len(errors) == 1 and "LU factors of this mesh need about" in errors[0], res.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", ["12GB", "0", "-5"])
def test_a_share_that_is_not_a_number_of_mb_is_one_line(value, monkeypatch):
    monkeypatch.setenv(memory.SHARE_VARIABLE, value)
    memory.rank_share_mb.cache_clear()
    try:
        with pytest.raises(
            ValueError, match=f"SKINID_RANK_MEMORY_MB must be a positive whole number of MB, got '{value}'"
        ):
            memory.rank_share_mb()
    finally:
        memory.rank_share_mb.cache_clear()
