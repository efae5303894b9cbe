"""Is one material's emulator error the average one? Whitened errors at the truth, per material.

    python benchmarks/material_scale.py --emulator EMU --data FRESH.h5 [--results FILE]

For every test material of FRESH.h5, the last frame of one design (material i: design i mod n,
as ``skinid study coverage --starts 1``) and of all designs, projected on the emulator's PCs and
whitened at the true parameters by the likelihood's covariance (GP + held-out excess + PCA
truncation, ``inference.model.SkinPosterior``, noise-free): under the model each whitened weight
is a standard normal, so the sum of squares q of one material is chi^2 with n = weights; under
the material scale (lambda ~ InverseGamma(a, a - 1)) q / n / (b / a) is F(n, 2a). Writes the
quantiles of q over materials next to both models' (benchmarks/results/material_scale.json),
and, per PC weight, the correlation of the errors between two designs of one material over the
materials against the one the likelihood assumes (mean over the pairs of designs).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.stats import chi2, f

HERE = Path(__file__).resolve().parent
LEVELS = [0.1, 0.25, 0.5, 0.75, 0.9]


def at_truth(emulator, data, material: int, designs: list[int]):
    """The noise-free likelihood of one material's last frames and its true parameters (5,)."""
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset

    observed = ObservedWeights.project(emulator, from_dataset(data, material, designs, [-1]))
    return SkinPosterior(emulator, observed), torch.as_tensor(observed.truth)


def whitened(posterior, truth) -> np.ndarray:
    """(n_obs * G,) whitened PC weights at the truth (noise sigma ~0: noise-free data)."""
    sigma = torch.full((posterior.n_sigma,), 1e-8, dtype=torch.float64)
    white, _ = posterior.whitened_residuals(truth, sigma)
    return white.numpy().ravel()


def standardised_errors(posterior, truth) -> tuple[np.ndarray, np.ndarray]:
    """Errors / model sd (n_obs, G) at the truth, and the model's correlation between the
    observations (G, n_obs, n_obs) (noise-free)."""
    with torch.no_grad():
        mean, gp_cov = posterior.gp_moments(truth)
        cov = posterior.model_covariance(gp_cov).numpy()
    sd = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))  # (G, n_obs)
    return (posterior.weights.numpy() - mean.numpy()) / sd.T, cov / sd[:, :, None] / sd[:, None, :]


def design_correlations(likelihoods: list) -> dict:
    """Per PC weight: mean over design pairs of the errors' correlation over materials, and of the
    likelihood's (median over materials); ``likelihoods``: (posterior, truth) of every material
    observed from every design."""
    pairs = [standardised_errors(*at) for at in likelihoods]
    z = np.stack([p[0] for p in pairs])  # (M, n_obs, G)
    model = np.median(np.stack([p[1] for p in pairs]), axis=0)  # (G, n_obs, n_obs)
    upper = np.triu_indices(z.shape[1], 1)
    measured = [float(np.corrcoef(z[:, :, g].T)[upper].mean()) for g in range(z.shape[2])]
    assumed = [float(model[g][upper].mean()) for g in range(z.shape[2])]
    return {"measured": measured, "assumed": assumed, "materials": len(likelihoods)}


def quantiles(q: np.ndarray, n: int, shape: float, rate: float) -> dict:
    """Quantiles of the sums of squares q (materials,) of n weights, and of both models' q."""
    return {
        "n_weights": n,
        "levels": LEVELS,
        "fresh": np.percentile(q, [100 * p for p in LEVELS]).round(3).tolist(),
        "gaussian": chi2.ppf(LEVELS, n).round(3).tolist(),
        "material_scale": (n * rate / shape * f.ppf(LEVELS, n, 2 * shape)).round(3).tolist(),
    }


def main() -> None:
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--emulator", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True, help="dataset of fresh test materials")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "material_scale.json")
    args = parser.parse_args()
    emulator, data = Emulator.load(args.emulator), StrainDataset.open(args.data)
    shape, rate = emulator.held_out_excess.material_scale
    tests = [int(i) for i in np.flatnonzero(data.split == 1)]
    n_designs = len(data.designs)
    results = {"emulator": str(args.emulator), "data": str(args.data), "material_scale": [shape, rate]}
    likelihoods = {}
    for name, designs_of in (
        ("one_design", lambda i: [i % n_designs]),
        ("all_designs", lambda i: list(range(n_designs))),
    ):
        likelihoods[name] = [at_truth(emulator, data, i, designs_of(i)) for i in tests]
        white = np.stack([whitened(*at) for at in likelihoods[name]])
        results[name] = {
            **quantiles(np.sum(white**2, axis=1), white.shape[1], shape, rate),
            "materials": len(tests),
            "kurtosis": float(np.mean(white**4) / np.mean(white**2) ** 2),
            "median_abs": float(np.median(np.abs(white))),
        }
    results["design_correlation"] = design_correlations(likelihoods["all_designs"])
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
