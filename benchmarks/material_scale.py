"""Is one material's emulator error the average one? Whitened errors at the truth, per material.

    python benchmarks/material_scale.py --emulator EMU --data FRESH.h5 [--results FILE]

For every test material of FRESH.h5, the last frame of one design (material i: design i mod n,
as ``skinid study coverage --starts 1``) and of all designs, projected on the emulator's PCs and
whitened at the true parameters by the likelihood's covariance (GP + held-out excess + PCA
truncation, ``inference.model.SkinPosterior``, noise-free): under the model each whitened weight
is a standard normal, so the sum of squares q of one material is chi^2 with n = weights; under
the material scale (lambda ~ InverseGamma(a, a - 1)) q / n / (b / a) is F(n, 2a). Writes the
quantiles of q over materials next to both models' (benchmarks/results/material_scale.json).
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


def whitened(emulator, data, material: int, designs: list[int]) -> np.ndarray:
    """(n_obs * G,) whitened PC weights of one material's last frames at its true parameters."""
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset

    observed = ObservedWeights.project(emulator, from_dataset(data, material, designs, [-1]))
    posterior = SkinPosterior(emulator, observed, noise="known" if observed.noise_var is not None else "halfcauchy")
    sigma = torch.full((posterior.n_sigma,), 1e-8, dtype=torch.float64)  # noise-free data
    white, _ = posterior.whitened_residuals(torch.as_tensor(observed.truth), sigma)
    return white.numpy().ravel()


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
    for name, designs_of in (
        ("one_design", lambda i: [i % n_designs]),
        ("all_designs", lambda i: list(range(n_designs))),
    ):
        white = np.stack([whitened(emulator, data, i, designs_of(i)) for i in tests])
        results[name] = {
            **quantiles(np.sum(white**2, axis=1), white.shape[1], shape, rate),
            "materials": len(tests),
            "kurtosis": float(np.mean(white**4) / np.mean(white**2) ** 2),
            "median_abs": float(np.median(np.abs(white))),
        }
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
