"""The emulator's own error in PC-weight units: what a posterior carries next to the noise.

For the PC weights w_og (observation o, weight g) of one material, the emulator's prediction
m_g differs from the simulated weights by three terms, each a covariance over the observations
of one material and independent between weights (as the GPs are):

1. **GP predictive covariance** (:meth:`surrogate.gp.GPBank.joint`), what each GP itself says.
2. **Held-out excess** tau_g^2 R_g: how much larger the GP's error on materials it was not
   conditioned on is than its own predictive variance. Measured by material-wise K-fold
   cross-validation on the training materials with the fitted kernels
   (:func:`cross_validated_excess`): tau_g^2 is the smallest variance with
   mean(r^2 / (v + tau_g^2)) <= 1 over the left-out rows (r the error, v the GP variance).
   Between observations of one material it is correlated as the GP's kernel is along the
   design inputs (:func:`design_correlation`): the error of a material changes smoothly with
   alpha * t.
3. **PCA truncation**: the training fields' variance along the discarded PCA directions, carried
   through the (masked) projection onto the retained ones (:func:`truncation_variance`). Zero
   for a field observed on every cell (the projection is orthogonal), and growing with the
   holes of a DIC field; taken independent between observations.

Units: weights are in the PCA's standardised units (per-cell scaled strain), as the GPs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import brentq

from surrogate.gp import GPBank
from surrogate.pca import StrainPCA

FOLDS = 5


@dataclass(frozen=True)
class HeldOutExcess:
    """The cross-validated excess error of each GP (recorded in ``meta.json``).

    Attributes:
        variance: (G,) tau_g^2 [PC-weight units^2], 0 where the GP's own variance suffices.
        z_rms: (G,) RMS of error / GP predictive sd on the left-out rows, before the excess [-].
        folds: number of material folds.
        n_rows: left-out (material, design, frame) rows the excess was fitted on.
    """

    variance: tuple[float, ...]
    z_rms: tuple[float, ...]
    folds: int
    n_rows: int

    def to_json(self) -> dict:
        return {"variance": list(self.variance), "z_rms": list(self.z_rms), "folds": self.folds,
                "n_rows": self.n_rows}

    @classmethod
    def from_json(cls, entry: dict) -> HeldOutExcess:
        return cls(tuple(entry["variance"]), tuple(entry["z_rms"]), entry["folds"], entry["n_rows"])


def excess_variance(error: np.ndarray, variance: np.ndarray) -> float:
    """Smallest tau^2 >= 0 with mean(error^2 / (variance + tau^2)) <= 1; error, variance (n,)."""
    excess = lambda tau2: float(np.mean(error**2 / (variance + tau2))) - 1.0  # noqa: E731
    if excess(0.0) <= 0:
        return 0.0
    return brentq(excess, 0.0, float(np.mean(error**2)), xtol=1e-14, rtol=1e-10)


def cross_validated_excess(bank: GPBank, x: np.ndarray, weights: np.ndarray, materials: np.ndarray,
                           gp_subset: np.ndarray, folds: int = FOLDS, seed: int = 0,
                           max_rows: int = 4000) -> HeldOutExcess:
    """Material-wise K-fold cross-validation of a fitted GP bank.

    Args:
        bank: the fitted GPs (their kernels are kept; only the conditioning rows change).
        x: (n, 7) unit-box inputs of every training row; weights: (n, G) their PC weights.
        materials: (n,) material index of each row.
        gp_subset: indices of the rows ``bank`` was conditioned on.
        max_rows: at most this many left-out rows are predicted (a seeded subset).
    """
    rng = np.random.default_rng(seed)
    names = rng.permutation(np.unique(materials))
    if len(names) < folds:
        raise ValueError(f"cross-validation by material needs >= {folds} training materials, got {len(names)}")
    rows = np.sort(rng.choice(len(x), min(max_rows, len(x)), replace=False))
    errors, variances = [], []
    for fold in np.array_split(names, folds):
        keep = gp_subset[~np.isin(materials[gp_subset], fold)]
        test = rows[np.isin(materials[rows], fold)]
        fold_bank = bank.conditioned(x[keep], weights[keep])
        for chunk in np.array_split(test, max(1, len(test) // 500)):
            with torch.no_grad():
                mean, var = fold_bank(torch.as_tensor(x[chunk]))
            errors.append(weights[chunk] - mean.numpy())
            variances.append(var.numpy())
    error, variance = np.concatenate(errors), np.concatenate(variances)
    tau2 = [excess_variance(error[:, g], variance[:, g]) for g in range(error.shape[1])]
    z_rms = np.sqrt(np.mean(error**2 / variance, axis=0))
    return HeldOutExcess(tuple(tau2), tuple(z_rms.tolist()), folds, len(error))


def design_correlation(bank: GPBank, design: np.ndarray) -> np.ndarray:
    """(G, n_obs, n_obs) correlation of one material's emulator error between observations:
    each GP's RBF kernel on the design inputs only; ``design`` (n_obs, 2) in the unit box."""
    scaled = design[None] / bank.length_scale[:, 5:].cpu().numpy()[:, None]  # (G, n_obs, 2)
    sq = ((scaled[:, :, None] - scaled[:, None]) ** 2).sum(-1)
    return np.exp(-0.5 * sq)


def truncation_variance(pca: StrainPCA, projector: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M,) variance that the discarded PCA directions put on the M weights of a field observed
    on ``mask`` (n_cells,) through ``projector`` (M, n_masked) (:meth:`StrainPCA.transform_masked`)."""
    leak = projector @ pca.discarded_components_[:, mask].T  # (M, K)
    return (leak**2) @ pca.discarded_variance_
