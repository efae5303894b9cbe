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
from skinfem.effects import get_effect

STRONG_EVIDENCE = 6.0  # Delta BIC above which a candidate is reported (Kass & Raftery: strong)
MIN_SHARE = 0.5  # ... and it must explain at least this share of the excess residual
ALPHA = 0.01  # posterior-predictive p below which the residual is "structured" (not noise)
NOISE_STRUCTURE_Z = 3.0  # |Moran z| below which a residual has the stated noise's spatial structure
CHI2_TOLERANCE = 1e-3  # a calibration stops once a step lowers chi^2 by less than this


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

    def whiteners(self, xy: np.ndarray, model_sd: np.ndarray | None = None) -> list[np.ndarray]:
        """Symmetric Sigma_c^(-1/2) (m, m) per component c for points xy (m, 2), cached.

        Sigma_c = sd_c^2 R + diag(model_sd[:, c]^2): the correlated noise plus an independent
        model-form error of standard deviation ``model_sd`` (m, 3) (None: no model error).
        """
        key = ("whiten", xy.tobytes(), None if model_sd is None else model_sd.tobytes())
        if key not in self._roots:
            corr = correlation_matrix(xy, self.length, self.nugget)
            if model_sd is None:
                root = inverse_sqrt(corr)
                self._roots[key] = [root / s for s in self.sd]
            else:
                self._roots[key] = [inverse_sqrt(s**2 * corr + np.diag(model_sd[:, c] ** 2))
                                    for c, s in enumerate(self.sd)]
        return self._roots[key]

    def whiten(self, residual: np.ndarray, xy: np.ndarray, masks: np.ndarray,
               model_sd: np.ndarray | None = None) -> np.ndarray:
        """(n_obs, n_pts, 3) residual -> whitened residual (NaN off the mask).

        ``xy`` (n_obs, n_pts, 2) points, ``masks`` (n_obs, n_pts), ``model_sd`` (n_obs, n_pts, 3)
        or None: see :meth:`whiteners`."""
        out = np.full(residual.shape, np.nan)
        for o, mask in enumerate(masks):
            extra = None if model_sd is None else model_sd[o, mask]
            for c, root in enumerate(self.whiteners(xy[o, mask], extra)):
                out[o, mask, c] = root @ residual[o, mask, c]
        return out

    def sample(self, xy: np.ndarray, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """Noise fields (*shape, m, 3) drawn from this model at points xy (m, 2)."""
        key = ("root", xy.tobytes())
        if key not in self._roots:  # eigen-root: also valid for length 0 or nugget 1
            w, v = np.linalg.eigh(correlation_matrix(xy, self.length, self.nugget))
            self._roots[key] = v * np.sqrt(np.maximum(w, 0))
        return noise_fields(self._roots[key], self.sd, shape, rng)


def inverse_sqrt(matrix: np.ndarray) -> np.ndarray:
    """Symmetric inverse square root of a symmetric positive (semi-)definite matrix."""
    w, v = np.linalg.eigh(matrix)
    w = np.maximum(w, 1e-10 * w.max())
    return (v / np.sqrt(w)) @ v.T


def stack(values: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Flatten (n_obs, n_pts, ...) values on the observed points to (n,)."""
    return np.concatenate([values[o, m].ravel() for o, m in enumerate(masks)])


@dataclass
class Data:
    """Measured fields of the observations at their points, with the noise and model-error terms.

    Attributes:
        fields: (n_obs, n_pts, 3) log strain, NaN off the mask (observations zero-padded to the
            largest point count).
        masks: (n_obs, n_pts) True where a point is measured.
        xy: (n_obs, n_pts, 2) points [mm].
        noise: the stated measurement noise.
        model_sd: (n_obs, n_pts, 3) or None: standard deviation of the model's own error at the
            points (discretisation), carried as an independent variance next to the noise.
    """

    fields: np.ndarray
    masks: np.ndarray
    xy: np.ndarray
    noise: NoiseModel
    model_sd: np.ndarray | None = None

    @classmethod
    def from_points(cls, observations: list, noise: NoiseModel) -> "Data":
        """From observations with ``xy`` (n_o, 2) and ``strain`` (n_o, 3) (e.g. measurements)."""
        n = max(len(o.xy) for o in observations)
        fields = np.full((len(observations), n, 3), np.nan)
        xy = np.zeros((len(observations), n, 2))
        masks = np.zeros((len(observations), n), bool)
        for i, o in enumerate(observations):
            fields[i, : len(o.xy)], xy[i, : len(o.xy)], masks[i, : len(o.xy)] = o.strain, o.xy, True
        return cls(fields, masks, xy, noise)

    def with_model_sd(self, model_sd: np.ndarray | None) -> "Data":
        return Data(self.fields, self.masks, self.xy, self.noise, model_sd)

    @property
    def n(self) -> int:
        return int(self.masks.sum()) * 3

    @property
    def total_sd(self) -> np.ndarray:
        """(n_obs, n_pts, 3) per-point sd of noise and model error together."""
        sd = np.broadcast_to(self.noise.sd, self.fields.shape)
        return sd if self.model_sd is None else np.sqrt(sd**2 + self.model_sd**2)

    def standardised(self, model_fields: np.ndarray) -> np.ndarray:
        """(data - model) / total sd per component, NaN off the mask (still spatially correlated)."""
        return (self.fields - model_fields) / self.total_sd

    def whitened_residual(self, model_fields: np.ndarray) -> np.ndarray:
        return self.noise.whiten(self.fields - model_fields, self.xy, self.masks, self.model_sd)

    def whiten(self, fields: np.ndarray) -> np.ndarray:
        """Stacked whitened (n,) of any (n_obs, n_pts, 3) field difference."""
        return stack(self.noise.whiten(fields, self.xy, self.masks, self.model_sd), self.masks)


@dataclass
class Calibration:
    """A calibrated model version: point estimate, Laplace covariance, residuals.

    Attributes:
        names: all parameter names of the forward model; x: (p,) values (fixed ones included).
        free: indices of the calibrated parameters; cov: (k, k) their covariance.
        model_fields: (n_obs, n_pts, 3) fields at x; whitened: whitened residual.
        jac: (n, k) derivative of the stacked whitened *model* with respect to the free
            parameters (physical units).
        rejected: parameter points (p,) where the FE model did not converge (steps rejected).
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
    rejected: list[np.ndarray] = field(default_factory=list)

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


class CalibrationError(RuntimeError):
    """The forward model has no solution at the calibration's starting point."""


class _UnitBoxProblem:
    """Whitened residuals of the free parameters z in the unit box [0, 1]^k (helper of calibrate)."""

    def __init__(self, forward: ForwardModel, data: Data, x0: np.ndarray, free: list[int]):
        self.forward, self.data, self.free = forward, data, free
        self.lo, self.span = forward.bounds[free, 0], np.ptp(forward.bounds[free], axis=1)
        self.base = np.asarray(x0, dtype=float).copy()
        self.rejected: list[np.ndarray] = []
        self.fields: dict[bytes, np.ndarray] = {}  # model fields of evaluated z (no rerun at the end)

    def point(self, z: np.ndarray) -> np.ndarray:
        x = self.base.copy()
        x[self.free] = self.lo + np.clip(z, 0, 1) * self.span
        return x

    def residuals(self, zs: list[np.ndarray]) -> list[np.ndarray | None]:
        """Stacked whitened residuals (n,) at each z; None (and recorded) where FE failed."""
        points = [self.point(z) for z in zs]
        out = []
        for z, x, fields in zip(zs, points, self.forward.evaluate_many(points)):
            if fields is None:
                self.rejected.append(x)
                out.append(None)
            else:
                self.fields[z.tobytes()] = fields
                out.append(stack(self.data.whitened_residual(fields), self.data.masks))
        return out

    def evaluate(self, z: np.ndarray, step: float) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Residual r (n,) and Jacobian d r / d z (n, k) at z: exact in one run when the forward
        model has derivatives, else the Jacobian is left to :meth:`jacobian` (None)."""
        if not self.forward.exact_jacobian:
            return self.residuals([z])[0], None
        x = self.point(z)
        (result,) = self.forward.evaluate_with_jacobian([x], [self.forward.names[i] for i in self.free])
        if result is None:
            self.rejected.append(x)
            return None, None
        fields, derivative = result
        self.fields[z.tobytes()] = fields
        J = np.stack([-self.data.whiten(derivative[..., i]) * s for i, s in enumerate(self.span)], 1)
        return stack(self.data.whitened_residual(fields), self.data.masks), J

    def jacobian(self, z: np.ndarray, r0: np.ndarray, step: float) -> np.ndarray:
        """(n, k) one-sided differences d r / d z; the other side where a run failed (0 if both)."""
        eye = np.eye(len(z))
        h = np.where(z + step <= 1, step, -step)
        columns = self.residuals([z + h[i] * eye[i] for i in range(len(z))])
        retry = [i for i, c in enumerate(columns) if c is None and 0 <= z[i] - h[i] <= 1]
        h[retry] *= -1
        for i, c in zip(retry, self.residuals([z + h[i] * eye[i] for i in retry])):
            columns[i] = c
        return np.stack([np.zeros_like(r0) if c is None else (c - r0) / h[i] for i, c in enumerate(columns)], 1)


def calibrate(forward: ForwardModel, data: Data, x0: np.ndarray, free: list[int], label: str = "baseline",
              max_iterations: int = 12, step: float = 1e-3) -> Calibration:
    """Least-squares fit of the free parameters (within their prior box) to the whitened data.

    Levenberg–Marquardt in the unit box of the prior (steps projected onto the box). A trial
    point where the FE model does not converge is a rejected step: the damping grows (the
    step shrinks), the point is recorded in ``Calibration.rejected`` and the fit continues.
    Jacobians are exact when the forward model has derivatives (forward sensitivities: one
    run per trial point), else forward differences of ``step`` in the unit box (one run per
    free parameter, spread over MPI ranks by the forward model). The fit stops once a step
    lowers chi^2 by less than ``CHI2_TOLERANCE`` or after ``max_iterations`` trial steps.
    Returns the Laplace posterior at the optimum.

    Raises:
        CalibrationError: the model does not converge at the starting point.
    """
    start, runs0 = time.perf_counter(), forward.runs
    problem = _UnitBoxProblem(forward, data, x0, free)
    z = np.clip((problem.base[free] - problem.lo) / problem.span, 0, 1)
    r, J = problem.evaluate(z, step)
    if r is None:
        raise CalibrationError(f"the FE model does not converge at the starting point {problem.point(z)}")
    J, damping = problem.jacobian(z, r, step) if J is None else J, 1e-3
    for _ in range(max_iterations):
        A, g = J.T @ J, J.T @ r
        dz = np.linalg.solve(A + damping * np.diag(np.diag(A) + 1e-12 * np.trace(A)), -g)
        z_new = np.clip(z + dz, 0, 1)
        if np.max(np.abs(z_new - z)) < 1e-8:
            break
        r_new, J_new = problem.evaluate(z_new, step)
        if r_new is None or r_new @ r_new >= r @ r:  # failed run or no decrease: a shorter step
            damping *= 10 if r_new is None else 4
            continue
        decrease = r @ r - r_new @ r_new
        z, r, damping = z_new, r_new, damping / 3
        if J_new is not None:
            J = J_new
        if decrease < CHI2_TOLERANCE:  # chi^2 no longer moves by a statistically visible amount
            break
        if J_new is None:
            J = problem.jacobian(z, r, step)
    x = problem.point(z)
    cov = np.linalg.pinv(J.T @ J, rcond=1e-12) * np.outer(problem.span, problem.span)
    fields = problem.fields[z.tobytes()]
    return Calibration(
        names=list(forward.names), x=x, free=list(free), cov=cov, model_fields=fields,
        whitened=data.whitened_residual(fields), jac=-J / problem.span, fe_runs=forward.runs - runs0,
        seconds=time.perf_counter() - start, label=label, rejected=problem.rejected,
    )


# -- metrics ---------------------------------------------------------------------------------
def neighbour_weights(xy: np.ndarray, k: int = 8) -> sparse.csr_matrix:
    """Symmetric binary k-nearest-neighbour weights (n, n) on points (n, 2)."""
    k = min(k, len(xy) - 1)
    _, idx = cKDTree(xy).query(xy, k + 1)
    rows = np.repeat(np.arange(len(xy)), k)
    w = sparse.csr_matrix((np.ones(rows.size), (rows, idx[:, 1:].ravel())), shape=(len(xy),) * 2)
    return ((w + w.T) > 0).astype(float)


def morans_i_statistic(values: np.ndarray, masks: np.ndarray, weights: list[sparse.csr_matrix]) -> float:
    """Moran's I of (n_obs, n_pts, 3) values, pooled over observations and components.

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

    The noise itself is spatially correlated, so the null is simulated: I of ``n_sim`` fields
    drawn from the stated noise model plus the model-error term. z = (I - mean_null) / sd_null; p is the
    Monte-Carlo p-value for more positive autocorrelation (structure) than noise gives.
    """
    weights = [neighbour_weights(data.xy[o, m]) for o, m in enumerate(data.masks)]
    stat = morans_i_statistic(standardised, data.masks, weights)
    rng = np.random.default_rng(seed)
    null_fields = np.zeros((n_sim, *data.fields.shape))
    for o, m in enumerate(data.masks):
        draw = data.noise.sample(data.xy[o, m], (n_sim,), rng)
        if data.model_sd is not None:
            draw += data.model_sd[o, m] * rng.standard_normal(draw.shape)
        null_fields[:, o, m] = draw / data.total_sd[o, m]
    null = np.array([morans_i_statistic(f, data.masks, weights) for f in null_fields])
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
    """Points (n, 2) [mm] of each named region around a membrane |x|, |y| <= half [mm].

    ``band`` [mm] is the half-width of the edge strip; the far field (beyond the strip) is
    split by the angle between a point's position and the fiber direction theta.
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
    """Regions ranked by RMS standardised residual (data - model)/sd [sigma]; noise alone gives ~1.

    The sd is the total one (noise and model error); points of every observation are pooled."""
    theta = float(cal.x[4])
    squares = np.nanmean(data.standardised(cal.model_fields) ** 2, axis=2)  # (n_obs, n_pts)
    sums: dict[str, list[float]] = {}
    for o, m in enumerate(data.masks):
        for name, inside in region_masks(data.xy[o], half, theta, band).items():
            sel = inside & m
            total = sums.setdefault(name, [0.0, 0])
            total[0] += float(squares[o, sel].sum())
            total[1] += int(sel.sum())
    out = [{"region": name, "points": n, "rms_sigma": math.sqrt(ss / n)} for name, (ss, n) in sums.items() if n]
    return sorted(out, key=lambda r: -r["rms_sigma"])


@dataclass
class NoiseStatement:
    """Whether the stated noise sd is consistent with the residual (:func:`check_noise_statement`)."""

    consistent: bool
    factor: float  # estimated sd / stated sd (1 when consistent)
    moran_z: float
    chi2_per_dof: float

    def summary(self, stated: np.ndarray) -> str:
        if self.consistent:
            return ""
        estimated = ", ".join(f"{v:.2g}" for v in self.factor * stated)
        return (f"The stated noise is inconsistent with the residual: it is {self.factor:.1f}x larger than stated "
                f"(chi^2/dof = {self.chi2_per_dof:.2f}) but has the stated noise's spatial structure (Moran's I "
                f"z = {self.moran_z:.1f}); the check continues with the estimated sd {estimated} (xx, yy, xy) "
                "instead of looking for a missing effect in it (give --noise-sd to state it).")


def check_noise_statement(forward: ForwardModel, cal: Calibration, data: Data,
                          max_iterations: int = 6) -> tuple[Calibration, Data, NoiseStatement]:
    """Is a structured residual only noise larger than stated?

    Moran's I does not depend on the residual's scale: a residual that is larger than the
    stated noise (PPC p < ALPHA) but whose spatial autocorrelation is that of the stated noise
    model (|z| < NOISE_STRUCTURE_Z) is read as understated noise, not as missing physics
    (missing effects are smooth fields: large z). The noise sd is then scaled by
    sqrt(chi^2/dof) and the calibration repeated with it.
    """
    metrics = residual_metrics(cal, data)
    statement = NoiseStatement(True, 1.0, metrics["moran_z"], metrics["chi2_per_dof"])
    if not metrics["structured"] or abs(metrics["moran_z"]) >= NOISE_STRUCTURE_Z:
        return cal, data, statement
    statement.consistent, statement.factor = False, math.sqrt(metrics["chi2_per_dof"])
    noise = NoiseModel(data.noise.sd * statement.factor, data.noise.length, data.noise.nugget)
    data = Data(data.fields, data.masks, data.xy, noise, data.model_sd)
    return calibrate(forward, data, cal.x, cal.free, cal.label, max_iterations), data, statement


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
    """Whitened signatures (n, dim phi) of each effect: derivatives of the model at ``cal.x``.

    Exact (forward sensitivities, one run) when the forward model has derivatives. Otherwise
    each parameter is moved ``rel_step`` of its prior range both ways, clipped to the range
    (a null value on a bound gives a one-sided difference); a side whose FE run failed is
    replaced by the calibrated point itself; if both fail the column is zero.
    """
    if forward.exact_jacobian:
        names = [q for name in effects for q in get_effect(name).qualified_names()]
        (result,) = forward.evaluate_with_jacobian([cal.x], names)
        if result is not None:
            columns = iter(data.whiten(result[1][..., i]) for i in range(len(names)))
            return {name: np.stack([next(columns) for _ in get_effect(name).parameters], 1) for name in effects}
    jobs = []  # (effect, parameter index, low value, high value)
    for name in effects:
        for i in forward.index(get_effect(name).qualified_names()):
            h = rel_step * np.ptp(forward.bounds[i])
            jobs.append((name, i, max(cal.x[i] - h, forward.bounds[i, 0]), min(cal.x[i] + h, forward.bounds[i, 1])))
    points = []
    for _, i, low, high in jobs:
        for value in (low, high):
            x = cal.x.copy()
            x[i] = value
            points.append(x)
    fields = forward.evaluate_many(points)
    columns: dict[str, list] = {name: [] for name in effects}
    for (name, i, low, high), f_low, f_high in zip(jobs, fields[::2], fields[1::2]):
        if f_low is None:
            f_low, low = cal.model_fields, cal.x[i]
        if f_high is None:
            f_high, high = cal.model_fields, cal.x[i]
        column = data.whiten(f_high - f_low) / (high - low) if high > low else np.zeros(data.n)
        columns[name].append(column)
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
             confirm: int = 2, mesh_resolved: bool = True, **fit_kwargs) -> Diagnosis:
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
    text = verdict(metrics, scores, regions, mesh_resolved)
    return Diagnosis(metrics, regions, scores, fits, text, forward.runs - runs0,
                     time.perf_counter() - start)


def verdict(metrics: dict, scores: list[CandidateScore], regions: list[dict], mesh_resolved: bool = True) -> str:
    """One paragraph: is the residual noise, where is it not, which candidate explains it.

    ``mesh_resolved`` False (the model's discretisation error exceeds the noise) turns "something
    outside the registry is missing" into "rerun on a finer mesh first"."""
    if not metrics["structured"]:
        return (f"The residual is consistent with the stated noise (chi^2/dof = {metrics['chi2_per_dof']:.2f}, "
                f"posterior-predictive p = {metrics['ppc_p']:.2f}, Moran's I z = {metrics['moran_z']:.1f}): "
                "no missing effect is needed.")
    worst = regions[0]
    text = (f"The residual is structured (chi^2/dof = {metrics['chi2_per_dof']:.2f}, posterior-predictive "
            f"p = {metrics['ppc_p']:.3f}, Moran's I z = {metrics['moran_z']:.1f}); it is largest at the "
            f"{worst['region']} ({worst['rms_sigma']:.1f} sigma RMS; noise and carried model error alone give 1).")
    best = next((s for s in scores if s.explains), None)
    if best is None:
        lead = f" The best candidate, {scores[0].summary()}, is not enough." if scores else ""
        if not mesh_resolved:
            return (text + " No candidate explains the residual." + lead + " The check's own discretisation error "
                    "exceeds the noise, so this structure may be the mesh's: rerun on a finer mesh before concluding "
                    "that something outside the registry is missing.")
        return text + " No candidate explains the residual." + lead + " Something outside the registry is missing."
    text += f" Most likely missing: {best.summary()}."
    effect = get_effect(best.effect)
    text += " Estimated " + effect.describe({q.split(".", 1)[1]: v for q, v in best.estimate.items()})
    if best.confounding > 0.8:
        text += (" It is strongly confounded with the skin parameters: more load frames or membrane designs "
                 "would separate them.")
    return text + f" Add it with --add {best.effect}."
