"""Principal components of strain fields, one strain component at a time.

Each field (one row: the n_cells values of E_xx, say) is centred with the training data's
mean per cell and, with ``scaling="cell"`` (the paper's), divided by its standard deviation per
cell; with ``scaling="none"`` it stays in strain units. It is then projected on the leading
principal directions. ``n_components`` is an int (fixed M) or a float in (0, 1): the smallest
M whose cumulative explained variance reaches it.

The scaling decides what noise does to the weights. Cells whose strain barely changes between
materials (under the membrane the surface strain is ln(1 + alpha) whatever the skin) get a tiny
sd, so per-cell scaling amplifies a measurement's noise there and the retained weights carry a
tenth of the field's information at 1 % noise on the paper mesh; unscaled, the same number of
PCs keeps nearly all of it, and white noise of sd sigma on every cell is white noise of sd sigma
on every weight (the components are orthonormal) -- the likelihood's noise model
(``benchmarks/information_loss.py``; docs/paper-comparison.md).
"""

from __future__ import annotations

import numpy as np


class StrainPCA:
    """PCA of standardised fields (scikit-learn style: ``fit``/``transform``/``inverse_transform``).

    Args:
        n_components: M (int) or the explained variance to reach (float in (0, 1)).
        scaling: "cell" (per-cell sd, the paper's) or "none" (strain units; ``scale_`` is 1).

    Fitted attributes:
        mean_, scale_: (n_cells,) per-cell centring and scaling [strain].
        components_: (M, n_cells) orthonormal principal directions (standardised units).
        explained_variance_ratio_: (min(n_rows, n_cells),) of every direction, descending;
            the first M belong to the retained components.
        n_components_: M.
        discarded_components_: (K, n_cells) the K <= 20 leading directions after the first M
            (empty for PCAs saved before they were kept).
        discarded_variance_: (K,) variance of the training fields along them [standardised
            units^2]; with ``discarded_components_`` it describes what the retained PCs cannot
            represent (see :func:`surrogate.error_model.truncation_variance`).
    """

    N_DISCARDED = 20

    SCALINGS = ("cell", "none")

    def __init__(self, n_components: int | float = 0.99, scaling: str = "cell"):
        if scaling not in self.SCALINGS:
            raise ValueError(f"PCA scaling must be one of {self.SCALINGS}, got '{scaling}'")
        self.n_components = n_components
        self.scaling = scaling

    def fit(self, fields: np.ndarray) -> StrainPCA:
        """Fit on training fields (n_rows, n_cells)."""
        fields = np.asarray(fields, dtype=float)
        if fields.ndim != 2 or len(fields) < 2:
            raise ValueError(f"fields must be (n_rows >= 2, n_cells), got {fields.shape}")
        if not np.all(np.isfinite(fields)):
            raise ValueError("fields contain NaN or inf (failed simulations must be dropped first)")
        self.mean_ = fields.mean(axis=0)
        scale = fields.std(axis=0) if self.scaling == "cell" else np.ones(fields.shape[1])
        self.scale_ = np.where(scale > 1e-12 * max(scale.max(), 1e-300), scale, 1.0)
        z = (fields - self.mean_) / self.scale_
        _, s, vt = np.linalg.svd(z, full_matrices=False)
        variance = s**2
        self.explained_variance_ratio_ = variance / variance.sum()
        n = self.n_components
        if isinstance(n, float) and 0 < n < 1:
            cumulative = np.cumsum(self.explained_variance_ratio_)
            m = int(np.searchsorted(cumulative, n) + 1)
        elif isinstance(n, int) and 1 <= n <= len(s):
            m = n
        else:
            raise ValueError(f"n_components must be an int in [1, {len(s)}] or a float in (0, 1), got {n!r}")
        self.n_components_ = m
        # sign convention: the largest-magnitude entry of each direction is positive
        signs = np.sign(vt[np.arange(m), np.argmax(np.abs(vt[:m]), axis=1)])
        self.components_ = vt[:m] * signs[:, None]
        self.discarded_components_ = vt[m : m + self.N_DISCARDED]
        self.discarded_variance_ = variance[m : m + self.N_DISCARDED] / len(fields)
        return self

    def transform(self, fields: np.ndarray) -> np.ndarray:
        """PC weights (n_rows, M) of fields (n_rows, n_cells)."""
        return ((np.asarray(fields, dtype=float) - self.mean_) / self.scale_) @ self.components_.T

    def transform_masked(self, field: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weights (M,) of one field known only on ``mask`` (least squares on those cells).

        Also returns the (M, n_masked) matrix P with weights = P @ z[mask], z the standardised
        field, used to carry per-cell noise into weight space. With a full mask P is
        ``components_`` and the weights equal :meth:`transform`.
        """
        mask = np.asarray(mask, dtype=bool)
        if mask.all():
            projector = self.components_
        else:
            a = self.components_[:, mask].T  # (n_masked, M)
            projector = np.linalg.pinv(a)
        z = (np.asarray(field, dtype=float)[mask] - self.mean_[mask]) / self.scale_[mask]
        return projector @ z, projector

    def inverse_transform(self, weights: np.ndarray) -> np.ndarray:
        """Fields (n_rows, n_cells) from PC weights (n_rows, M)."""
        return (np.asarray(weights, dtype=float) @ self.components_) * self.scale_ + self.mean_

    def explained_variance(self, fields: np.ndarray) -> np.ndarray:
        """Cumulative share of the standardised variance of ``fields`` captured by 1..M PCs."""
        z = (np.asarray(fields, dtype=float) - self.mean_) / self.scale_
        z -= z.mean(axis=0)
        total = np.sum(z**2)
        w = z @ self.components_.T
        return np.cumsum(np.sum(w**2, axis=0)) / total

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        return {
            f"{prefix}mean": self.mean_,
            f"{prefix}scale": self.scale_,
            f"{prefix}components": self.components_,
            f"{prefix}explained_variance_ratio": self.explained_variance_ratio_,
            f"{prefix}discarded_components": self.discarded_components_,
            f"{prefix}discarded_variance": self.discarded_variance_,
        }

    @classmethod
    def from_arrays(cls, arrays, prefix: str) -> StrainPCA:
        pca = cls(n_components=int(len(arrays[f"{prefix}components"])))
        pca.mean_ = np.asarray(arrays[f"{prefix}mean"])
        pca.scale_ = np.asarray(arrays[f"{prefix}scale"])
        pca.components_ = np.asarray(arrays[f"{prefix}components"])
        pca.explained_variance_ratio_ = np.asarray(arrays[f"{prefix}explained_variance_ratio"])
        pca.n_components_ = len(pca.components_)
        pca.scaling = "none" if np.all(pca.scale_ == 1.0) else "cell"
        if f"{prefix}discarded_components" in arrays:
            pca.discarded_components_ = np.asarray(arrays[f"{prefix}discarded_components"])
            pca.discarded_variance_ = np.asarray(arrays[f"{prefix}discarded_variance"])
        else:  # saved before the discarded directions were kept
            pca.discarded_components_ = np.zeros((0, pca.components_.shape[1]))
            pca.discarded_variance_ = np.zeros(0)
        return pca
