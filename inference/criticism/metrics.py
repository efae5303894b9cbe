"""Is the residual noise? And where is it not: fit metrics, Moran's I and regions."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse, stats
from scipy.spatial import cKDTree

from inference.criticism.calibration import Calibration
from inference.criticism.data import Data, stack
from skinfem.config import THETA
from skinfem.io import COMPONENTS

ALPHA = 0.01  # posterior-predictive p below which the residual is "structured" (not noise)
HOTSPOT_POINTS = 9  # the residual's peak is located over this many nearest measured points


@dataclass(frozen=True)
class MoranI:
    """Moran's I of a residual, its z against the noise model's null and the Monte-Carlo p."""

    I: float  # noqa: E741  (the statistic's name)
    z: float
    p: float


@dataclass(frozen=True)
class ResidualMetrics:
    """How far a calibrated model is from the measurements (:func:`residual_metrics`).

    Strain quantities are log strain [-]; chi^2 is of the whitened residual (noise and carried
    model error); ``structured``: posterior-predictive p below ALPHA (not noise)."""

    rmse: float
    rmse_by_component: dict[str, float]  # "xx", "yy", "xy"
    noise_rms: float  # RMS of the noise sd used (the stated one, or the noise statement's estimate)
    chi2: float
    dof: int
    chi2_per_dof: float
    ppc_p: float
    moran_I: float
    moran_z: float
    moran_p: float
    bic: float
    n_data: int
    n_params: int
    structured: bool


@dataclass(frozen=True)
class MembraneRegions:
    """The named regions around a square membrane |x|, |y| <= ``half`` [mm]: under it, its edges
    and corners (a strip of half-width ``band`` [mm] about its outline) and the far field beyond
    that strip, split by the angle to the fiber direction."""

    half: float
    band: float

    def masks(self, xy: np.ndarray, theta_deg: float) -> dict[str, np.ndarray]:
        """Points (n, 2) [mm] of each named region; the far field is split by the angle between a
        point's position and the fiber direction ``theta_deg`` [deg]."""
        ax, ay = np.abs(xy[:, 0]), np.abs(xy[:, 1])
        ring = np.maximum(ax, ay)
        corner = (np.abs(ax - self.half) <= self.band) & (np.abs(ay - self.half) <= self.band)
        edge = (np.abs(ring - self.half) <= self.band) & ~corner
        far = ring > self.half + self.band
        angle = np.degrees(np.abs(np.arctan2(xy[:, 1], xy[:, 0]) - math.radians(theta_deg))) % 180
        off = np.minimum(angle, 180 - angle)
        return {
            "under the membrane": ring < self.half - self.band,
            "membrane edges": edge,
            "membrane corners": corner,
            "far field along the fibers": far & (off <= 30),
            "far field across the fibers": far & (off >= 60),
            "far field, oblique to the fibers": far & (off > 30) & (off < 60),
        }


@dataclass(frozen=True)
class RegionResidual:
    """RMS standardised residual [sigma] over the points of one named region."""

    region: str
    points: int
    rms_sigma: float


@dataclass(frozen=True)
class Hotspot:
    """The disc around the measured point (x, y) [mm] whose ``points`` nearest measured points
    (within ``radius`` [mm]) have the largest RMS standardised residual [sigma], all
    observations and components pooled: where a local defect sits."""

    x: float
    y: float
    radius: float
    points: int
    rms_sigma: float

    def summary(self) -> str:
        return (
            f"within {self.radius:.1f} mm of (x, y) = ({self.x:.1f}, {self.y:.1f}) mm "
            f"({self.rms_sigma:.1f} sigma RMS over its {self.points} nearest points)"
        )


def residual_hotspot(cal: Calibration, data: Data, k: int = HOTSPOT_POINTS) -> Hotspot:
    """The measured point whose ``k`` nearest measured points hold the largest RMS standardised
    residual (k nearest rather than a fixed radius: the disc adapts to the point density).
    Observations that share a point are averaged there first, so that the k points are k
    places, not copies of fewer."""
    squares = data.point_mean_square(cal.model_fields)
    pooled = np.concatenate([data.xy[o, m] for o, m in enumerate(data.masks)])
    xy, where = np.unique(pooled, axis=0, return_inverse=True)
    sq = np.bincount(where.ravel(), np.concatenate([squares[o, m] for o, m in enumerate(data.masks)]))
    sq /= np.bincount(where.ravel())
    k = min(k, len(xy))
    distance, nearest = cKDTree(xy).query(xy, k)
    distance, nearest = distance.reshape(len(xy), k), nearest.reshape(len(xy), k)
    rms = np.sqrt(sq[nearest].mean(axis=1))
    best = int(np.argmax(rms))
    return Hotspot(float(xy[best, 0]), float(xy[best, 1]), float(distance[best, -1]), k, float(rms[best]))


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


