"""Checks of the inference commands' inputs: paths that must exist, index lists, designs named by index or by their
eigen-strains, sampler options, the emulator's mesh, a measurement's strain scale. Each refuses
bad input with one ValueError line."""

from __future__ import annotations

from pathlib import Path

import numpy as np

INPUT_PATHS = {"emulator": "emulator directory", "data": "dataset", "measurement": "measurement file"}


def check_input_paths(args) -> None:
    """Refuse an input path (``--emulator``, ``--data``, ``--measurement``) that does not exist
    before a command imports torch and Pyro (about 5 s)."""
    for option, what in INPUT_PATHS.items():
        value = getattr(args, option, None)
        for path in value if isinstance(value, list) else [value]:
            if path is not None and not path.exists():
                raise FileNotFoundError(f"{what} '{path}' does not exist")


def int_list(text: str | None, option: str) -> list[int] | None:
    """The indices of a list option such as ``--designs '0,2,4'`` (None if not given)."""
    if text is None:
        return None
    try:
        return [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise ValueError(f"{option} must be integers such as '2' or '0,2,4', got '{text}'") from None


def design_indices(text: str | None, designs: np.ndarray, path: Path, option: str = "--designs") -> list[int] | None:
    """Designs of a dataset named by index (``'7'``, ``'7,6,13'``) or by eigen-strain pairs
    (``'0.05,-0.05'`` or ``'0.05,-0.05,-0.05,0.05'``; a list holding a non-integer is read as
    (alpha11, alpha22) pairs [-], each matched by :func:`skinfem.io.design_index`).

    Args:
        designs: (n_des, 2) the dataset's eigen-strains.
    Returns:
        Design indices (None if ``text`` is None); indices given as such are not range-checked here.
    """
    from skinfem.io import design_index

    if text is None:
        return None
    try:
        return int_list(text, option)
    except ValueError:
        pass
    try:
        values = np.array([float(v) for v in text.replace(",", " ").split()])
    except ValueError:
        raise ValueError(
            f"{option} takes design indices ('2', '0,2,4') or eigen-strain pairs ('0.05,-0.05'), got '{text}'"
        ) from None
    if len(values) == 0 or len(values) % 2:
        raise ValueError(f"{option} {text}: eigen-strains come in pairs alpha11,alpha22 (e.g. 0.05,-0.05)")
    try:
        return [design_index(designs, pair, path) for pair in values.reshape(-1, 2)]
    except ValueError as exc:
        raise ValueError(f"{option}: {exc}") from None


def one_design(text: str, designs: np.ndarray, path: Path) -> int:
    """The single design of ``--designs`` (index or one eigen-strain pair)."""
    indices = design_indices(text, designs, path)
    if len(indices) != 1:
        raise ValueError(f"--designs names one design here (an index or alpha11,alpha22), got '{text}'")
    return indices[0]


def check_indices(option: str, values: list[int] | None, size: int, path: Path, negative: bool = True) -> None:
    """Refuse indices outside a dataset's ``size`` entries (negative ones count from the end if allowed)."""
    for v in values or []:
        if not (-size if negative else 0) <= v < size:
            raise ValueError(f"{option} {v} is not in [0, {size}) of {path}")


def check_sampler(args) -> None:
    """Refuse sampler options that cannot give a posterior (before any input is read)."""
    for option, value, least in (
        ("--chains", args.chains, 1),
        ("--draws", args.draws, 1),
        ("--warmup", args.warmup, 0),
        ("--jobs", args.jobs, 1),
    ):
        if value < least:
            raise ValueError(f"{option} must be >= {least}, got {value}")


def check_same_mesh(data, emulator) -> None:
    """Refuse a dataset simulated on another mesh than the emulator's training data (the PC basis
    belongs to that mesh's cells, even when the cell count is the same)."""
    if data.mesh_sha256 != emulator.provenance.mesh_sha256 or data.xy.shape != emulator.xy.shape:
        raise ValueError(
            f"'{data.path}' was simulated on another mesh than the emulator's dataset "
            f"'{emulator.provenance.dataset}' (mesh sha256 {data.mesh_sha256[:12]}... vs "
            f"{emulator.provenance.mesh_sha256[:12]}...)"
        )


def check_strain_scale(m, membrane_half: float) -> None:
    """Refuse a measurement whose strains are far larger than its design imposes: strains in percent."""
    from inference.dic_import import RATIO_RANGE, assess_plausibility
    from inference.observations import MeasurementError

    ratio = assess_plausibility(m.xy, m.strain, m.alpha, m.t, membrane_half).ratio
    if ratio > RATIO_RANGE[1]:
        raise MeasurementError(
            f"{m.path}: the mean strain under the membrane is {ratio:.3g}x the design's "
            "ln(1 + t·alpha): strains in percent? a measurement file holds fractions"
        )
