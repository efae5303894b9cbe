"""Memory of the LU factors: one clear line when a mesh's factors do not fit, not a killed job.

A mesh whose LU factors need more memory than the machine has used to end in the system's
out-of-memory kill (under ``mpirun``: "signal 9", no word of ours). Each rank now gives MUMPS
the most working memory it may use (ICNTL(23), in MB): its share of the memory available on
this machine when it first asks, divided among the ranks on the machine, less what the process
already holds. When the analysis of a matrix needs more, MUMPS stops before allocating
(INFOG(1) = -19) and :func:`raise_if_out_of_memory` raises :class:`FactorMemoryError` with the
memory it needed (INFOG(16), MB) and the share it had. MUMPS may reserve address space
towards the limit but touches only what it uses: a run that fits keeps its resident memory,
fields and time (``benchmarks/results/memory_limit.json``).

The share is read from ``/proc/meminfo`` (Linux); where it cannot be read no limit is set.
Ranks on this machine are counted from the launcher's environment (MPICH/Hydra:
``MPI_LOCALNRANKS``; Open MPI: ``OMPI_COMM_WORLD_LOCAL_SIZE``; otherwise 1). The environment
variable ``SKINID_RANK_MEMORY_MB`` sets the share instead (e.g. under a batch system whose
memory limit ``/proc/meminfo`` does not show).
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

from skinfem.fenics import PETSc

MEMORY_LIMIT_ICNTL = 23  # MUMPS: most working memory per process [MB]
NEEDED_INFOG = 16  # MUMPS: estimated memory of the factorisation, largest process [MB]
OUT_OF_MEMORY = {
    -9: "its working array was too small",
    -13: "an allocation failed",
    -19: "the analysis needs more than the limit",
}  # INFOG(1) codes of MUMPS
LOCAL_RANKS_VARIABLES = ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE")
SHARE_VARIABLE = "SKINID_RANK_MEMORY_MB"


class FactorMemoryError(RuntimeError):
    """The LU factorisation of a tangent does not fit in this rank's share of the memory."""


def _meminfo_mb(key: str) -> int | None:
    try:
        lines = Path("/proc/meminfo").read_text().splitlines()
    except OSError:
        return None
    values = {line.split(":")[0]: line.split()[1] for line in lines if ":" in line}
    return int(values[key]) // 1024 if key in values else None  # kB -> MB


def local_ranks() -> int:
    """Ranks of this job on this machine, from the MPI launcher's environment (1 if unknown)."""
    for name in LOCAL_RANKS_VARIABLES:
        if os.environ.get(name, "").isdigit():
            return max(int(os.environ[name]), 1)
    return 1


@functools.cache
def rank_share_mb() -> int | None:
    """This rank's share [MB] of the memory available on this machine when first asked
    (``MemAvailable`` / :func:`local_ranks`, or ``SKINID_RANK_MEMORY_MB``); None where it
    cannot be read."""
    value = os.environ.get(SHARE_VARIABLE, "")
    if value:
        if not value.isdigit() or int(value) == 0:
            raise ValueError(f"{SHARE_VARIABLE} must be a positive whole number of MB, got '{value}'")
        return int(value)
    available = _meminfo_mb("MemAvailable")
    return None if available is None else available // local_ranks()


def resident_mb() -> int:
    """Memory this process holds now [MB] (0 where /proc is not readable)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except OSError:
        return 0
    return pages * os.sysconf("SC_PAGE_SIZE") // 2**20


def factor_memory_limit_mb() -> int | None:
    """MUMPS's working-memory limit for a factorisation made now [MB]: this rank's share less
    what the process already holds (at least 1), or None (no limit) where the share is unknown."""
    share = rank_share_mb()
    return None if share is None else max(share - resident_mb(), 1)


def limit_factor_memory(pc: PETSc.PC) -> None:
    """Set the limit on the MUMPS factor of ``pc`` (a PC of type lu whose operators are set)."""
    limit = factor_memory_limit_mb()
    if limit is not None:
        pc.setFactorSetUpSolverType()
        pc.getFactorMatrix().setMumpsIcntl(MEMORY_LIMIT_ICNTL, limit)


def raise_if_out_of_memory(pc: PETSc.PC) -> None:
    """After a failed solve: raise :class:`FactorMemoryError` if MUMPS ran out of memory."""
    if pc.getType() != "lu" or pc.getFactorSolverType() != "mumps":
        return
    factor = pc.getFactorMatrix()
    code = factor.getMumpsInfog(1)
    if code not in OUT_OF_MEMORY:
        return
    share = rank_share_mb()
    context = (
        ""
        if share is None
        else f", more than is left of this rank's share of the machine's memory ({_size(share)} for "
        f"{local_ranks()} rank(s) here, {_size(resident_mb())} held already)"
    )
    raise FactorMemoryError(
        f"the LU factors of this mesh need about {_size(factor.getMumpsInfog(NEEDED_INFOG))} on this "
        f"rank{context}; MUMPS stopped: {OUT_OF_MEMORY[code]}. Run fewer ranks on this machine, or "
        f"use a coarser mesh (or set {SHARE_VARIABLE})"
    )


def _size(mb: int) -> str:
    return f"{mb / 1024:.1f} GB" if mb >= 1024 else f"{mb} MB"
