"""The linear-algebra work of FE runs, counted by PETSc's event log.

A phase of a long computation (e.g. a check's calibration) is costed in Newton steps (tangent
assemblies), LU factorisations and triangular solves (one per GMRES iteration preconditioned by
a kept factorisation, and one per sensitivity back-solve): on the paper mesh a factorisation
costs about 40 triangular solves and a tangent assembly about 5 (docs/performance.md).
:func:`solver_work` reads the counts so far; the work of a phase is the difference of two
readings (:class:`WorkMeter`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from mpi4py import MPI

from skinfem.fenics import PETSc

EVENTS = {"newton_steps": "SNESJacobianEval", "factorisations": "MatLUFactorNum", "triangular_solves": "MatSolve"}


@dataclass(frozen=True)
class SolverWork:
    """Counts of linear-algebra operations, summed over the ranks (each rank runs its own
    simulations)."""

    newton_steps: int = 0
    factorisations: int = 0
    triangular_solves: int = 0

    def __sub__(self, other: SolverWork) -> SolverWork:
        return SolverWork(*(getattr(self, f.name) - getattr(other, f.name) for f in fields(self)))


def start_counting() -> None:
    """Switch PETSc's event log on (idempotent; the counts start when it is first on)."""
    if not PETSc.Log.isActive():
        PETSc.Log.begin()


def event_count(event: str) -> int:
    """How often PETSc's event ``event`` (e.g. "MatLUFactorSym") ran in this process since
    :func:`start_counting`."""
    return PETSc.Log.Event(event).getPerfInfo()["count"]


def solver_work(comm: MPI.Comm) -> SolverWork:
    """The counts since :func:`start_counting`, summed over ``comm`` (collective)."""
    local = np.array([event_count(event) for event in EVENTS.values()], np.int64)
    return SolverWork(**{name: int(n) for name, n in zip(EVENTS, comm.allreduce(local, op=MPI.SUM))})


class WorkMeter:
    """Work per phase: :meth:`lap` returns the work since the previous lap (or the meter's
    creation). Switches the event log on; collective, like :func:`solver_work`."""

    def __init__(self, comm: MPI.Comm):
        start_counting()
        self.comm, self.last = comm, solver_work(comm)

    def lap(self) -> SolverWork:
        now = solver_work(self.comm)
        done, self.last = now - self.last, now
        return done
