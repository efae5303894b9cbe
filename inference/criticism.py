"""Model criticism: compare the calibrated model with measurements, locate and explain misfit.

The steps (``skinid check``, README "Model criticism"):

1. **Calibrate** (:func:`calibrate`): Gauss–Newton (trust-region least squares in the unit
   box of the prior) of the forward model to the whitened measurements, started from the
   emulator's posterior mode; the posterior is the Laplace approximation at the optimum
   (the priors are uniform, so it is the likelihood's Gaussian). Criticism runs on the FE
   model itself: an emulator's own error would otherwise pose as missing physics.
2. **Compare** (:func:`residual_metrics`): RMSE in strain units, chi^2/dof against the stated
   noise, a posterior-predictive p-value (below 0.01: the residual is "structured", not
   noise), and Moran's I of residual / sd against its distribution under the correlated
   noise model (spatial structure beyond the noise's own).
3. **Where** (:func:`rank_regions`): RMS standardised residual under the membrane, on its
   edges and corners, and in the far field along / across the fibers.
4. **Which effect** (:func:`diagnose`): each candidate effect's signature d field / d phi
   (central differences at the calibrated point, null effect values), whitened, with what
   re-tuning the skin parameters could absorb projected out; the efficient score statistic
   T (chi^2 with dim(phi) degrees of freedom under "no effect"), the share of the excess
   residual it explains, its confounding with the skin parameters and Delta BIC =
   T - dim(phi) ln n (> 0 favours the effect; > 6 is strong evidence).
5. **Add** (:func:`calibrate` with the effect's parameters free) and compare versions.

Noise model: independent strain components with the stated standard deviations sd_c and a
spatial correlation (1 - w) RBF(l) + w I between cells (:func:`inference.noise.correlation_matrix`).
Whitening uses the symmetric inverse square root of the correlation, so whitened values stay
attached to their cells.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse, stats
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from inference.forward import ForwardModel
from inference.noise import correlation_matrix, noise_fields
from inference.observations import Observation
from skinfem.effects import get_effect, principal_prestretch

STRONG_EVIDENCE = 6.0  # Delta BIC above which a candidate is reported (Kass & Raftery: strong)
MIN_SHARE = 0.5  # ... and it must explain at least this share of the excess residual
ALPHA = 0.01  # posterior-predictive p below which the residual is "structured" (not noise)


@dataclass
class NoiseModel:
    """Stated measurement noise: sd (3,) per strain component, correlation length [mm], nugget."""

    sd: np.ndarray
    length: float = 0.0
    nugget: float = 1.0
    _roots: dict = field(default_factory=dict, repr=False)  # cached matrix (inverse) square roots

    def __post_init__(self):
        self.sd = np.asarray(self.sd, dtype=float)
        if self.sd.shape != (3,) or not np.all(self.sd > 0):
            raise ValueError(f"noise sd must be three positive numbers (xx, yy, xy), got {self.sd}")
        correlation_matrix(np.zeros((1, 2)), self.length, self.nugget)  # validates both

    def whitener(self, xy: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Symmetric R^(-1/2) (m, m) on the masked cells (cached per mask)."""
        key = ("whitener", xy.tobytes(), mask.tobytes())
        if key not in self._roots:
            corr = correlation_matrix(xy[mask], self.length, self.nugget)
            w, v = np.linalg.eigh(corr)
            w = np.maximum(w, 1e-10 * w.max())
            self._roots[key] = (v / np.sqrt(w)) @ v.T
        return self._roots[key]

    def whiten(self, residual: np.ndarray, xy: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """(n_obs, n_cells, 3) residual -> standardised residual (NaN off the mask)."""
        out = np.full_like(residual, np.nan)
        for o, mask in enumerate(masks):
            out[o, mask] = self.whitener(xy, mask) @ (residual[o, mask] / self.sd)
        return out

    def sample(self, xy: np.ndarray, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """Noise fields (*shape, n_cells, 3) drawn from this model."""
        key = ("root", xy.tobytes())
        if key not in self._roots:  # eigen-root: also valid for length 0 or nugget 1
            w, v = np.linalg.eigh(correlation_matrix(xy, self.length, self.nugget))
            self._roots[key] = v * np.sqrt(np.maximum(w, 0))
        return noise_fields(self._roots[key], self.sd, shape, rng)


def stack(values: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Flatten (n_obs, n_cells, ...) values on the observed cells to (n,)."""
    return np.concatenate([values[o, m].ravel() for o, m in enumerate(masks)])


@dataclass
class Data:
    """Measured fields of the observations with their masks and noise model."""

    fields: np.ndarray  # (n_obs, n_cells, 3), NaN off the mask
    masks: np.ndarray  # (n_obs, n_cells) bool
    xy: np.ndarray  # (n_cells, 2) [mm]
    noise: NoiseModel

    @classmethod
    def from_observations(cls, observations: list[Observation], xy: np.ndarray, noise: NoiseModel) -> "Data":
        return cls(np.stack([o.fields for o in observations]), np.stack([o.mask for o in observations]),
                   np.asarray(xy), noise)

    @property
    def n(self) -> int:
        return int(self.masks.sum()) * 3

    def standardised(self, model_fields: np.ndarray) -> np.ndarray:
        """(data - model) / sd per component, NaN off the mask (still spatially correlated)."""
        return (self.fields - model_fields) / self.noise.sd

    def whitened_residual(self, model_fields: np.ndarray) -> np.ndarray:
        return self.noise.whiten(self.fields - model_fields, self.xy, self.masks)


@dataclass
class Calibration:
    """A calibrated model version: point estimate, Laplace covariance, residuals.

    Attributes:
        names: all parameter names of the forward model; x: (p,) values (fixed ones included).
        free: indices of the calibrated parameters; cov: (k, k) their covariance.
        model_fields: (n_obs, n_cells, 3) fields at x; whitened: standardised residual.
        jac: (n, k) derivative of the stacked standardised *model* with respect to the free
            parameters (physical units).
    """

    names: list[str]
    x: np.ndarray
    free: list[int]
    cov: np.ndarray
    model_fields: np.ndarray
    whitened: np.ndarray
    jac: np.ndarray
    fe_runs: int
    seconds: float
    label: str = "baseline"

    @property
    def free_names(self) -> list[str]:
        return [self.names[i] for i in self.free]

    @property
    def chi2(self) -> float:
        """Sum of squares of the whitened residual."""
        return float(np.nansum(self.whitened**2))

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    def estimates(self) -> dict[str, dict[str, float]]:
        sd = dict(zip(self.free_names, self.sd))
        return {n: {"value": float(self.x[i]), "sd": float(sd.get(n, 0.0))} for i, n in enumerate(self.names)
                if i in self.free}


def calibrate(forward: ForwardModel, data: Data, x0: np.ndarray, free: list[int], label: str = "baseline",
              max_iterations: int = 12, step: float = 1e-3) -> Calibration:
    """Least-squares fit of the free parameters (within their prior box) to the whitened data.

    Jacobians are forward differences of ``step`` in the unit box (one run per free
    parameter, spread over MPI ranks by the forward model). Returns the Laplace posterior.
    """
    start, runs0 = time.perf_counter(), forward.runs
    lo, span = forward.bounds[free, 0], np.ptp(forward.bounds[free], axis=1)
    base = np.asarray(x0, dtype=float).copy()

    def point(z):
        x = base.copy()
        x[free] = lo + np.clip(z, 0, 1) * span
        return x

    def residual(fields):
        return stack(data.whitened_residual(fields), data.masks)

    def fun(z):
        return residual(forward(point(z)))

    def jac(z):
        h = np.where(z + step <= 1, step, -step)
        pts = [point(z)] + [point(z + h[i] * np.eye(len(z))[i]) for i in range(len(z))]
        fields = forward.evaluate_many(pts)
        r0 = residual(fields[0])
        return np.stack([(residual(f) - r0) / h[i] for i, f in enumerate(fields[1:])], 1)

    z0 = np.clip((base[free] - lo) / span, 0, 1)
    fit = least_squares(fun, z0, jac=jac, bounds=(0, 1), method="trf", x_scale=1.0,
                        max_nfev=max_iterations, xtol=1e-8, ftol=1e-10)
    x = point(fit.x)
    J_unit = fit.jac  # d residual / dz at the optimum
    jac_phys = -J_unit / span  # d model / dx (the residual is data - model)
    info = J_unit.T @ J_unit
    cov_unit = np.linalg.pinv(info, rcond=1e-12)
    cov = cov_unit * np.outer(span, span)
    fields = forward(x)
    return Calibration(
        names=list(forward.names), x=x, free=list(free), cov=cov, model_fields=fields,
        whitened=data.whitened_residual(fields), jac=jac_phys, fe_runs=forward.runs - runs0,
        seconds=time.perf_counter() - start, label=label,
    )


# -- metrics ---------------------------------------------------------------------------------
def neighbour_weights(xy: np.ndarray, k: int = 8) -> sparse.csr_matrix:
    """Symmetric binary k-nearest-neighbour weights (n, n) on cell centroids."""
    k = min(k, len(xy) - 1)
    _, idx = cKDTree(xy).query(xy, k + 1)
    rows = np.repeat(np.arange(len(xy)), k)
    w = sparse.csr_matrix((np.ones(rows.size), (rows, idx[:, 1:].ravel())), shape=(len(xy),) * 2)
    return ((w + w.T) > 0).astype(float)


def morans_i_statistic(values: np.ndarray, masks: np.ndarray, weights: list[sparse.csr_matrix]) -> float:
    """Moran's I of (n_obs, n_cells, 3) values, pooled over observations and components.

    Each (observation, component) map is one block of a block-diagonal k-NN weight matrix.
    """
    num = den = s0 = 0.0
    n = 0
    for o, mask in enumerate(masks):
        w = weights[o]
        for c in range(values.shape[-1]):
            z = values[o, mask, c] - values[o, mask, c].mean()
            num += z @ (w @ z)
            den += z @ z
            s0 += w.sum()
            n += len(z)
    return n / s0 * num / den


def morans_i(standardised: np.ndarray, data: "Data", n_sim: int = 400, seed: int = 0) -> dict[str, float]:
    """Moran's I of the standardised residual and its null distribution under the noise model.

    The noise itself is spatially correlated, so the null is simulated: I of ``n_sim`` noise
    fields drawn from the stated noise model. z = (I - mean_null) / sd_null; p is the
    Monte-Carlo p-value for more positive autocorrelation (structure) than noise gives.
    """
    weights = [neighbour_weights(data.xy[m]) for m in data.masks]
    stat = morans_i_statistic(standardised, data.masks, weights)
    rng = np.random.default_rng(seed)
    noise = data.noise.sample(data.xy, (n_sim, len(data.masks)), rng) / data.noise.sd
    null = np.array([morans_i_statistic(f, data.masks, weights) for f in noise])
    z = (stat - null.mean()) / null.std()
    return {"I": float(stat), "z": float(z), "p": float((1 + np.sum(null >= stat)) / (n_sim + 1))}


def residual_metrics(cal: Calibration, data: Data, n_draws: int = 4000, seed: int = 0) -> dict:
    """RMSE [strain], chi^2/dof, posterior-predictive p-value, Moran's I and the verdict.

    The posterior-predictive check uses the realised discrepancy T(y, x) = |whitened residual|^2:
    draws x_s from the Laplace posterior, replicated data from the model linearised at the
    optimum plus noise; p = P(T(y_rep, x_s) >= T(y, x_s)).
    """
    residual = data.fields - cal.model_fields
    r = stack(residual, data.masks).reshape(-1, 3)
    r_tilde = stack(cal.whitened, data.masks)
    n, k = r_tilde.size, len(cal.free)
    chi2 = float(r_tilde @ r_tilde)
    rng = np.random.default_rng(seed)
    delta = rng.multivariate_normal(np.zeros(k), cal.cov, size=n_draws, method="svd")
    shift = delta @ cal.jac.T  # (draws, n): model change of each draw
    t_obs = chi2 - 2 * shift @ r_tilde + np.sum(shift**2, axis=1)
    t_rep = stats.chi2.rvs(n, size=n_draws, random_state=rng)
    moran = morans_i(data.standardised(cal.model_fields), data, seed=seed)
    ppc_p = float(np.mean(t_rep >= t_obs))
    structured = ppc_p < ALPHA
    return {
        "rmse": float(np.sqrt(np.mean(r**2))),
        "rmse_by_component": {c: float(np.sqrt(np.mean(r[:, i] ** 2))) for i, c in enumerate(("xx", "yy", "xy"))},
        "noise_rms": float(np.sqrt(np.mean(data.noise.sd**2))),
        "chi2": chi2,
        "dof": n - k,
        "chi2_per_dof": chi2 / (n - k),
        "ppc_p": ppc_p,
        "moran_I": moran["I"],
        "moran_z": moran["z"],
        "moran_p": moran["p"],
        "bic": chi2 + k * math.log(n),
        "n_data": n,
        "n_params": k,
        "structured": bool(structured),
    }


def region_masks(xy: np.ndarray, half: float, theta_deg: float, band: float) -> dict[str, np.ndarray]:
    """Cells of each named region around a membrane |x|, |y| <= half [mm].

    ``band`` [mm] is the half-width of the edge strip; the far field (beyond the strip) is
    split by the angle between a cell's position and the fiber direction theta.
    """
    ax, ay = np.abs(xy[:, 0]), np.abs(xy[:, 1])
    ring = np.maximum(ax, ay)
    corner = (np.abs(ax - half) <= band) & (np.abs(ay - half) <= band)
    edge = (np.abs(ring - half) <= band) & ~corner
    far = ring > half + band
    angle = np.degrees(np.abs(np.arctan2(xy[:, 1], xy[:, 0]) - math.radians(theta_deg))) % 180
    off = np.minimum(angle, 180 - angle)
    return {
        "under the membrane": ring < half - band,
        "membrane edges": edge,
        "membrane corners": corner,
        "far field along the fibers": far & (off <= 30),
        "far field across the fibers": far & (off >= 60),
        "far field, oblique to the fibers": far & (off > 30) & (off < 60),
    }


def rank_regions(cal: Calibration, data: Data, half: float, band: float) -> list[dict]:
    """Regions ranked by RMS standardised residual (data - model)/sd [sigma]; noise alone gives ~1."""
    theta = float(cal.x[4])
    per_cell = np.nanmean(data.standardised(cal.model_fields) ** 2, axis=(0, 2))  # (n_cells,)
    out = []
    for name, mask in region_masks(data.xy, half, theta, band).items():
        if mask.any():
            out.append({"region": name, "cells": int(mask.sum()),
                        "rms_sigma": float(np.sqrt(np.nanmean(per_cell[mask])))})
    return sorted(out, key=lambda r: -r["rms_sigma"])


# -- diagnosis -------------------------------------------------------------------------------
@dataclass
class CandidateScore:
    """How well one candidate effect explains the residual of a calibrated model.

    The *score* fields come from the linearised test at the null effect (cheap, all
    candidates); the *fit* fields from actually calibrating the model with the effect added
    (the strongest candidates only), which also holds when the effect is too large for the
    linearisation. ``share_explained`` is the share of the excess residual chi^2 (above its
    noise expectation) that the effect removes; ``explains`` needs strong evidence and at
    least half of the excess.
    """

    effect: str
    description: str
    parameters: list[str]
    statistic: float  # efficient score T, chi^2_dof under "no effect"
    dof: int
    p_value: float
    delta_bic: float  # T - dof ln n: > 0 favours the effect
    share_explained: float
    confounding: float  # share of the fitted signature that skin-parameter re-tuning absorbs
    estimate: dict[str, float]  # one-step (linear) estimate of the effect's parameters
    fitted: bool = False  # delta_bic, share_explained, estimate come from a calibration
    explains: bool = False

    def summary(self) -> str:
        est = ", ".join(f"{k.split('.')[-1]} = {v:.3g}" for k, v in self.estimate.items())
        how = "fitted" if self.fitted else "linearised"
        return (f"{self.effect} (Delta BIC = {self.delta_bic:+.1f}, explains {self.share_explained:.0%} of the "
                f"excess residual, {self.confounding:.0%} confounded with the skin parameters; {how} estimate {est})")


def signatures(forward: ForwardModel, cal: Calibration, data: Data, effects: list[str],
               rel_step: float = 0.02) -> dict[str, np.ndarray]:
    """Whitened signatures (n, dim phi) of each effect: central differences of the model."""
    jobs = []
    for name in effects:
        for q in get_effect(name).qualified_names():
            i = forward.names.index(q)
            h = rel_step * np.ptp(forward.bounds[i])
            for sign in (1, -1):
                x = cal.x.copy()
                x[i] += sign * h
                jobs.append((name, h, x))
    fields = forward.evaluate_many([job[-1] for job in jobs])
    columns: dict[str, list] = {name: [] for name in effects}
    for (name, h, _), f_plus, f_minus in zip(jobs[::2], fields[::2], fields[1::2]):
        diff = stack(data.noise.whiten(f_plus - f_minus, data.xy, data.masks), data.masks) / (2 * h)
        columns[name].append(diff)
    return {name: np.stack(cols, 1) for name, cols in columns.items()}


def excess_chi2(cal: Calibration, data: Data) -> float:
    """chi^2 of the residual above its expectation under noise alone (n - k)."""
    return cal.chi2 - (data.n - len(cal.free))


def score_candidates(cal: Calibration, data: Data, sigs: dict[str, np.ndarray]) -> list[CandidateScore]:
    """Linearised score test, share explained, confounding and Delta BIC of each candidate."""
    r = stack(cal.whitened, data.masks)
    n = r.size
    q, _ = np.linalg.qr(cal.jac)  # what re-tuning the calibrated parameters can absorb
    excess = excess_chi2(cal, data)
    out = []
    for name, S in sigs.items():
        S_perp = S - q @ (q.T @ S)
        beta, *_ = np.linalg.lstsq(S_perp, r, rcond=None)
        fitted = S_perp @ beta
        T = float(fitted @ fitted)
        raw = S @ beta
        dof = S.shape[1]
        cls = get_effect(name)
        out.append(CandidateScore(
            effect=name, description=cls.description, parameters=cls.qualified_names(), statistic=T, dof=dof,
            p_value=float(stats.chi2.sf(T, dof)), delta_bic=T - dof * math.log(n),
            share_explained=float(np.clip((T - dof) / excess, 0, 1)) if excess > 0 else 0.0,
            confounding=float(np.clip(1 - T / float(raw @ raw), 0, 1)) if raw @ raw > 0 else 1.0,
            estimate={qn: float(b) for qn, b in zip(cls.qualified_names(), beta)},
        ))
    return sorted(out, key=lambda s: -s.delta_bic)


def extend(forward: ForwardModel, cal: Calibration, data: Data, effect: str, **kwargs) -> Calibration:
    """Calibrate ``cal``'s model with ``effect``'s parameters freed (started at their null)."""
    added = forward.index(get_effect(effect).qualified_names())
    x0 = cal.x.copy()
    x0[added] = forward.null[added]
    return calibrate(forward, data, x0, cal.free + added, label=f"{cal.label} + {effect}", **kwargs)


@dataclass
class Diagnosis:
    metrics: dict
    regions: list[dict]
    scores: list[CandidateScore]
    fits: dict[str, Calibration]
    text: str
    fe_runs: int
    seconds: float

    @property
    def best(self) -> CandidateScore | None:
        return next((s for s in self.scores if s.explains), None)


def diagnose(forward: ForwardModel, cal: Calibration, data: Data, effects: list[str], half: float, band: float,
             confirm: int = 2, **fit_kwargs) -> Diagnosis:
    """Compare, locate and explain: metrics, regions, candidate ranking and the verdict.

    If the residual is structured, the ``confirm`` best candidates by linearised Delta BIC
    (only those with strong evidence) are calibrated for real, and their fitted Delta BIC and
    share of the excess residual replace the linearised ones.
    """
    start, runs0 = time.perf_counter(), forward.runs
    metrics = residual_metrics(cal, data)
    regions = rank_regions(cal, data, half, band)
    scores = score_candidates(cal, data, signatures(forward, cal, data, effects))
    fits: dict[str, Calibration] = {}
    if metrics["structured"]:
        excess, n = excess_chi2(cal, data), metrics["n_data"]
        for s in [s for s in scores if s.delta_bic > STRONG_EVIDENCE][:confirm]:
            fit = fits[s.effect] = extend(forward, cal, data, s.effect, **fit_kwargs)
            drop = cal.chi2 - fit.chi2
            s.delta_bic = drop - s.dof * math.log(n)
            s.share_explained = float(np.clip((drop - s.dof) / excess, 0, 1)) if excess > 0 else 0.0
            s.estimate = {q: float(fit.x[forward.names.index(q)]) for q in s.parameters}
            s.fitted = True
        scores.sort(key=lambda s: -s.delta_bic)
    for s in scores:
        s.explains = metrics["structured"] and s.delta_bic > STRONG_EVIDENCE and s.share_explained >= MIN_SHARE
    return Diagnosis(metrics, regions, scores, fits, verdict(metrics, scores, regions), forward.runs - runs0,
                     time.perf_counter() - start)


def verdict(metrics: dict, scores: list[CandidateScore], regions: list[dict]) -> str:
    """One paragraph: is the residual noise, where is it not, which candidate explains it."""
    if not metrics["structured"]:
        return (f"The residual is consistent with the stated noise (chi^2/dof = {metrics['chi2_per_dof']:.2f}, "
                f"posterior-predictive p = {metrics['ppc_p']:.2f}, Moran's I z = {metrics['moran_z']:.1f}): "
                "no missing effect is needed.")
    worst = regions[0]
    text = (f"The residual is structured (chi^2/dof = {metrics['chi2_per_dof']:.2f}, posterior-predictive "
            f"p = {metrics['ppc_p']:.3f}, Moran's I z = {metrics['moran_z']:.1f}); it is largest at the "
            f"{worst['region']} ({worst['rms_sigma']:.1f} sigma RMS; noise alone gives 1).")
    best = next((s for s in scores if s.explains), None)
    if best is None:
        lead = f" The best candidate, {scores[0].summary()}, is not enough." if scores else ""
        return text + " No candidate explains the residual." + lead + " Something outside the registry is missing."
    text += f" Most likely missing: {best.summary()}."
    if best.effect == "pre_stretch":
        l1, l2, ang = principal_prestretch(*best.estimate.values())
        text += f" Estimated pre-stretch {l1:.3f} x {l2:.3f}, major axis at {ang:.0f} deg."
    if best.confounding > 0.8:
        text += (" It is strongly confounded with the skin parameters: more load frames or membrane designs "
                 "would separate them.")
    return text + f" Add it with --add {best.effect}."
