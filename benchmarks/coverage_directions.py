"""Are coverage posteriors calibrated along their own principal directions? From kept case files.

    python benchmarks/coverage_directions.py --store out/cov_draws/<study> [...] --bounds EMU [--results FILE]

Reads the case files of ``skinid study coverage`` folders (each keeps the truth and the 99
thinned draws it was ranked among). Per case, in the emulator's unit box: the draws' covariance,
its eigenvectors (narrowest first) and the truth's distance from the posterior mean along each,
in that direction's sd. Calibrated, each has variance 1 over the cases, whichever direction the
data constrain and whichever the prior alone bounds; a narrow direction with variance far above 1
is an over-confident one. Also the mean |theta loading| and sd of each direction, the RMS error of the posterior mean
per parameter (unit box), and theta's own
z^2 = (sum_k w_k z_k)^2 (w_k = V_theta,k sd_k / sd_theta) split into the directions' parts
sum_k w_k^2 z_k^2 and the cross terms; θ's rms_z and central-half coverage by band of the true
θ (0-20, 20-70, 70-90 deg). Writes benchmarks/results/coverage_directions.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def direction_scores(draws: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(z (5,), sd (5,), eigenvectors (5, 5) as columns) of one case, narrowest direction first;
    ``draws`` (n, 5) and ``truth`` (5,) in the unit box."""
    values, vectors = np.linalg.eigh(np.cov(draws.T))
    return vectors.T @ (truth - draws.mean(axis=0)) / np.sqrt(values), np.sqrt(values), vectors


def kept_cases(folder: Path) -> list:
    """The :class:`inference.coverage.CaseResult` of every case file of ``folder`` that kept its draws."""
    from inference.coverage import CaseResult

    cases = [CaseResult(**json.loads(p.read_text())) for p in sorted((folder / "cases").glob("*.json"))]
    cases = [c for c in cases if c.thinned_draws]
    if not cases:
        raise SystemExit(f"coverage_directions.py: {folder} has no case files with kept draws")
    return cases


def summarise(cases: list, lower: np.ndarray, upper: np.ndarray) -> dict:
    """Variance of the truth's z per principal direction over the ``cases`` of one study folder."""
    scores, errors = [], []
    for case in cases:
        unit = (np.array(case.thinned_draws) - lower) / (upper - lower)
        truth = (np.array(case.truth) - lower) / (upper - lower)
        scores.append(direction_scores(unit, truth))
        errors.append(unit.mean(axis=0) - truth)
    z, sd, vectors = (np.array(s) for s in zip(*scores))
    weights = vectors[:, 4, :] * sd / np.sqrt(np.sum((vectors[:, 4, :] * sd) ** 2, axis=1, keepdims=True))
    theta_z2 = np.sum(weights * z, axis=1) ** 2  # theta's own z^2 = (sum_k w_k z_k)^2
    parts = np.sum(weights**2 * z**2, axis=1)
    return {
        "cases": len(scores),
        "rms_error_of_mean_unit_box": np.sqrt(np.mean(np.square(errors), axis=0)).round(4).tolist(),  # per parameter
        "truth_z_variance": np.mean(z**2, axis=0).round(3).tolist(),
        "mean_sd_unit_box": sd.mean(axis=0).round(4).tolist(),
        "mean_abs_theta_loading": np.abs(vectors[:, 4, :]).mean(axis=0).round(3).tolist(),
        "theta_mean_z2": round(float(theta_z2.mean()), 3),
        "theta_mean_z2_per_direction_parts": round(float(parts.mean()), 3),
        "theta_mean_z2_cross_terms": round(float((theta_z2 - parts).mean()), 3),
    }


def theta_bands(cases: list, edges=(0.0, 20.0, 70.0, 90.0)) -> dict:
    """θ's rms_z and central-half coverage over the ``cases`` whose true θ [deg] lies in each band."""
    truth = np.array([c.truth[4] for c in cases])
    z = np.array([c.z_scores()[4] for c in cases])
    covered = np.array([c.covered_50[4] for c in cases], float)
    bands = {}
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (truth >= lo) & (truth < hi)
        bands[f"{lo:g}-{hi:g} deg"] = {
            "cases": int(inside.sum()),
            "rms_z": round(float(np.sqrt(np.mean(z[inside] ** 2))), 3),
            "coverage_50": round(float(covered[inside].mean()), 3),
        }
    return bands


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, nargs="+", required=True, help="study folders with cases/")
    parser.add_argument("--bounds", type=Path, required=True, help="emulator folder (its meta.json box)")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "coverage_directions.json")
    args = parser.parse_args()
    meta = json.loads((args.bounds / "meta.json").read_text())
    lower, upper = np.array(meta["lower"][:5]), np.array(meta["upper"][:5])
    results = {"order": "narrowest direction first", "studies": {}}
    for folder in args.store:
        cases = kept_cases(folder)
        results["studies"][str(folder)] = {**summarise(cases, lower, upper), "theta_bands": theta_bands(cases)}
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
