"""How large the emulator's error on unseen materials is, frame by frame, against what it says.

    python benchmarks/emulator_error.py --train TRAIN.h5 --test TEST.h5 [--gp-fraction 0.5 --restarts 1]

Fits the emulator on TRAIN's training materials (as ``skinid surrogate fit``) and reports, per
frame and PC weight, the RMS of the standardised errors (error / predicted sd):
- on TEST's test materials (fresh materials): with the GP variance alone, and with the held-out
  excess of ``surrogate.error_model`` added;
- by 5-fold cross-validation by material on TRAIN: with the fitted kernels kept (only the
  conditioning rows left out) and with the GPs refitted per fold (what the emulator does).
A calibrated error model gives 1 (the spread of the error between materials:
``benchmarks/material_scale.py``). Results: benchmarks/results/emulator_error.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent


def per_frame_z_rms(error: np.ndarray, variance: np.ndarray, frame: np.ndarray) -> list[list[float]]:
    """(n_frames, G) RMS of error / sqrt(variance) over the rows of each frame."""
    z2 = error**2 / variance
    return [np.sqrt(z2[frame == k].mean(0)).round(3).tolist() for k in np.unique(frame)]


def main() -> None:
    from sklearn.gaussian_process import GaussianProcessRegressor

    from skinfem.io import StrainDataset
    from surrogate.emulator import TrainingRows, fit_emulator, gp_rows
    from surrogate.error_model import cross_validated_errors, cross_validated_excess
    from surrogate.gp import GPBank, StandardisedGP, fit_gps, standardisation

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=Path, required=True)
    parser.add_argument("--test", type=Path, required=True)
    parser.add_argument("--gp-fraction", type=float, default=0.5)
    parser.add_argument("--restarts", type=int, default=1)
    args = parser.parse_args()
    train, test = StrainDataset.open(args.train), StrainDataset.open(args.test)
    emulator = fit_emulator(train, gp_fraction=args.gp_fraction, restarts=args.restarts, n_jobs=1)
    excess = emulator.held_out_excess
    results = {"train": str(args.train), "test": str(args.test), "held_out_excess": excess.to_json()}

    rows = TrainingRows.from_dataset(test, np.flatnonzero(test.split == 1))
    weights = emulator.weights_of_fields(emulator.dataset_fields(rows.fields))
    with torch.no_grad():
        mean, var = emulator.predict_weights(torch.as_tensor(rows.inputs))
    error, var = weights - mean.numpy(), var.numpy()
    tau2 = np.array(excess.variance) * excess.load_scale(rows.inputs[:, 5:])[:, None] ** 2
    results["fresh_materials"] = {
        "gp_only": per_frame_z_rms(error, var, rows.index[:, 2]),
        "with_excess": per_frame_z_rms(error, var + tau2, rows.index[:, 2]),
    }

    train_rows = TrainingRows.from_dataset(train, np.flatnonzero(train.split == 0))
    x = emulator.scale(train_rows.inputs)
    w = emulator.weights_of_fields(emulator.dataset_fields(train_rows.fields))
    subset = gp_rows(len(x), args.gp_fraction, None, 0)
    kernels = [gp.gp.kernel_ for gp in emulator.sklearn_gps]

    def fixed_kernels(x_rows, y_rows):
        gps = []
        for g, kernel in enumerate(kernels):
            m, s = standardisation(y_rows[:, g])
            gp = GaussianProcessRegressor(kernel, optimizer=None).fit(x_rows, (y_rows[:, g] - m) / s)
            gps.append(StandardisedGP(gp, m, s))
        return GPBank.from_sklearn(gps)

    def refitted(x_rows, y_rows):
        return GPBank.from_sklearn(fit_gps(x_rows, y_rows, restarts=0, n_jobs=1, kernels=kernels))

    for name, fit in (("cv_kernels_kept", fixed_kernels), ("cv_refitted", refitted)):
        error, variance, _ = cross_validated_errors(fit, x, w, train_rows.index[:, 0], subset)
        results[name] = per_frame_z_rms(error, variance, train_rows.index[:, 2])
        results[name + "_excess"] = cross_validated_excess(
            fit,
            x,
            w,
            train_rows.index[:, 0],
            train_rows.inputs[:, 5:],
            subset,
            train_rows.index[:, 2] == train_rows.index[:, 2].max(),
            emulator.error_correlation,
        ).to_json()
    (HERE / "results" / "emulator_error.json").write_text(json.dumps(results, indent=2) + "\n")
    for key in ("fresh_materials", "cv_kernels_kept", "cv_refitted"):
        print(key, json.dumps(results[key])[:300])


if __name__ == "__main__":
    main()
