"""The statistical model: uniform priors on the skin parameters, a Gaussian likelihood of the
observed PC weights around the emulator's prediction.

For observation o (one design alpha_o and load fraction t_o) and PC weight g of strain
component c(g):

    w_og ~ Normal(m_g(params, alpha_o t_o), v_og + s_og^2)

with m, v the emulator's GP predictive mean and variance, and the observation noise s either
- ``noise="halfcauchy"``: one unknown sigma_c per strain component shared by all its PC weights
  (and observations), sigma_c ~ HalfCauchy(noise_scale), in PC-weight units; or
- ``noise="known"``: the measurement's stated per-cell standard deviation carried through the
  (masked) PCA projection (independent cells).
Priors: Uniform on the emulator's training box for each of (mu, k1, k2, kappa, theta) --
never hard-coded.

GP variance: ``gp_variance="exact"`` (default) evaluates v at every leapfrog step, which costs
O(n_gp^2) per GP (about 3 ms per step for a 600-row, 6-GP emulator; ~35 ms for 1,400 rows and
16 GPs). ``gp_variance="mode"`` evaluates it once at the posterior mode and holds it fixed
(cheap, O(n_gp) per step); :meth:`SkinPosterior.gp_variance_spread` then measures how much v
really changes over the posterior draws, and summary.json reports it.

:class:`SkinPosterior` is a plain torch log density on an unconstrained vector (logit of the
unit box, log of sigma) with the Jacobian terms; :func:`pyro_model` states the same model in
Pyro (the reference the tests compare the potential with), its priors in :func:`pyro_prior`.

The emulator cannot extrapolate: :meth:`ObservedWeights.project` refuses observations whose
emulator inputs alpha * t lie outside the box the emulator was trained on, and stated noise
standard deviations that are not positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyro
import pyro.distributions as dist
import torch

from inference.observations import Observation
from skinfem.config import PARAM_NAMES
from surrogate.emulator import COMPONENTS, Emulator


@dataclass
class ObservedFields:
    """The observations the PC weights were projected from (recorded in ``posterior.nc``).

    Attributes:
        alpha: (n_obs, 2) membrane designs (alpha11, alpha22).
        t: (n_obs,) load fractions.
        strain: (n_obs, n_cells, 3) observed log strain xx, yy, xy on the skin cells (NaN: masked).
        xy: (n_cells, 2) skin-cell centroids [mm].
        sd: (n_obs, 3) stated noise sd per component [strain], or None.
        sources: where each observation came from.
    """

    alpha: np.ndarray
    t: np.ndarray
    strain: np.ndarray
    xy: np.ndarray
    sd: np.ndarray | None
    sources: list[str]


def check_observation(emulator: Emulator, o: Observation) -> None:
    """Refuse an observation the emulator cannot predict or whose stated noise is degenerate.

    Raises:
        ValueError: naming the observation, the value and the range: alpha * t (the emulator's
            design inputs) outside the box of its training rows, t outside (0, 1], or a stated
            sd that is not positive (a zero sd makes the likelihood's noise covariance singular).
    """
    where = f"{o.source or 'observation'} (alpha11 = {o.alpha[0]:g}, alpha22 = {o.alpha[1]:g}, t = {o.t:g})"
    if not 0 < o.t <= 1:
        raise ValueError(f"{where}: the load fraction t must be in (0, 1]")
    lower, upper = emulator.lower[5:], emulator.upper[5:]
    slack = 1e-9 * (upper - lower)
    for k, name in enumerate(("alpha11", "alpha22")):
        value = o.alpha[k] * o.t
        if not lower[k] - slack[k] <= value <= upper[k] + slack[k]:
            raise ValueError(
                f"{where}: {name}*t = {value:g} is outside the emulator's training range "
                f"[{lower[k]:g}, {upper[k]:g}] of {name}*t; it cannot extrapolate: observe designs and "
                f"frames inside it, or fit an emulator on a dataset that covers them")
    if o.sd is not None and not np.all(np.isfinite(o.sd) & (np.asarray(o.sd) > 0)):
        raise ValueError(f"{where}: the stated noise sd {np.asarray(o.sd).tolist()} (xx, yy, xy) must be positive "
                         f"and finite: a zero sd makes the noise covariance singular")


@dataclass
class ObservedWeights:
    """Observations projected on the emulator's PC basis.

    Attributes:
        design_inputs: (n_obs, 2) alpha11*t, alpha22*t.
        weights: (n_obs, G) observed PC weights.
        noise_var: (n_obs, G) known noise variance in weight units, or None.
        truth: (5,) generating parameters when known.
        fields: the observations projected (set by :meth:`project`), or None.
    """

    design_inputs: np.ndarray
    weights: np.ndarray
    noise_var: np.ndarray | None
    truth: np.ndarray | None
    fields: ObservedFields | None = None

    @classmethod
    def project(cls, emulator: Emulator, observations: list[Observation]) -> ObservedWeights:
        """PC weights of the observations (each checked by :func:`check_observation`)."""
        if not observations:
            raise ValueError("no observation given")
        if any(len(o.fields) != len(emulator.xy) for o in observations):
            raise ValueError("observation fields do not have one value per emulator skin cell")
        for o in observations:
            check_observation(emulator, o)
        rows, noise = [], []
        for o in observations:
            w, v = [], []
            for c, pca in emulator.pcas.items():
                k = COMPONENTS.index(c)
                weights, projector = pca.transform_masked(o.fields[:, k], o.mask)
                w.append(weights)
                if o.sd is not None:
                    per_cell = (o.sd[k] / pca.scale_[o.mask]) ** 2
                    v.append(projector**2 @ per_cell)
            rows.append(np.concatenate(w))
            noise.append(np.concatenate(v) if v else None)
        known = None if any(n is None for n in noise) else np.stack(noise)
        truths = [o.truth for o in observations if o.truth is not None]
        fields = ObservedFields(
            alpha=np.stack([o.alpha for o in observations]),
            t=np.array([o.t for o in observations]),
            strain=np.stack([np.where(o.mask[:, None], o.fields, np.nan) for o in observations]),
            xy=emulator.xy,
            sd=None if any(o.sd is None for o in observations) else np.stack([o.sd for o in observations]),
            sources=[o.source for o in observations],
        )
        return cls(
            design_inputs=np.stack([o.alpha * o.t for o in observations]),
            weights=np.stack(rows),
            noise_var=known,
            truth=truths[0] if truths else None,
            fields=fields,
        )


class SkinPosterior:
    """Log posterior of (mu, k1, k2, kappa, theta[, sigma_c...]) on an unconstrained vector.

    Args:
        noise: "halfcauchy" (unknown sigma per component) or "known" (from the measurement sd).
        noise_scale: HalfCauchy scale of sigma [PC-weight units].
        gp_variance: "mode" (fixed at the posterior mode, see module doc) or "exact".
    """

    def __init__(
        self,
        emulator: Emulator,
        observed: ObservedWeights,
        noise: str = "halfcauchy",
        noise_scale: float = 1.0,
        gp_variance: str = "exact",
    ):
        if noise not in ("halfcauchy", "known"):
            raise ValueError(f"noise must be 'halfcauchy' or 'known', got '{noise}'")
        if noise == "known" and observed.noise_var is None:
            raise ValueError("noise='known' needs measurements with sd_exx, sd_eyy, sd_exy columns")
        if gp_variance not in ("mode", "exact"):
            raise ValueError(f"gp_variance must be 'mode' or 'exact', got '{gp_variance}'")
        if not noise_scale > 0:
            raise ValueError(f"noise_scale (the HalfCauchy scale of sigma) must be > 0, got {noise_scale}")
        self.emulator = emulator
        self.observed = observed
        self.noise = noise
        self.noise_scale = noise_scale
        self.gp_variance = gp_variance
        bounds = emulator.param_bounds
        self.lower = torch.as_tensor(bounds[:, 0])
        self.span = torch.as_tensor(bounds[:, 1] - bounds[:, 0])
        self.design_inputs = torch.as_tensor(observed.design_inputs)
        self.weights = torch.as_tensor(observed.weights)
        self.component_of_weight = torch.as_tensor(
            np.concatenate([[k] * m for k, m in enumerate(emulator.n_weights.values())])
        )
        self.noise_var = None if observed.noise_var is None else torch.as_tensor(observed.noise_var)
        self.fixed_gp_var: torch.Tensor | None = None
        self._density = None

    # -- parametrisation -------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        sigmas = tuple(f"sigma_{c}" for c in self.emulator.components) if self.noise == "halfcauchy" else ()
        return PARAM_NAMES + sigmas

    @property
    def dim(self) -> int:
        return len(self.names)

    def constrain(self, u: torch.Tensor) -> torch.Tensor:
        """Unconstrained (..., dim) -> (mu, k1, k2, kappa, theta [deg], sigma...) (..., dim)."""
        params = self.lower + torch.sigmoid(u[..., :5]) * self.span
        return torch.cat([params, torch.exp(u[..., 5:])], -1)

    def unconstrain(self, values: torch.Tensor) -> torch.Tensor:
        z = ((values[..., :5] - self.lower) / self.span).clamp(1e-9, 1 - 1e-9)
        return torch.cat([torch.logit(z), torch.log(values[..., 5:])], -1)

    # -- density ---------------------------------------------------------------------------
    def predict(self, params: torch.Tensor, return_var: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """GP mean (n_obs, G) and variance at params (5,) for every observation."""
        x = torch.cat([params.expand(len(self.design_inputs), 5), self.design_inputs], -1)
        if return_var:
            return self.emulator.predict_weights(x, return_var=True)
        return self.emulator.predict_weights(x, return_var=False), None

    @property
    def variance_is_fixed(self) -> bool:
        """True once the GP variance is held at the mode (``gp_variance="mode"``)."""
        return self.gp_variance == "mode" and self.fixed_gp_var is not None

    def weight_moments(self, params: torch.Tensor, sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and total variance (GP + observation noise) of the observed weights (n_obs, G)."""
        mean, var = self.predict(params, return_var=not self.variance_is_fixed)
        if self.variance_is_fixed:
            var = self.fixed_gp_var
        noise = self.noise_var if self.noise == "known" else sigma[self.component_of_weight] ** 2
        return mean, var + noise

    def log_likelihood(self, params: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        mean, total = self.weight_moments(params, sigma)
        resid = self.weights - mean
        return -0.5 * torch.sum(resid**2 / total + torch.log(2 * math.pi * total))

    def pointwise_log_likelihood(self, values: torch.Tensor) -> torch.Tensor:
        """Log density (n_obs, G) of each observed PC weight at constrained ``values`` (dim,).

        The observed weights are independent normals given the parameters (not whitened: their
        covariance is diagonal), so these terms sum to :meth:`log_likelihood`; they are the
        elements of :func:`pyro_model`'s ``weights`` site.
        """
        mean, total = self.weight_moments(values[:5], values[5:])
        return dist.Normal(mean, torch.sqrt(total), validate_args=False).log_prob(self.weights)

    def log_prior_and_jacobian(self, u: torch.Tensor) -> torch.Tensor:
        """Log prior density of ``constrain(u)`` plus the log Jacobian of ``constrain``: (...,) for u (..., dim)."""
        log_z = torch.nn.functional.logsigmoid(u[..., :5]) + torch.nn.functional.logsigmoid(-u[..., :5])  # log z(1-z)
        log_jac = torch.sum(torch.log(self.span) + log_z, -1) + torch.sum(u[..., 5:], -1)
        log_prior = -torch.sum(torch.log(self.span))
        if u.shape[-1] > 5:
            sigma = torch.exp(u[..., 5:])
            log_prior = log_prior + torch.sum(
                dist.HalfCauchy(torch.tensor(self.noise_scale, dtype=u.dtype), validate_args=False).log_prob(sigma), -1
            )
        return log_prior + log_jac

    def log_density(self, u: torch.Tensor) -> torch.Tensor:
        """Log posterior density of the unconstrained vector u (dim,), Jacobian included."""
        values = self.constrain(u)
        return self.log_likelihood(values[:5], values[5:]) + self.log_prior_and_jacobian(u)

    def potential(self, sites: dict[str, torch.Tensor]) -> torch.Tensor:
        """Pyro's ``potential_fn``: minus the log density of ``sites["u"]``.

        With ``gp_variance="mode"`` it is evaluated by the closed-form
        :class:`~inference.density.FusedLogDensity` (same value and gradient as
        :meth:`log_density`, ~3x less overhead).
        """
        from inference.density import FusedLogDensity, fused_potential

        if not self.variance_is_fixed:
            return -self.log_density(sites["u"])
        if self._density is None:
            self._density = FusedLogDensity(self)
        return fused_potential(sites["u"], self._density)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_density": None}  # rebuilt where it is used

    # -- helpers ---------------------------------------------------------------------------
    def initial_sigma(self) -> np.ndarray:
        """A data-driven starting noise level per component: RMS of the observed weights / 10."""
        out = []
        for k in range(len(self.emulator.components)):
            w = self.weights[:, self.component_of_weight == k]
            out.append(float(torch.sqrt(torch.mean(w**2))) / 10 + 1e-6)
        return np.array(out)

    def fix_gp_variance(self, params: np.ndarray) -> None:
        """Hold the GP variance at its value at ``params`` (5,) (``gp_variance="mode"``)."""
        with torch.no_grad():
            self.fixed_gp_var = self.predict(torch.as_tensor(params), return_var=True)[1]

    def gp_variance_spread(self, draws: np.ndarray, n: int = 50, seed: int = 0) -> dict:
        """How the GP variance over ``n`` posterior draws (k, 5) compares with the fixed one."""
        rng = np.random.default_rng(seed)
        pick = draws[rng.choice(len(draws), size=min(n, len(draws)), replace=False)]
        with torch.no_grad():
            ratios = np.stack([
                (self.predict(torch.as_tensor(p), True)[1] / self.fixed_gp_var).numpy() for p in pick
            ])
        return {"ratio_median": float(np.median(ratios)), "ratio_5": float(np.percentile(ratios, 5)),
                "ratio_95": float(np.percentile(ratios, 95))}


def pyro_prior(posterior: SkinPosterior) -> tuple[torch.Tensor, torch.Tensor]:
    """The priors in Pyro's language: params (5,) and sigma (n_sigma,) (empty with known noise)."""
    lo, span = posterior.lower, posterior.span
    params = torch.stack(
        [pyro.sample(name, dist.Uniform(lo[i], lo[i] + span[i])) for i, name in enumerate(PARAM_NAMES)]
    )
    sigma = torch.stack(
        [pyro.sample(name, dist.HalfCauchy(torch.tensor(posterior.noise_scale, dtype=torch.float64)))
         for name in posterior.names[5:]]
    ) if posterior.noise == "halfcauchy" else torch.zeros(0, dtype=torch.float64)
    return params, sigma


def prior_draws(posterior: SkinPosterior, n: int, seed: int) -> np.ndarray:
    """(n, dim) seeded draws of :func:`pyro_prior` (Pyro's ``Predictive``), theta in degrees."""
    from pyro.infer import Predictive

    with torch.random.fork_rng():
        torch.manual_seed(seed)
        draws = Predictive(pyro_prior, num_samples=n, return_sites=list(posterior.names))(posterior)
    return np.column_stack([draws[name].reshape(n).numpy() for name in posterior.names])


def pyro_model(posterior: SkinPosterior) -> None:
    """The same model in Pyro's language (reference for :class:`SkinPosterior`)."""
    params, sigma = pyro_prior(posterior)
    mean, total = posterior.weight_moments(params, sigma)
    pyro.sample("weights", dist.Normal(mean, torch.sqrt(total)).to_event(2), obs=posterior.weights)
