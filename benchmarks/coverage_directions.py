"""Are coverage posteriors calibrated along their own principal directions? From kept case files.

    python benchmarks/coverage_directions.py --store out/cov_draws/<study> [...] --bounds EMU [--results FILE] [--pool]

Reads the case files of ``skinid study coverage`` folders (each keeps the truth and the 99
thinned draws it was ranked among). Per case, in the emulator's unit box: the draws' covariance,
its eigenvectors (narrowest first) and the truth's distance from the posterior mean along each,
in that direction's sd. Calibrated, each has variance 1 over the cases, whichever direction the
data constrain and whichever the prior alone bounds; a narrow direction with variance far above 1
is an over-confident one. Also the mean |theta loading| and sd of each direction, the RMS error of the posterior mean
per parameter (unit box), and theta's own
z^2 = (sum_k w_k z_k)^2 (w_k = V_theta,k sd_k / sd_theta) split into the directions' parts
sum_k w_k^2 z_k^2 and the cross terms; by band of the true θ (0-20, 20-70, 70-90 deg) θ's
rms_z and central-half coverage, and every parameter's RMS error of the mean against its mean
posterior sd; by quartile of |sin 2θ| θ's error and sd in degrees. ``--pool``: the folders'
cases as one study (halves run apart). Writes
benchmarks/results/coverage_directions.json.
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


def in_unit_box(cases: list, lower: np.ndarray, upper: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Each case's thinned draws (99, 5) and the truths (n, 5), in the unit box of ``lower``, ``upper`` (5,)."""
    span = upper - lower
    draws = [(np.array(c.thinned_draws) - lower) / span for c in cases]
    return draws, (np.array([c.truth for c in cases]) - lower) / span


def summarise(cases: list, lower: np.ndarray, upper: np.ndarray) -> dict:
    """Variance of the truth's z per principal direction over the ``cases`` of one study folder."""
    draws, truths = in_unit_box(cases, lower, upper)
    z, sd, vectors = (np.array(s) for s in zip(*map(direction_scores, draws, truths)))
    errors = np.array([d.mean(axis=0) for d in draws]) - truths
    weights = vectors[:, 4, :] * sd / np.sqrt(np.sum((vectors[:, 4, :] * sd) ** 2, axis=1, keepdims=True))
    theta_z2 = np.sum(weights * z, axis=1) ** 2  # theta's own z^2 = (sum_k w_k z_k)^2
    parts = np.sum(weights**2 * z**2, axis=1)
    return {
        "cases": len(cases),
        "rms_error_of_mean_unit_box": np.sqrt(np.mean(np.square(errors), axis=0)).round(4).tolist(),  # per parameter
        "truth_z_variance": np.mean(z**2, axis=0).round(3).tolist(),
        "mean_sd_unit_box": sd.mean(axis=0).round(4).tolist(),
        "mean_abs_theta_loading": np.abs(vectors[:, 4, :]).mean(axis=0).round(3).tolist(),
        "theta_mean_z2": round(float(theta_z2.mean()), 3),
        "theta_mean_z2_per_direction_parts": round(float(parts.mean()), 3),
        "theta_mean_z2_cross_terms": round(float((theta_z2 - parts).mean()), 3),
    }


def theta_bands(cases: list, lower: np.ndarray, upper: np.ndarray, edges=(0.0, 20.0, 70.0, 90.0)) -> dict:
    """Over the ``cases`` whose true θ [deg] lies in each band: θ's rms_z and central-half
    coverage, and per parameter the RMS error of the posterior mean and the mean posterior sd, in
    the unit box (calibrated: equal)."""
    truth = np.array([c.truth[4] for c in cases])
    z = np.array([c.z_scores()[4] for c in cases])
    covered = np.array([c.covered_50[4] for c in cases], float)
    draws, truths = in_unit_box(cases, lower, upper)
    error = np.array([d.mean(axis=0) for d in draws]) - truths
    sd = np.array([d.std(axis=0) for d in draws])
    bands = {}
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (truth >= lo) & (truth < hi)
        bands[f"{lo:g}-{hi:g} deg"] = {
            "cases": int(inside.sum()),
            "rms_z": round(float(np.sqrt(np.mean(z[inside] ** 2))), 3),
            "coverage_50": round(float(covered[inside].mean()), 3),
            "rms_error_of_mean_unit_box": np.sqrt(np.mean(error[inside] ** 2, axis=0)).round(4).tolist(),
            "mean_sd_unit_box": sd[inside].mean(axis=0).round(4).tolist(),
        }
    return bands


def theta_sensitivity_quartiles(cases: list) -> list[dict]:
    """θ's error and width against |sin 2θ| of the true θ (the fibre term's sensitivity to θ: the
    fibre invariant is C11 cos²θ + C22 sin²θ + C12 sin 2θ), over quartiles of the cases by it: the
    RMS error of the posterior mean [deg], the mean posterior sd [deg], and the RMS of error x
    |sin 2θ| (constant over the quartiles if θ's error is a fixed-size error of cos 2θ)."""
    truth = np.array([c.truth[4] for c in cases])
    draws = [np.array(c.thinned_draws)[:, 4] for c in cases]
    error = np.array([d.mean() for d in draws]) - truth
    sd = np.array([d.std() for d in draws])
    sensitivity = np.abs(np.sin(np.radians(2 * truth)))
    scaled = error * sensitivity
    quartiles = []
    for part in np.array_split(np.argsort(sensitivity), 4):
        quartiles.append(
            {
                "abs_sin_2theta": [round(float(sensitivity[part].min()), 3), round(float(sensitivity[part].max()), 3)],
                "cases": len(part),
                "rms_error_deg": round(float(np.sqrt(np.mean(error[part] ** 2))), 2),
                "mean_sd_deg": round(float(sd[part].mean()), 2),
                "rms_error_times_abs_sin_2theta_deg": round(float(np.sqrt(np.mean(scaled[part] ** 2))), 2),
            }
        )
    return quartiles


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, nargs="+", required=True, help="study folders with cases/")
    parser.add_argument("--bounds", type=Path, required=True, help="emulator folder (its meta.json box)")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "coverage_directions.json")
    parser.add_argument("--pool", action="store_true", help="the folders' cases as one study (e.g. halves of one)")
    args = parser.parse_args()
    meta = json.loads((args.bounds / "meta.json").read_text())
    lower, upper = np.array(meta["lower"][:5]), np.array(meta["upper"][:5])
    results = {"order": "narrowest direction first", "studies": {}}
    groups = {" + ".join(map(str, args.store)): args.store} if args.pool else {str(f): [f] for f in args.store}
    for name, folders in groups.items():
        cases = [case for folder in folders for case in kept_cases(folder)]
        results["studies"][name] = {
            **summarise(cases, lower, upper),
            "theta_bands": theta_bands(cases, lower, upper),
            "theta_sensitivity_quartiles": theta_sensitivity_quartiles(cases),
        }
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
