"""Is the likelihood's error right along each parameter's signature? One design, fresh materials.

    python benchmarks/signature_error.py --emulator EMU --data FRESH.h5 [--results FILE]

For every test material of FRESH.h5, the last frame of one design (material i: design i mod n,
as ``skinid study coverage --starts 1``), noise-free, at the true parameters: the emulator's
error e (PC weights) against the likelihood's covariance S of each error model (``off``: the
GP variance; ``on``: with the held-out excess and the PCA truncation; ``shift``: the parameter
shift J C J^T and what it leaves). Along the signature j_k = d(mean)/d(parameter k) the whitened
error a_k = j_k^T S^-1 e / sqrt(j_k^T S^-1 j_k) is a standard normal if S is right, so its variance
over the materials is 1: above 1 the model understates the error that looks like a change of
parameter k, below 1 it overstates it. Also e^T S^-1 e (chi^2 with as many degrees of freedom as
weights), and the variance along theta's signature by band of the true theta. Writes
benchmarks/results/signature_error.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # material_scale, a sibling
THETA_BANDS = ((0.0, 20.0), (20.0, 70.0), (70.0, 90.0))  # of the true theta [deg]
MODELS = {"off": (False, False), "on": (True, False), "shift": (True, True)}  # (emulator_error, shift)


def signature_errors(posterior, truth: torch.Tensor) -> tuple[np.ndarray, float]:
    """(a (5,), e^T S^-1 e) of one observed material at its truth (5,), noise-free."""
    from material_scale import error_at_truth

    error, signature, cov = error_at_truth(posterior, truth)
    precision = np.linalg.inv(cov)
    along = signature.T @ precision @ error / np.sqrt(np.einsum("ik,ij,jk->k", signature, precision, signature))
    return along, float(error @ precision @ error)


def main() -> None:
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset
    from skinfem.config import PARAM_NAMES
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--emulator", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True, help="dataset of fresh test materials")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "signature_error.json")
    args = parser.parse_args()
    emulator, data = Emulator.load(args.emulator), StrainDataset.open(args.data)
    materials = [int(i) for i in np.flatnonzero(data.split == 1)]
    results = {"emulator": str(args.emulator), "data": str(args.data), "parameters": list(PARAM_NAMES)}
    observed = [
        ObservedWeights.project(emulator, from_dataset(data, i, [i % len(data.designs)], [-1])) for i in materials
    ]
    for name, (error_model, shift) in MODELS.items():
        rows = []
        for weights in observed:
            posterior = SkinPosterior(emulator, weights, emulator_error=error_model, emulator_shift=shift)
            rows.append(signature_errors(posterior, torch.as_tensor(weights.truth)))
        along, quadratic = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
        theta = data.params[materials, 4]
        results[name] = {
            "variance_along_signature": np.mean(along**2, axis=0).round(3).tolist(),
            "variance_along_theta_by_band": {
                f"{lo:g}-{hi:g} deg": round(float(np.mean(along[(theta >= lo) & (theta < hi), 4] ** 2)), 3)
                for lo, hi in THETA_BANDS
            },
            "mean_quadratic_form": round(float(quadratic.mean()), 3),
            "median_quadratic_form": round(float(np.median(quadratic)), 3),
            "weights": int(posterior.weights.numel()),
            "materials": len(materials),
        }
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
