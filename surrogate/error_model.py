"""The emulator's own error in PC-weight units: what a posterior carries next to the noise.

For the PC weights w_og (observation o, weight g) of one material, the emulator's prediction
m_g differs from the simulated weights by three terms, each a covariance over the observations
of one material and independent between weights (as the GPs are):

1. **GP predictive covariance** (:meth:`surrogate.gp.GPBank.joint`), what each GP itself says.
2. **Held-out excess** tau_g^2 s_o s_p R_g: how much larger the GP's error on materials it
   was not conditioned on is than its own predictive variance. The error grows with the load
   (it is a near-constant share of the strain, while a stationary GP's variance is not), so
   it scales with s = |alpha t| / |alpha t|_max, the load of the observation relative to the
   largest in the training rows. Measured by material-wise K-fold cross-validation on the
   training materials, the GPs refitted per fold (:func:`cross_validated_excess`): tau_g^2
   maximises the likelihood of the left-out errors r ~ N(0, v + tau_g^2 s^2) (v the GP
   variance). Between observations of one material it is correlated as the GP's kernel is
   along the design inputs (:func:`design_correlation`): the error of a material changes
   smoothly with alpha * t.
3. **PCA truncation**: the training fields' variance along the discarded PCA directions, carried
   through the (masked) projection onto the retained ones (:func:`truncation_variance`). Zero
   for a field observed on every cell (the projection is orthogonal), and growing with the
   holes of a DIC field; taken independent between observations.

The error of one material is not an average material's: on held-out materials most have a
smaller error than the mean square that tau_g^2 matches and a few a much larger one (the same
material is badly emulated in every weight and design). The error model therefore carries a
**material scale** lambda: the emulator covariance of one material is lambda times the terms
above, lambda ~ InverseGamma(a, a - 1) (mean 1: the level is tau_g^2's), its shape a fitted by
maximum likelihood to the held-out materials' errors at the largest load
(:func:`fit_material_scale`); a -> infinity is the Gaussian model. The posterior samples
lambda with the parameters.

Most of a material's error is a **parameter shift**: the emulator predicts the field of a
slightly different material, e_m(o) ~ J(o) delta_m + eps_m(o) with J the GP mean's Jacobian in
the five material inputs (on the ``small`` emulator 76-96 % of a left-out material's whitened
|e|^2 over all its rows, where an error independent between rows would lose 5 / n of it;
``benchmarks/material_scale.py``). That part is shared by every observation of the material,
so more observations do not average it out, and a residual cannot tell it from the parameters
(it moves the estimate instead of widening it). :func:`fit_parameter_shift` measures the
shifts delta_m of the left-out materials (their covariance C) and the held-out excess of what
they leave (:class:`ParameterShift`): a share rho_g of the GP variance and an excess; a
likelihood that carries J C J^T next to rho_g times the GP covariance and the rest
(``inference.model``, ``emulator_shift``) widens the intervals by C in parameter space without
counting the shift twice (once in C, once in the GP variance that measured it).

Units: weights are in the PCA's standardised units (per-cell scaled strain), as the GPs; the
shift in the emulator's unit box of the inputs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import minimize, minimize_scalar
from scipy.special import gammaln

from surrogate.gp import GPBank
from surrogate.pca import StrainPCA

FOLDS = 5
SHIFT_MATERIALS = 7  # a new material's shift covariance from fewer is unbounded (shift_covariance)


@dataclass(frozen=True)
class ParameterShift:
    """A material's emulator error as a shift of its parameters (module doc).

    Attributes:
        covariance: (5, 5) covariance C of the shift delta in the emulator's unit box [-].
        residual_variance: (G,) held-out excess of what the shift leaves, at s = 1 (as
            :attr:`HeldOutExcess.variance`) [PC-weight units^2].
        absorbed_share: mean share of a left-out material's whitened |e|^2 its shift explains [-].
        gp_share: (G,) rho_g in (0, 1]: what the shift leaves is N(0, rho_g v + tau_g^2 s^2), v the
            GP's predictive variance; most of v is the shift itself, which J C J^T carries
            (:func:`shift_residual_model`) [-]. 1 for emulators fitted before it was measured.
    """

    covariance: tuple[tuple[float, ...], ...]
    residual_variance: tuple[float, ...]
    absorbed_share: float
    gp_share: tuple[float, ...]

    def to_json(self) -> dict:
        return {
            "covariance": [list(row) for row in self.covariance],
            "residual_variance": list(self.residual_variance),
            "absorbed_share": self.absorbed_share,
            "gp_share": list(self.gp_share),
        }

    @classmethod
    def from_json(cls, entry: dict) -> ParameterShift:
        residual = tuple(float(v) for v in entry["residual_variance"])
        return cls(
            tuple(tuple(float(c) for c in row) for row in entry["covariance"]),
            residual,
            float(entry["absorbed_share"]),
            tuple(float(v) for v in entry.get("gp_share", [1.0] * len(residual))),
        )


@dataclass(frozen=True)
class HeldOutExcess:
    """The cross-validated excess error of each GP (recorded in ``meta.json``).

    Attributes:
        variance: (G,) tau_g^2 [PC-weight units^2] at the largest training load (s = 1).
        z_rms: (G,) RMS of error / GP predictive sd on the left-out rows, before the excess [-].
        folds: number of material folds.
        n_rows: left-out (material, design, frame) rows the excess was fitted on.
        load_reference: |alpha t|_max of the training rows [-] (s = |alpha t| / load_reference).
        material_scale: (shape a, rate b) of the material scale lambda ~ InverseGamma(a, b)
            (:func:`fit_material_scale`), or None (lambda = 1: emulators fitted before it).
        parameter_shift: the error as a parameter shift (:func:`fit_parameter_shift`), or None
            (emulators fitted before it, or on fewer than :data:`SHIFT_MATERIALS` materials).
    """

    variance: tuple[float, ...]
    z_rms: tuple[float, ...]
    folds: int
    n_rows: int
    load_reference: float
    material_scale: tuple[float, float] | None = None
    parameter_shift: ParameterShift | None = None

    def to_json(self) -> dict:
        return {
            "variance": list(self.variance),
            "z_rms": list(self.z_rms),
            "folds": self.folds,
            "n_rows": self.n_rows,
            "load_reference": self.load_reference,
            "material_scale": None if self.material_scale is None else list(self.material_scale),
            "parameter_shift": None if self.parameter_shift is None else self.parameter_shift.to_json(),
        }

    @classmethod
    def from_json(cls, entry: dict) -> HeldOutExcess:
        scale, shift = entry.get("material_scale"), entry.get("parameter_shift")
        return cls(
            tuple(entry["variance"]),
            tuple(entry["z_rms"]),
            entry["folds"],
            entry["n_rows"],
            entry["load_reference"],
            None if scale is None else (float(scale[0]), float(scale[1])),
            None if shift is None else ParameterShift.from_json(shift),
        )

    def load_scale(self, design_inputs: np.ndarray) -> np.ndarray:
        """s (n,) of raw design inputs (alpha11 t, alpha22 t) (n, 2)."""
        return np.linalg.norm(np.asarray(design_inputs, dtype=float), axis=-1) / self.load_reference


def excess_variance(error: np.ndarray, variance: np.ndarray, scale: np.ndarray) -> float:
    """Maximum-likelihood tau^2 >= 0 of error ~ N(0, variance + tau^2 scale^2); all (n,)."""

    def minus_log_likelihood(log_tau2: float) -> float:
        total = variance + np.exp(log_tau2) * scale**2
        return float(np.sum(error**2 / total + np.log(total)))

    at_zero = float(np.sum(error**2 / variance + np.log(variance)))
    upper = np.log(np.mean(error**2 / np.maximum(scale, 1e-3) ** 2)) + 2
    best = minimize_scalar(minus_log_likelihood, bounds=(upper - 40, upper), method="bounded", options={"xatol": 1e-6})
    return float(np.exp(best.x)) if best.fun < at_zero else 0.0


def fit_material_scale(quadratic: np.ndarray, n_values: np.ndarray) -> tuple[float, float]:
    """The spread of the emulator's error between materials: (shape a, rate a - 1) of
    lambda ~ InverseGamma, mean 1.

    Material m's errors e_m (n_m values) are N(0, lambda_m C_m) given its lambda_m; integrating
    lambda_m ~ InverseGamma(a, b) out, the log likelihood of its Mahalanobis form
    q_m = e_m^T C_m^-1 e_m is
    a log b - log Gamma(a) + log Gamma(a + n_m / 2) - (a + n_m / 2) log(b + q_m / 2) + const.
    Both are fitted; the shape a (the spread) is kept and the level set to a mean of 1: the
    cross-validated errors come from GPs fitted on fewer materials than the emulator's, so
    their level (b / a) overstates a fresh material's error, which tau_g^2 is checked against
    (``benchmarks/emulator_error.py``). a is kept in [1.5, 1e4] (a = 1e4: no spread,
    lambda = 1; a = 1.5: as heavy as a Student t with 3 degrees of freedom).

    Args:
        quadratic: (M,) q_m of each material [-]; n_values: (M,) n_m.
    """
    q, n = np.asarray(quadratic, dtype=float), np.asarray(n_values, dtype=float)
    if len(q) < 3 or not np.all(np.isfinite(q)):
        raise ValueError(f"the material scale needs finite errors of >= 3 materials, got {q.tolist()}")

    def minus_log_likelihood(log_ab: np.ndarray) -> float:
        a, b = np.exp(log_ab)
        return -float(np.sum(a * np.log(b) - gammaln(a) + gammaln(a + n / 2) - (a + n / 2) * np.log(b + q / 2)))

    mean = float(np.sum(q) / np.sum(n))
    start = np.log([2.0, 2.0 * mean])
    best = minimize(minus_log_likelihood, start, method="L-BFGS-B", bounds=[(np.log(1.5), np.log(1e4)), (None, None)])
    a = float(np.exp(best.x[0]))
    return a, a - 1


def least_squares_shift(error: np.ndarray, jacobian: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The shift delta (5,) whose J delta best explains the whitened errors e (n,) (J: (n, 5),
    whitened the same way), the covariance (5, 5) of that fit's error, s^2 (J^T J)^+ with s^2 the
    residual's mean square over n - 5, and the share 1 - |e - J delta|^2 / |e|^2 of |e|^2 it absorbs."""
    delta = np.linalg.lstsq(jacobian, error, rcond=None)[0]
    left = error - jacobian @ delta
    fit_error = float(left @ left) / (error.size - 5) * np.linalg.pinv(jacobian.T @ jacobian)
    return delta, fit_error, 1 - float(left @ left) / float(error @ error)


