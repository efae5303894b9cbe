"""Outputs of the ``skinid`` commands: never replaced silently, never half-written, one writer.

Every command that writes a file or a directory

- checks it before any computing (:func:`check_output`): an existing output is refused unless
  ``--force`` is given (or, for the resumable outputs of ``sweep``, ``study`` and ``check``,
  ``--resume``), and so is one whose folder cannot be written;
- writes it under a temporary name and renames it when complete (:func:`write_atomically`,
  :func:`write_text`, :func:`save_figure`);
- ``sweep`` also holds a lock file next to its output while it runs (:func:`take_lock`), so
  that a second sweep to the same file is refused instead of writing into it.

The refusals are ``ValueError`` with a one-line message; the commands print it and exit with 2.
"""

from __future__ import annotations

import os
import shutil
import socket
from pathlib import Path


def check_writable(path: Path | str) -> Path:
    """Refuse an output whose nearest existing folder is a file or cannot be written."""
    path = Path(path)
    folder = next(p for p in (path.parent, *path.parent.parents) if p.exists())
    if not folder.is_dir():
        raise ValueError(f"cannot write '{path}': '{folder}' is a file, not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write '{path}': '{folder}' is not writable")
    return path


def check_output(path: Path | str, force: bool = False, *, directory: bool = False, resume: bool | None = None) -> Path:
    """Refuse an output before any computing: it exists (without ``force``), is of the other kind
    (a folder for a file or a file for a folder), or its folder cannot be written.

    Args:
        directory: the output is a folder (else a file).
        resume: ``None`` for outputs that cannot be resumed; else whether ``--resume`` was
            given (an existing resumable output is accepted with it, and the refusal names it).

    Raises:
        ValueError: with one line saying which and what to do (also: both ``force`` and ``resume``).
    """
    path = Path(path)
    if force and resume:
        raise ValueError("--resume completes an existing output and --force replaces it: give one of them")
    if path.exists() and path.is_dir() != directory:
        kind = "folder" if path.is_dir() else "file"
        raise ValueError(f"'{path}' is a {kind}; give a {'folder' if directory else 'file'} name")
    if path.exists() and not (force or resume):
        hint = "" if resume is None else " or --resume to complete it"
        raise ValueError(f"{path} exists; pass --force to replace it{hint}")
    return check_writable(path)


def remove_output(path: Path | str) -> None:
    """Delete a file or folder if it exists (an output that ``--force`` replaces in place)."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def write_atomically(path: Path | str, write) -> Path:
    """Call ``write(tmp)`` and move the result to ``path`` only if it succeeded.

    ``tmp`` is a hidden sibling of ``path`` with the same suffix (writers that choose the format
    by the name write the right one). ``write`` may make a file or a folder; a folder already at
    ``path`` is replaced whole: moved aside, and deleted once the new one is in place.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    old = path.with_name(f".{path.name}.{os.getpid()}.old")
    try:
        write(tmp)
        _move_into_place(tmp, path, old)
    finally:
        remove_output(tmp)
        remove_output(old)
    return path


def _move_into_place(new: Path, path: Path, old: Path) -> None:
    """Rename ``new`` to ``path``; a folder at ``path`` is first renamed to ``old`` (and put back
    if the rename fails)."""
    if not (path.is_dir() and not path.is_symlink()):
        new.replace(path)
        return
    path.rename(old)
    try:
        new.rename(path)
    except OSError:
        old.rename(path)
        raise


def write_text(path: Path | str, text: str) -> Path:
    """Write a text file (UTF-8) under a temporary name and rename it."""
    return write_atomically(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def save_figure(fig, path: Path | str, dpi: int = 110) -> Path:
    """Lay out a matplotlib figure, write it under a temporary name and rename it, close it.

    The format is the one of ``path``'s suffix (PNG without one), whatever the temporary name.
    """
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        fig.tight_layout()
        write_atomically(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format=path.suffix[1:] or "png"))
    finally:
        plt.close(fig)
    return path


# ---------------------------------------------------------------- lock


def lock_path(path: Path | str) -> Path:
    """The lock file of an output: ``<output>.lock`` next to it."""
    path = Path(path)
    return path.with_name(f"{path.name}.lock")


def _running(pid: int) -> bool:
    """Whether a process with this id runs on this machine."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it runs, under another user
        pass
    return True


def _locked(path: Path, lock: Path) -> ValueError:
    """The refusal of a locked output: by whom, or that the lock is stale and how to remove it."""
    words = lock.read_text(errors="replace").split() if lock.exists() else []
    pid = int(words[0]) if words and words[0].isdigit() else None
    host = words[1] if len(words) > 1 else socket.gethostname()
    if pid is not None and (host != socket.gethostname() or _running(pid)):
        return ValueError(f"{path} is being written by another sweep (PID {pid} on {host}; lock {lock})")
    holder = "it names no process" if pid is None else f"PID {pid} is not running"
    return ValueError(f"stale lock {lock} ({holder}); if no sweep writes {path}, remove it: rm '{lock}'")


def take_lock(path: Path | str) -> Path:
    """Create ``<path>.lock`` (exclusively) holding this process's id and host; returns it.

    Raises:
        ValueError: the lock exists: another sweep runs (its PID and host), or the lock is
            stale (its process is not running on this host; the message gives the ``rm``).
    """
    path = Path(path)
    lock = lock_path(path)
    lock.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        raise _locked(path, lock) from None
    with os.fdopen(fd, "w") as f:
        f.write(f"{os.getpid()} {socket.gethostname()}\n")
    return lock


def release_lock(path: Path | str) -> None:
    """Remove the lock :func:`take_lock` created for ``path``."""
    lock_path(path).unlink(missing_ok=True)
