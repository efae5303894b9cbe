"""Is one material's emulator error the average one? Whitened errors at the truth, per material.

    python benchmarks/material_scale.py --emulator EMU --data FRESH.h5 [--results FILE]
    python benchmarks/material_scale.py --emulator EMU --data FRESH.h5 --fresh-shift TRAINING.h5 [--oracle DIR]

For every test material of FRESH.h5, the last frame of one design (material i: design i mod n,
as ``skinid study coverage --starts 1``) and of all designs, projected on the emulator's PCs and
whitened at the true parameters by the likelihood's covariance (GP + held-out excess + PCA
truncation, ``inference.model.SkinPosterior``, noise-free): under the model each whitened weight
is a standard normal, so the sum of squares q of one material is chi^2 with n = weights; under
the material scale (lambda ~ InverseGamma(a, a - 1)) q / n / (b / a) is F(n, 2a). Writes the
quantiles of q over materials next to both models' (benchmarks/results/material_scale.json),
and, per PC weight, the correlation of the errors between two designs of one material over the
materials against the one the likelihood assumes (mean over the pairs of designs).

``linearised``: the coverage study's cases with more weights than parameters (``frames``,
``membranes``, one starting design per material as ``--starts 1``) and every design's last frame
(``all_designs``) or last three frames (``all_designs_3_frames``), linearised at the truth. The
whitened error e (n,) moves the estimate by delta = (J^T J)^-1 J^T e (J the whitened Jacobian of
the emulator mean in the parameters); under the model delta_k / sd_k is a standard normal
(lambda = 1), and with the material scale the marginal of a parameter is Student-t with
nu = 2a + n - 5 and scale^2 = sd_k^2 b' / a' (lambda's posterior InverseGamma(a + (n - 5) / 2,
b + |e - J delta|^2 / 2)). Recorded per parameter: the coverage of those linearised 50 % / 95 %
intervals (flat prior, box bounds ignored) under both, mean z^2, and the share of |e|^2 the
parameters absorb against the p / n an isotropic error would give.

``--fresh-shift``: the cross-validation's shift covariance C (recomputed from TRAINING.h5, the
emulator's dataset) against the fresh materials' own shifts under the emulator's GPs, same
estimator, and what the shifts leave of the error against the GP variance
(benchmarks/results/material_scale_fresh_shift.json); ``--oracle`` also writes a copy of the
emulator with the fresh materials' C (a diagnostic: fitted on the cases it is scored on).

``--halves DIR``: C fitted as the emulator fits it but on alternate halves of the fresh materials
(each half's copy of the emulator, DIR_A and DIR_B, is then scored by ``benchmarks/coverage.py
--materials`` on the other half: a C from materials the GPs did not see, without the oracle's
circularity; benchmarks/results/material_scale_halves.json).

``shift``: the same cases under the likelihood of ``--emulator-error shift`` (the emulator's
cross-validated parameter shift, ``meta.json`` ``held_out_excess.parameter_shift``, carried as
J C J^T over every weight): the generalised least-squares shift of the estimate and its
covariance under that likelihood, linearised at the truth as above.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.stats import chi2, f, norm, t

HERE = Path(__file__).resolve().parent
LEVELS = [0.1, 0.25, 0.5, 0.75, 0.9]


def at_truth(emulator, data, material: int, designs: list[int], frames: tuple[int, ...] = (-1,), shift=False):
    """The noise-free likelihood of one material's frames (default: the last; with the parameter
    shift or not) and its true parameters (5,)."""
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset

    observed = ObservedWeights.project(emulator, from_dataset(data, material, designs, list(frames)))
    return SkinPosterior(emulator, observed, emulator_shift=shift), torch.as_tensor(observed.truth)


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


@dataclass(frozen=True)
class LinearisedFit:
    """The estimate's shift by the emulator error at the truth, linearised (physical units)."""

    delta: np.ndarray  # (5,) shift of the estimate
    cov: np.ndarray  # (5, 5) (J^T J)^-1, the likelihood's covariance of the estimate at lambda = 1
    residual: float  # |e - J delta|^2 left after the shift [-]
    absorbed: float  # share of |e|^2 the parameters absorb [-]

    @property
    def z(self) -> np.ndarray:
        return self.delta / np.sqrt(np.diag(self.cov))