def shift_covariance(shifts: np.ndarray, fit_errors: np.ndarray) -> np.ndarray:
    """C (5, 5): the covariance of a new material's shift predicted from the M materials' fitted
    shifts (M, 5) and their fit errors' covariances (M, 5, 5).

    Their second moment less the fit errors (:func:`shift_second_moment`) times M / (M - 6): a
    second moment S / M of M draws, used for a new draw, has
    E[delta^T (S / M)^-1 delta] = 5 M / (M - 6) (Hotelling's T^2), not 5 -- twice the variance
    for the 12 training materials of ``small`` (needs M >= :data:`SHIFT_MATERIALS`)."""
    m = len(shifts)
    if m < SHIFT_MATERIALS:
        raise ValueError(f"a shift covariance predicted from {m} materials needs >= {SHIFT_MATERIALS}")
    return shift_second_moment(shifts, fit_errors) * m / (m - 6)


def shift_second_moment(shifts: np.ndarray, fit_errors: np.ndarray) -> np.ndarray:
    """(5, 5) mean of delta_m delta_m^T over the fitted shifts (M, 5) less the mean of their fit
    errors' covariances (M, 5, 5) (a fitted shift is the true one plus its fit error; without the
    correction a direction the errors barely inform, a small column of J, gets the fit's noise
    as its C), projected onto the positive semi-definite matrices."""
    raw = shifts.T @ shifts / len(shifts) - fit_errors.mean(0)
    values, vectors = np.linalg.eigh((raw + raw.T) / 2)
    return (vectors * np.clip(values, 0, None)) @ vectors.T


