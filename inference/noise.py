"""Spatially correlated measurement noise on the skin cells (the paper's noise study).

Noise fields are zero-mean Gaussian processes on the skin-cell centroids with an RBF kernel

    cov(x_i, x_j) = a_c^2 [(1 - w) exp(-|x_i - x_j|^2 / (2 l^2)) + w delta_ij],

length scale l [mm], uncorrelated share w (the "nugget"; 0 in the paper's study) and
amplitude a_c = level x max |strain_c| over the training materials of the clean dataset, per
component c. One Cholesky factor of the correlation matrix
(O(n_cells^3) once, ~1 s for the 4,624 cells of the paper mesh) serves every field; each
field then costs one (n_cells x n_cells) triangular product, so all fields of a dataset are
drawn in one matrix product per material.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.distance import cdist

from skinfem.io import AddedNoise, StrainDataset, copy_simulations, create_dataset_like
from skinfem.outputs import write_atomically


def correlation_matrix(xy: np.ndarray, length: float, nugget: float = 0.0) -> np.ndarray:
    """(n, n) correlation of noise at points xy (n, 2) [mm]: (1 - nugget) RBF(length) + nugget I.

    ``length = 0`` means independent cells (the identity); ``nugget`` in [0, 1] is the share of
    the variance that is uncorrelated (pixel noise on top of the subset-correlated DIC error).
    """
    if length < 0:
        raise ValueError(f"noise length scale must be >= 0 mm, got {length}")
    if not 0 <= nugget <= 1:
        raise ValueError(f"noise nugget must be in [0, 1], got {nugget}")
    if length == 0:
        return np.eye(len(xy))
    corr = (1 - nugget) * np.exp(-cdist(xy, xy, "sqeuclidean") / (2 * length**2))
    corr[np.diag_indices_from(corr)] += nugget
    return corr


def correlation_factor(xy: np.ndarray, length: float, jitter: float = 1e-8) -> np.ndarray:
    """Lower Cholesky factor (n, n) of the RBF correlation matrix of points xy (n, 2) [mm]."""
    if length <= 0:
        raise ValueError(f"noise length scale must be > 0 mm, got {length}")
    corr = correlation_matrix(xy, length)
    corr[np.diag_indices_from(corr)] += jitter
    return np.linalg.cholesky(corr)


def noise_amplitude(data: StrainDataset, level: float) -> np.ndarray:
    """(3,) amplitude per component: level x max |strain| of the training materials."""
    if not 0 <= level < 1:
        raise ValueError(f"noise level must be a fraction in [0, 1), got {level}")
    peak = np.zeros(3)
    for i in np.flatnonzero(data.split == 0):
        block = data.strain(int(i))
        if np.isfinite(block).any():
            peak = np.maximum(peak, np.nanmax(np.abs(block), axis=(0, 1, 2)))
    return level * peak


def noise_fields(factor: np.ndarray, amplitude: np.ndarray, shape: tuple[int, ...], rng) -> np.ndarray:
    """Noise of shape (*shape, n_cells, 3): independent fields per leading index and component.

    ``factor`` is any square root L (L L^T = correlation) of the cells' correlation matrix.
    """
    n = len(factor)
    white = rng.standard_normal((*shape, 3, n))
    correlated = white @ factor.T  # (..., 3, n): each row is L @ z
    return np.swapaxes(correlated, -1, -2) * amplitude


def check_clean(data: StrainDataset) -> None:
    """ValueError if ``data`` already carries added noise: a second noise would go unrecorded."""
    if data.added_noise is not None:
        raise ValueError(f"'{data.path}' already carries added noise: add noise to the clean dataset")


def add_noise(data: StrainDataset, out: Path | str, length: float, level: float, seed: int = 0) -> Path:
    """Write a copy of ``data`` with correlated noise added to every converged frame.

    Raises:
        ValueError: ``data`` already carries added noise (the copy could not say which it holds).
    """
    check_clean(data)
    amplitude = noise_amplitude(data, level)
    factor = correlation_factor(data.xy, length)
    rng = np.random.default_rng(seed)
    _, n_des, n_frames, _ = data.shape

    def write(tmp: Path) -> None:
        import h5py

        create_dataset_like(tmp, data)
        with h5py.File(tmp, "a") as f:
            added = AddedNoise(length, level, tuple(amplitude.tolist()))
            f.attrs["noise"] = json.dumps(added.to_json() | {"seed": seed, "source": str(data.path)})
        copy_simulations(data, tmp, lambda i: data.strain(i) + noise_fields(factor, amplitude, (n_des, n_frames), rng))

    return write_atomically(out, write)