def error_at_truth(posterior, truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The emulator's error e (n,), the mean's Jacobian in the raw parameters (n, 5) and the
    likelihood's covariance over every weight (n, n) at the truth, noise-free, in the order (g, o)
    (the parameter shift's J C J^T included when the posterior carries it)."""
    from inference.model import coupled_covariance

    factor = posterior.shift_factor(truth, differentiable=False)
    with torch.no_grad():
        mean, gp_cov = posterior.gp_moments(truth)
        blocks = posterior.model_covariance(gp_cov)
        cov = torch.block_diag(*blocks) if factor is None else coupled_covariance(blocks, factor, 1.0)
    jac = torch.autograd.functional.jacobian(lambda p: posterior.gp_moments(p)[0], truth).numpy()  # (n_obs, G, 5)
    error = (posterior.weights - mean).numpy().T.ravel()
    return error, jac.transpose(1, 0, 2).reshape(-1, 5), cov.numpy()


def linearised_fit(posterior, truth) -> LinearisedFit:
    """The shift of one case's estimate, whitened by the likelihood's covariance over every weight
    (lambda = 1; the parameter shift's J C J^T included when the posterior carries it)."""
    from surrogate.error_model import least_squares_shift

    error, jacobian, cov = error_at_truth(posterior, truth)
    chol = np.linalg.cholesky(cov)
    jw = np.linalg.solve(chol, jacobian)
    white = np.linalg.solve(chol, error)
    delta, _, absorbed = least_squares_shift(white, jw)
    return LinearisedFit(delta, np.linalg.inv(jw.T @ jw), (1 - absorbed) * float(white @ white), absorbed)


def linearised_coverage(fits: list[LinearisedFit], shifted: list[LinearisedFit], n: int, shape, rate) -> dict:
    """Coverage of the linearised intervals over the materials' fits: the likelihood's (fixed),
    with the material scale (scaled), and ``shifted``: the fits under the parameter shift."""
    z = np.stack([fit.z for fit in fits])  # (M, 5)
    residual = np.array([fit.residual for fit in fits])
    dof = n - z.shape[1]
    nu = 2 * shape + dof
    spread = np.sqrt((rate + residual / 2) / (shape + dof / 2))[:, None]  # sqrt(b' / a')
    z_shift = np.stack([fit.z for fit in shifted])

    def covered(level: float) -> dict:
        q = (1 + level) / 2
        return {
            "fixed": np.mean(np.abs(z) < norm.ppf(q), axis=0).round(3).tolist(),
            "scaled": np.mean(np.abs(z) / spread < t.ppf(q, nu), axis=0).round(3).tolist(),
            "shift": np.mean(np.abs(z_shift) < norm.ppf(q), axis=0).round(3).tolist(),
        }

    return {
        "n_weights": n,
        "materials": len(fits),
        "coverage_50": covered(0.5),
        "coverage_95": covered(0.95),
        "mean_z2": {
            "fixed": np.mean(z**2, axis=0).round(3).tolist(),
            "shift": np.mean(z_shift**2, 0).round(3).tolist(),
        },
        "absorbed_share": float(np.mean([fit.absorbed for fit in fits])),
        "isotropic_share": z.shape[1] / n,
        "lambda_posterior_median": float(np.median(spread**2)),
    }


def quantiles(q: np.ndarray, n: int, shape: float, rate: float) -> dict:
    """Quantiles of the sums of squares q (materials,) of n weights, and of both models' q."""
    return {
        "n_weights": n,
        "levels": LEVELS,
        "fresh": np.percentile(q, [100 * p for p in LEVELS]).round(3).tolist(),
        "gaussian": chi2.ppf(LEVELS, n).round(3).tolist(),
        "material_scale": (n * rate / shape * f.ppf(LEVELS, n, 2 * shape)).round(3).tolist(),
    }


def rows_and_weights(emulator, data, materials) -> tuple:
    """Every converged (design, frame) row of ``materials`` of ``data``: rows, unit-box inputs (n, 7),
    PC weights (n, G) and load scale s (n,) as the emulator's fit makes them."""
    from surrogate.emulator import TrainingRows

    rows = TrainingRows.from_dataset(data, materials)
    weights = emulator.weights_of_fields(emulator.dataset_fields(rows.fields))
    return rows, emulator.scale(rows.inputs), weights, emulator.held_out_excess.load_scale(rows.inputs[:, 5:])


def fresh_errors(emulator, data) -> tuple:
    """The fresh (test-split) materials' rows of ``data`` under the emulator's own GPs: rows, PC
    weight errors and GP variances (n, G), the mean's Jacobian in the material inputs (n, G, 5)
    and the load scale s (n,)."""
    from surrogate.error_model import mean_jacobian

    rows, x, weights, scale = rows_and_weights(emulator, data, np.flatnonzero(data.split == 1))
    mean, var, jac = mean_jacobian(emulator.gps, x)
    return rows, weights - mean, var, jac, scale


def split_shift_covariances(emulator, data) -> dict:
    """C as the emulator's fit estimates it (:func:`surrogate.error_model.shift_covariance`: the
    shifts' second moment less their fit errors, times M / (M - 6)), but from the fresh materials'
    shifts under the emulator's GPs, on alternate halves: "A" from the 1st, 3rd, ... fresh
    material, scored on the others, "B" the other way round. Unlike ``--oracle``, no case is
    scored under a C fitted on its own material."""
    from surrogate.error_model import material_shifts, shift_covariance

    rows, error, var, jac, scale = fresh_errors(emulator, data)
    tau2 = np.array(emulator.held_out_excess.variance)
    shifts, fit_errors, _, _ = material_shifts(error, var, jac, rows.index[:, 0], scale, tau2)
    materials = np.unique(rows.index[:, 0])
    halves = {}
    for name, parity in (("A", 0), ("B", 1)):
        fitted = np.arange(len(materials)) % 2 == parity
        covariance = shift_covariance(shifts[fitted], fit_errors[fitted])
        halves[name] = {
            "fitted_on": materials[fitted].tolist(),
            "scored_on": materials[~fitted].tolist(),
            "sd_unit_box": np.sqrt(np.diag(covariance)).round(4).tolist(),
            "covariance": covariance.tolist(),
        }
    return halves


def shift_and_residual(error, variance, jacobian, materials, scale, tau2) -> tuple[np.ndarray, np.ndarray]:
    """The second moment (5, 5) of the materials' parameter shifts, as the emulator's fit
    estimates it from its cross-validation (:func:`surrogate.error_model.shift_second_moment`,
    before the prediction's factor) but from any errors, and what the shifts leave of the errors
    (n, G)."""
    from surrogate.error_model import material_shifts, shift_second_moment

    shifts, fit_errors, _, residual = material_shifts(error, variance, jacobian, materials, scale, tau2)
    return shift_second_moment(shifts, fit_errors), residual


def fresh_against_cross_validation(emulator, data, training) -> dict:
    """Is the shift covariance C the cross-validation fits (left-out training materials, GPs
    refitted on the other folds) the size of fresh materials' shifts under the emulator's own
    GPs? The shifts' second moment on both (same estimator), and the emulator's C, the
    cross-validation's predicted for a new material; also each PC weight's mean square error, GP variance and what the
    shifts leave of the error at the last frame on both, and over all rows what they leave as a
    share of the GP variance."""
    from skinfem.config import PARAM_NAMES
    from surrogate.emulator import fold_refit, gp_rows
    from surrogate.error_model import cross_validated_errors

    tau2 = np.array(emulator.held_out_excess.variance)
    fresh_rows, error, var, jac, scale = fresh_errors(emulator, data)
    fresh_c, fresh_left = shift_and_residual(error, var, jac, fresh_rows.index[:, 0], scale, tau2)
    train_rows, xt, wt, st = rows_and_weights(emulator, training, np.flatnonzero(training.split == 0))
    p = emulator.provenance
    subset = gp_rows(len(train_rows.index), p.gp_fraction, None, p.seed)
    materials = train_rows.index[:, 0]
    refit = fold_refit(emulator.sklearn_gps, p.seed)
    cv_error, cv_var, cv_jac = cross_validated_errors(refit, xt, wt, materials, subset)
    cv_c, cv_left = shift_and_residual(cv_error, cv_var, cv_jac, materials, st, tau2)
    last_f, last_t = fresh_rows.index[:, 2] == len(data.t) - 1, train_rows.index[:, 2] == len(training.t) - 1
    return {
        "parameters": list(PARAM_NAMES),
        "shift_sd_unit_box": {
            "emulator": np.sqrt(np.diag(emulator.held_out_excess.parameter_shift.covariance)).round(4).tolist(),
            "cross_validation_second_moment": np.sqrt(np.diag(cv_c)).round(4).tolist(),
            "fresh": np.sqrt(np.diag(fresh_c)).round(4).tolist(),
        },
        "fresh_shift_covariance": fresh_c.tolist(),
        "last_frame_per_weight": {
            "mean_square_error_cross_validation": (cv_error[last_t] ** 2).mean(0).round(5).tolist(),
            "mean_square_error_fresh": (error[last_f] ** 2).mean(0).round(5).tolist(),
            "gp_variance_cross_validation": cv_var[last_t].mean(0).round(5).tolist(),
            "gp_variance_fresh": var[last_f].mean(0).round(5).tolist(),
            "left_by_the_shift_cross_validation": (cv_left[last_t] ** 2).mean(0).round(5).tolist(),
            "left_by_the_shift_fresh": (fresh_left[last_f] ** 2).mean(0).round(5).tolist(),
        },
        "left_by_the_shift_over_gp_variance_all_rows": {
            "cross_validation": ((cv_left**2).mean(0) / cv_var.mean(0)).round(3).tolist(),
            "fresh": ((fresh_left**2).mean(0) / var.mean(0)).round(3).tolist(),
        },
        "materials": {"fresh": int(np.sum(data.split == 1)), "training": int(np.sum(training.split == 0))},
    }


def write_oracle(emulator: Path, out: Path, covariance: list) -> None:
    """A copy of the emulator folder whose parameter shift's C is ``covariance`` (5 x 5)."""
    import shutil

    shutil.copytree(emulator, out)
    meta = json.loads((out / "meta.json").read_text())
    meta["held_out_excess"]["parameter_shift"]["covariance"] = covariance
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")


def write_halves(args, parser) -> None:
    """``--halves``: the two emulator copies of :func:`split_shift_covariances` and their record."""
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    folders = {name: args.halves.with_name(f"{args.halves.name}_{name}") for name in "AB"}
    if any(folder.exists() for folder in folders.values()):
        parser.error(f"--halves: {folders['A']} or {folders['B']} exists already")
    halves = split_shift_covariances(Emulator.load(args.emulator), StrainDataset.open(args.data))
    for name, folder in folders.items():
        write_oracle(args.emulator, folder, halves[name]["covariance"])
    result = {"emulator": str(args.emulator), "data": str(args.data), "copies": {n: str(f) for n, f in folders.items()}}
    (args.results or HERE / "results" / "material_scale_halves.json").write_text(
        json.dumps({**result, "halves": halves}, indent=2) + "\n"
    )
    print(json.dumps({**result, "sd_unit_box": {n: h["sd_unit_box"] for n, h in halves.items()}}, indent=1))


def main() -> None:
    from inference.coverage import cases_of
    from skinfem.config import PARAM_NAMES
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--emulator", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True, help="dataset of fresh test materials")
    parser.add_argument(
        "--results",
        type=Path,
        help="default: results/material_scale.json, with --fresh-shift material_scale_fresh_shift.json",
    )
    parser.add_argument(
        "--fresh-shift",
        type=Path,
        metavar="TRAINING.h5",
        help="only compare fresh materials' shifts with the cross-validation's (the emulator's training data)",
    )
    parser.add_argument(
        "--oracle",
        type=Path,
        metavar="DIR",
        help="with --fresh-shift: also write a copy of the emulator whose C is the fresh materials' own (a diagnostic)",
    )
    parser.add_argument(
        "--halves",
        type=Path,
        metavar="DIR",
        help="write copies DIR_A, DIR_B of the emulator whose C is fitted on alternate halves of the fresh "
        "materials (results/material_scale_halves.json says which half each is scored on)",
    )
    args = parser.parse_args()
    if args.halves is not None:
        write_halves(args, parser)
        return
    if args.oracle is not None and (args.fresh_shift is None or args.oracle.exists()):
        parser.error(f"--oracle needs --fresh-shift and a folder that does not exist yet, got {args.oracle}")
    name = "material_scale.json" if args.fresh_shift is None else "material_scale_fresh_shift.json"
    args.results = args.results or HERE / "results" / name
    emulator, data = Emulator.load(args.emulator), StrainDataset.open(args.data)
    if args.fresh_shift is not None:
        result = {"emulator": str(args.emulator), "data": str(args.data), "training": str(args.fresh_shift)}
        result.update(fresh_against_cross_validation(emulator, data, StrainDataset.open(args.fresh_shift)))
        args.results.write_text(json.dumps(result, indent=2) + "\n")
        if args.oracle is not None:
            write_oracle(args.emulator, args.oracle, result["fresh_shift_covariance"])
        print(json.dumps(result, indent=1))
        return
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
    shift = emulator.held_out_excess.parameter_shift
    results["parameter_shift"] = {
        **shift.to_json(),
        "sd_unit_box": np.sqrt(np.diag(shift.covariance)).round(4).tolist(),
    }
    results["linearised"] = {"parameters": list(PARAM_NAMES)}
    every_design = list(range(n_designs))
    setups = {
        setup: [(c.material, list(c.designs), c.frames) for c in cases_of(data, setup, starts=1)]
        for setup in ("frames", "membranes")
    }
    setups["all_designs"] = [(i, every_design, (-1,)) for i in tests]
    setups["all_designs_3_frames"] = [(i, every_design, (-3, -2, -1)) for i in tests]
    for setup, cases in setups.items():
        likelihoods = [at_truth(emulator, data, *case) for case in cases]
        fits = [linearised_fit(*at) for at in likelihoods]
        shifted = [linearised_fit(*at_truth(emulator, data, *case, shift=True)) for case in cases]
        n = likelihoods[0][0].weights.numel()
        results["linearised"][setup] = linearised_coverage(fits, shifted, n, shape, rate)
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