def morans_i(standardised: np.ndarray, data: Data, n_sim: int = 400, seed: int = 0) -> MoranI:
    """Moran's I of the standardised residual and its null distribution under the noise model.

    The noise itself is spatially correlated, so the null is simulated: I of ``n_sim`` fields
    drawn from the stated noise model plus the model-error term. z = (I - mean_null) / sd_null; p is the
    Monte-Carlo p-value for more positive autocorrelation (structure) than noise gives.
    """
    weights = [neighbour_weights(data.xy[o, m]) for o, m in enumerate(data.masks)]
    stat = morans_i_statistic(standardised, data.masks, weights)
    null = np.array([morans_i_statistic(f, data.masks, weights) for f in null_fields(data, n_sim, seed)])
    z = (stat - null.mean()) / null.std()
    return MoranI(float(stat), float(z), float((1 + np.sum(null >= stat)) / (n_sim + 1)))


def null_fields(data: Data, n_sim: int, seed: int = 0) -> np.ndarray:
    """(n_sim, n_obs, n_pts, 3) standardised draws of the noise model plus the model-error term."""
    rng = np.random.default_rng(seed)
    fields = np.zeros((n_sim, *data.fields.shape))
    for o, m in enumerate(data.masks):
        draw = data.noise.sample(data.xy[o, m], (n_sim,), rng)
        if data.model_error is not None:
            draw += data.model_error.sample(data.xy[o, m], o, m, (n_sim,), rng)
        fields[:, o, m] = draw / data.total_sd[o, m]
    return fields


def heterogeneity_statistic(standardised: np.ndarray, groups: list[np.ndarray]) -> float:
    """H = sum_r n_r (log m_r - log m)^2: how unevenly the mean square m_r of a standardised
    residual (n_obs, n_pts, 3) is spread over regions (``groups``: per observation (n_regions,
    n_pts) masks) around its overall mean square m. Scale-free: noise understated by any factor
    gives the same H as the stated noise."""
    squares = np.nan_to_num(np.nanmean(standardised**2, axis=-1))  # (n_obs, n_pts)
    sums = sum((g * squares[o]).sum(1) for o, g in enumerate(groups))
    counts = sum(g.sum(1) for g in groups)
    keep = counts > 0
    means = sums[keep] / counts[keep]
    return float(np.sum(counts[keep] * np.log(means / (sums[keep].sum() / counts[keep].sum())) ** 2))


def region_heterogeneity(cal: Calibration, data: Data, membrane: MembraneRegions, n_sim: int = 400) -> float:
    """z of :func:`heterogeneity_statistic` over the ``membrane``'s regions against draws
    of the noise model: large when the residual is concentrated (a missing effect peaks at the
    membrane's edges and corners), ~0 for noise of any sd."""
    theta = float(cal.x[THETA])
    groups = [np.stack(list(membrane.masks(data.xy[o], theta).values())) & m for o, m in enumerate(data.masks)]
    stat = heterogeneity_statistic(data.standardised(cal.model_fields), groups)
    null = np.array([heterogeneity_statistic(f, groups) for f in null_fields(data, n_sim)])
    return float((stat - null.mean()) / null.std())


def residual_metrics(cal: Calibration, data: Data, n_draws: int = 4000, seed: int = 0) -> ResidualMetrics:
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
    return ResidualMetrics(
        rmse=float(np.sqrt(np.mean(r**2))),
        rmse_by_component={c: float(np.sqrt(np.mean(r[:, i] ** 2))) for i, c in enumerate(COMPONENTS)},
        noise_rms=float(np.sqrt(np.mean(data.noise.sd**2))),
        chi2=chi2,
        dof=n - k,
        chi2_per_dof=chi2 / (n - k),
        ppc_p=ppc_p,
        moran_I=moran.I,
        moran_z=moran.z,
        moran_p=moran.p,
        bic=chi2 + k * math.log(n),
        n_data=n,
        n_params=k,
        structured=bool(structured),
    )


def rank_regions(cal: Calibration, data: Data, membrane: MembraneRegions) -> list[RegionResidual]:
    """The ``membrane``'s regions ranked by RMS standardised residual (data - model)/sd [sigma];
    noise alone gives ~1.

    The sd is the total one (noise and model error); points of every observation are pooled."""
    theta = float(cal.x[THETA])
    squares = data.point_mean_square(cal.model_fields)
    sums: dict[str, list[float]] = {}
    for o, m in enumerate(data.masks):
        for name, inside in membrane.masks(data.xy[o], theta).items():
            sel = inside & m
            total = sums.setdefault(name, [0.0, 0])
            total[0] += float(squares[o, sel].sum())
            total[1] += int(sel.sum())
    out = [RegionResidual(name, n, math.sqrt(ss / n)) for name, (ss, n) in sums.items() if n]
    return sorted(out, key=lambda r: -r.rms_sigma)