def material_shifts(
    error: np.ndarray, variance: np.ndarray, jacobian: np.ndarray, materials: np.ndarray, scale: np.ndarray, tau2
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each material's shift delta_m: the least-squares fit of J delta to its errors whitened by
    the GP variance plus the held-out excess tau_g^2 s^2.

    Args:
        error, variance: (n, G) held-out errors and GP variances (:func:`cross_validated_errors`).
        jacobian: (n, G, 5) the GP mean's derivative in the five material inputs (unit box).
        materials: (n,) material of each row; scale: (n,) load s; tau2: (G,) held-out excess.

    Returns:
        the shifts (M, 5), their fit errors' covariances (M, 5, 5) and absorbed shares (M,) of
        the M materials, and what the shifts leave of the errors (n, G), scaled by n_m / (n_m - 5)
        for the 5 fitted values.
    """
    sd = np.sqrt(variance + np.asarray(tau2) * scale[:, None] ** 2)
    residual, shifts, fit_errors, absorbed = np.empty_like(error), [], [], []
    for m in np.unique(materials):
        rows = materials == m
        e, jw = (error[rows] / sd[rows]).ravel(), (jacobian[rows] / sd[rows][..., None]).reshape(-1, 5)
        delta, fit_error, share = least_squares_shift(e, jw)
        shifts.append(delta)
        fit_errors.append(fit_error)
        absorbed.append(share)
        residual[rows] = (error[rows] - jacobian[rows] @ delta) * np.sqrt(e.size / (e.size - 5))  # 5 fitted
    return np.array(shifts), np.array(fit_errors), np.array(absorbed), residual


def shift_residual_model(residual: np.ndarray, variance: np.ndarray, scale: np.ndarray) -> tuple[float, float]:
    """Maximum-likelihood (rho, tau^2) of residual ~ N(0, rho variance + tau^2 scale^2), all (n,),
    rho in [1e-3, 1], tau^2 >= 0: what a material's shift leaves of its error, against the GP
    variance and the load-scaled excess.

    The GP's predictive variance v measures the whole of the error of a material it was not
    conditioned on, most of which is the material's parameter shift; the likelihood carries that
    shift as J C J^T, so it carries of v only the share rho that the shift leaves. (On the
    ``small`` emulator what the shifts leave has 6-27 % of v's mean square, and the fit puts it
    almost all in tau^2, growing with the load: rho 0.001-0.016, docs/inference.md.) rho is
    capped at 1: the shift never adds GP variance (an error larger than v goes to tau^2). rho is
    found on a bounded log scale with tau^2 profiled out (:func:`excess_variance` at each rho)."""

    def profile(log_rho: float) -> tuple[float, float]:
        v = np.exp(log_rho) * variance
        tau2 = excess_variance(residual, v, scale)
        total = v + tau2 * scale**2
        return float(np.sum(residual**2 / total + np.log(total))), tau2

    best = minimize_scalar(lambda r: profile(r)[0], bounds=(np.log(1e-3), 0.0), method="bounded")
    return float(np.exp(best.x)), profile(best.x)[1]


def fit_parameter_shift(
    error: np.ndarray, variance: np.ndarray, jacobian: np.ndarray, materials: np.ndarray, scale: np.ndarray, tau2
) -> ParameterShift:
    """The materials' shifts (:func:`material_shifts`, arguments as there); C from the shifts
    less their fit errors (:func:`shift_covariance`); the share of the GP variance and the excess
    of what they leave (:func:`shift_residual_model`, per weight)."""
    shifts, fit_errors, absorbed, residual = material_shifts(error, variance, jacobian, materials, scale, tau2)
    rho, tau2_left = zip(*(shift_residual_model(residual[:, g], variance[:, g], scale) for g in range(error.shape[1])))
    covariance = shift_covariance(shifts, fit_errors)
    return ParameterShift(tuple(map(tuple, covariance.tolist())), tau2_left, float(np.mean(absorbed)), rho)


def material_quadratic_forms(
    error: np.ndarray, variance: np.ndarray, materials: np.ndarray, correlation: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """q_m = sum_g e_mg^T C_mg^-1 e_mg and n_m of every material from its rows at one load.

    Args:
        error: (n, G) errors of the rows; variance: (n, G) their GP variance plus held-out
            excess; materials: (n,) material of each row.
        correlation: (k,) row indices of one material -> (G, k, k) correlation of its excess
            between those rows; the covariance is diag(variance) scaled to it (C = D^1/2 R D^1/2).
    """
    quadratic, counts = [], []
    for m in np.unique(materials):
        rows = np.flatnonzero(materials == m)
        sd = np.sqrt(variance[rows]).T  # (G, k)
        cov = correlation(rows) * sd[:, :, None] * sd[:, None, :]
        resid = error[rows].T[..., None]
        quadratic.append(float(np.sum(resid * np.linalg.solve(cov, resid))))
        counts.append(resid.size)
    return np.array(quadratic), np.array(counts)


def material_folds(materials: np.ndarray, folds: int = FOLDS, seed: int = 0) -> list[np.ndarray]:
    """The seeded split of the distinct ``materials`` (n,) into ``folds`` groups (each a left-out fold)."""
    names = np.random.default_rng(seed).permutation(np.unique(materials))
    if len(names) < folds:
        raise ValueError(f"cross-validation by material needs >= {folds} training materials, got {len(names)}")
    return np.array_split(names, folds)


def cross_validated_errors(
    fit: Callable[[np.ndarray, np.ndarray], GPBank],
    x: np.ndarray,
    weights: np.ndarray,
    materials: np.ndarray,
    gp_subset: np.ndarray,
    folds: int = FOLDS,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Errors and GP variances (n, G) of every row predicted by GPs ``fit`` on the GP rows of
    the other folds' materials (material-wise K-fold cross-validation), and the derivative of
    those predictions in the five material inputs (n, G, 5).

    Args:
        fit: fits a GP bank to unit-box inputs (n, 7) and targets (n, G).
        x: (n, 7) unit-box inputs of every training row; weights: (n, G) their PC weights.
        materials: (n,) material index of each row.
        gp_subset: indices of the rows the emulator's GPs are fitted on.
    """
    error, variance = np.zeros_like(weights), np.zeros_like(weights)
    jacobian = np.zeros((*weights.shape, 5))
    for fold in material_folds(materials, folds, seed):
        keep = gp_subset[~np.isin(materials[gp_subset], fold)]
        fold_bank = fit(x[keep], weights[keep])
        test = np.flatnonzero(np.isin(materials, fold))
        for chunk in np.array_split(test, max(1, len(test) // 500)):
            mean, var, jacobian[chunk] = mean_jacobian(fold_bank, x[chunk])
            error[chunk], variance[chunk] = weights[chunk] - mean, var
    return error, variance, jacobian


def mean_jacobian(bank: GPBank, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GP mean and variance (n, G) at unit inputs x (n, 7) and the mean's derivative in the five
    material inputs (n, G, 5) (each row's mean depends on its own inputs only)."""
    xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    mean, var = bank(xt)
    grads = [torch.autograd.grad(mean[:, g].sum(), xt, retain_graph=True)[0][:, :5] for g in range(mean.shape[1])]
    return mean.detach().numpy(), var.detach().numpy(), torch.stack(grads, 1).numpy()


def cross_validated_excess(
    fit: Callable[[np.ndarray, np.ndarray], GPBank],
    x: np.ndarray,
    weights: np.ndarray,
    materials: np.ndarray,
    design_inputs: np.ndarray,
    gp_subset: np.ndarray,
    scale_rows: np.ndarray,
    correlation: Callable[[np.ndarray], np.ndarray],
    folds: int = FOLDS,
    seed: int = 0,
) -> HeldOutExcess:
    """The held-out excess of the GP fit (:func:`cross_validated_errors`), load-scaled, the
    spread of the material scale (:func:`fit_material_scale`) over the left-out materials and
    their errors as parameter shifts (:func:`fit_parameter_shift`).

    Each fold's GPs are fitted anew, hyper-parameters included (the emulator starts the
    optimizer from its fitted kernels, without restarts): kernels tuned to all materials know
    the left-out ones too, and on the ``small`` data that made the cross-validated error at the
    largest loads half what fresh materials show (``benchmarks/emulator_error.py``).

    Args:
        design_inputs: (n, 2) raw alpha11 t, alpha22 t of each row (the load scale s).
        scale_rows: (n,) bool, the rows the material scale is fitted on (one load fraction,
            e.g. each design's last frame: the rows of one load are what a posterior sees).
        correlation: raw design inputs (k, 2) -> (G, k, k) correlation of a material's error
            between them (:meth:`surrogate.emulator.Emulator.error_correlation`).
        The others as in :func:`cross_validated_errors`.
    """
    error, variance, jacobian = cross_validated_errors(fit, x, weights, materials, gp_subset, folds, seed)
    load = np.linalg.norm(design_inputs, axis=1)
    scale = load / load.max()
    tau2 = np.array([excess_variance(error[:, g], variance[:, g], scale) for g in range(error.shape[1])])
    z_rms = np.sqrt(np.mean(error**2 / variance, axis=0))
    total = variance + tau2 * scale[:, None] ** 2
    picked = np.flatnonzero(scale_rows)
    quadratic, counts = material_quadratic_forms(
        error[picked], total[picked], materials[picked], lambda rows: correlation(design_inputs[picked][rows])
    )
    return HeldOutExcess(
        tuple(tau2.tolist()),
        tuple(z_rms.tolist()),
        folds,
        len(error),
        float(load.max()),
        fit_material_scale(quadratic, counts),
        fit_parameter_shift(error, variance, jacobian, materials, scale, tau2)
        if len(np.unique(materials)) >= SHIFT_MATERIALS
        else None,
    )


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
