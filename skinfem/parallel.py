"""Errors under MPI: one clear line and every rank ends, never a hang.

Two paths, used by every command that runs on several ranks:

- **Agreed errors** (:func:`collective`, :func:`on_root`): work that may fail on some ranks
  only is run inside a call that gathers the outcome of every rank; if any rank failed, every
  rank raises the same :class:`CollectiveError` (the message of the lowest failing rank), so
  the command can print it once (rank 0) and exit normally on all ranks.
- **Anything else** (:func:`abort_on_uncaught`): an exception that escapes on one rank prints
  one line and calls ``MPI_Abort``, which ends every rank of the job at once.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

from mpi4py import MPI


class CollectiveError(RuntimeError):
    """Raised on every rank when the work of a collective call failed on at least one rank."""


def _message(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__


def collective[T](comm: MPI.Comm, work: Callable[[], T], expected: tuple[type[BaseException], ...] = (Exception,)) -> T:
    """Run ``work()`` on every rank; if it raised ``expected`` on any rank, raise on all.

    The raised :class:`CollectiveError` carries the message of the lowest failing rank
    (prefixed with the rank when the communicator has several).
    """
    result, error = None, None
    try:
        result = work()
    except expected as exc:  # reported to every rank below
        error = _message(exc)
    errors = comm.allgather(error)
    for rank, message in enumerate(errors):
        if message is not None:
            prefix = f"rank {rank}: " if comm.size > 1 else ""
            raise CollectiveError(prefix + message)
    return result


def on_root[T](comm: MPI.Comm, work: Callable[[], T]) -> T:
    """Run ``work()`` on rank 0 and broadcast its result, or its error as CollectiveError."""
    result, error = None, None
    if comm.rank == 0:
        try:
            result = work()
        except Exception as exc:  # reported to every rank below
            error = _message(exc)
    result, error = comm.bcast((result, error))
    if error is not None:
        raise CollectiveError(error)
    return result


def abort_on_uncaught(prog: str, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """On several ranks, an uncaught exception prints one line and aborts the whole job."""
    if comm.size == 1:
        return

    def hook(kind, exc, tb):
        print(
            f"{prog}: error on rank {comm.rank}: {_message(exc)} ({kind.__name__}); aborting all ranks",
            file=sys.stderr,
            flush=True,
        )
        comm.Abort(1)

    sys.excepthook = hook
