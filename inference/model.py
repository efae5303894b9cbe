"""The statistical model: uniform priors on the skin parameters, a Gaussian likelihood of the
observed PC weights around the emulator's prediction.

For observation o (one design alpha_o and load fraction t_o) and PC weight g of strain
component c(g):

    w_g ~ MultivariateNormal(m_g(params, alpha_o t_o), lambda (C_g + tau_g^2 (s s^T) * R_g + T_g) + S_g)   (over o)

with m_g the emulator's GP predictive mean, C_g its joint predictive covariance over the
observations (the GP's white-noise level included, unless the emulator was trained on noisy
strains: that level is then the measurement's noise, which S_g carries, and C_g is the latent
function's covariance; :attr:`surrogate.emulator.Emulator.white_noise_is_measurement`), and,
when ``emulator_error`` is on (default), the emulator's error beyond it
(:mod:`surrogate.error_model`): the cross-validated held-out excess tau_g^2, scaled by each
observation's load s_o = |alpha_o t_o| / |alpha t|_max and correlated between observations as
R_g, and the PCA-truncation variance T_g (diagonal) that a masked projection picks up; and
lambda, the material scale of that emulator error, lambda ~ InverseGamma(a, a - 1) fitted on
the held-out materials (:func:`surrogate.error_model.fit_material_scale`), sampled as
``emulator_scale`` when ``emulator_scale`` is on (off by default: lambda = 1; on the fresh
``small`` materials it calibrates the 50 % intervals of a few frames but makes those of θ from
three membranes over-confident, docs/inference.md).
Weights g are independent, as the GPs are -- unless ``emulator_shift`` is on: the emulator's
error is then mostly a shift of the material's parameters shared by every weight and
observation (:class:`surrogate.error_model.ParameterShift`), carried as lambda J C J^T over all
weights together (J the emulator mean's Jacobian in the unit box of the parameters, evaluated
at the point, or at the mode with the GP variance; C the shift covariance), with the held-out
excess tau_g^2 replaced by what the shift leaves, and C_g by rho_g C_g: the GP variance measures
the whole of a fresh material's error, shift included, and carried in full next to J C J^T it
would count the shift twice; rho_g is the share of it the shifts of held-out materials leave
(:func:`surrogate.error_model.shift_residual_model`). S_g is the observation noise, either
- ``noise="halfcauchy"``: one unknown sigma_c per strain component shared by all its PC weights
  (and observations), sigma_c ~ HalfCauchy(noise_scale), in PC-weight units; or
- ``noise="known"``: the measurement's stated per-cell standard deviation carried through the
  (masked) PCA projection (independent cells).
Priors: Uniform on the emulator's training box for each of (mu, k1, k2, kappa, theta) --
never hard-coded.

GP variance: ``gp_variance="exact"`` (default) evaluates C at every leapfrog step, which costs
O(n_gp^2) per GP (about 3 ms per step for a 600-row, 6-GP emulator; ~35 ms for 1,400 rows and
16 GPs). ``gp_variance="mode"`` evaluates it once at the posterior mode and holds it fixed
(cheap, O(n_gp) per step); :meth:`SkinPosterior.gp_variance_spread` then measures how much its
diagonal really changes over the posterior draws, and summary.json reports it.
:meth:`SkinPosterior.error_budget` says which term dominates the variance of the weights.

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
from scipy.stats import invgamma

from inference.observations import Observation, load_fraction_problem
from skinfem.config import PARAM_NAMES
from skinfem.io import COMPONENTS
from surrogate.emulator import Emulator
from surrogate.error_model import SHIFT_MATERIALS, truncation_variance


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
    if problem := load_fraction_problem(o.t):
        raise ValueError(f"{where}: the load fraction {problem}")
    lower, upper = emulator.lower[5:], emulator.upper[5:]
    slack = 1e-9 * (upper - lower)
    for k, name in enumerate(("alpha11", "alpha22")):
        value = o.alpha[k] * o.t
        if not lower[k] - slack[k] <= value <= upper[k] + slack[k]:
            raise ValueError(
                f"{where}: {name}*t = {value:g} is outside the emulator's training range "
                f"[{lower[k]:g}, {upper[k]:g}] of {name}*t; it cannot extrapolate: observe designs and "
                f"frames inside it, or fit an emulator on a dataset that covers them"
            )
    if o.sd is not None and not np.all(np.isfinite(o.sd) & (np.asarray(o.sd) > 0)):
        raise ValueError(
            f"{where}: the stated noise sd {np.asarray(o.sd).tolist()} (xx, yy, xy) must be positive "
            f"and finite: a zero sd makes the noise covariance singular"
        )


@dataclass
class ObservedWeights:
    """Observations projected on the emulator's PC basis.

    Attributes:
        design_inputs: (n_obs, 2) alpha11*t, alpha22*t.
        weights: (n_obs, G) observed PC weights.
        noise_var: (n_obs, G) known noise variance in weight units, or None.
        truth: (5,) generating parameters when known.
        fields: the observations projected (set by :meth:`project`), or None.
        truncation_var: (n_obs, G) variance the discarded PCA directions put on the weights
            through the masked projection (:func:`surrogate.error_model.truncation_variance`),
            or None (zero).
    """

    design_inputs: np.ndarray
    weights: np.ndarray
    noise_var: np.ndarray | None
    truth: np.ndarray | None
    fields: ObservedFields | None = None
    truncation_var: np.ndarray | None = None

    @classmethod
    def project(cls, emulator: Emulator, observations: list[Observation]) -> ObservedWeights:
        """PC weights of the observations (each checked by :func:`check_observation`)."""
        if not observations:
            raise ValueError("no observation given")
        if any(len(o.fields) != len(emulator.xy) for o in observations):
            raise ValueError("observation fields do not have one value per emulator skin cell")
        for o in observations:
            check_observation(emulator, o)
        rows, noise, truncation = [], [], []
        for o in observations:
            w, v, tv = [], [], []
            for c, pca in emulator.pcas.items():
                k = COMPONENTS.index(c)
                weights, projector = pca.transform_masked(o.fields[:, k], o.mask)
                w.append(weights)
                tv.append(truncation_variance(pca, projector, o.mask))
                if o.sd is not None:
                    per_cell = (o.sd[k] / pca.scale_[o.mask]) ** 2
                    v.append(projector**2 @ per_cell)
            rows.append(np.concatenate(w))
            truncation.append(np.concatenate(tv))
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
            truncation_var=np.stack(truncation),
        )


@dataclass(frozen=True)
class GpVarianceSpread:
    """The GP variance over posterior draws against the one fixed at the mode: quantiles of their ratio [-]."""

    ratio_median: float
    ratio_5: float
    ratio_95: float


@dataclass(frozen=True)
class ErrorBudget:
    """Share of the variance of the observed PC weights held by each term, at one point [-]
    (mean over weights and observations of term / total; the shares sum to 1)."""

    noise: float
    gp: float  # the GPs' own predictive variance (its share rho_g with the parameter shift)
    held_out_excess: float  # the cross-validated excess (surrogate.error_model)
    truncation: float  # what the retained PCs cannot represent, through the masked projection
    parameter_shift: float = 0.0  # the error shared as a shift of the parameters (emulator_shift)

    @property
    def emulator(self) -> float:
        return self.gp + self.held_out_excess + self.truncation + self.parameter_shift

    def statement(self, params: np.ndarray) -> str:
        """One sentence for the summary: which term limits the intervals."""
        shift = f"parameter shift {self.parameter_shift:.0%}, " if self.parameter_shift else ""
        shares = (
            f"noise {self.noise:.0%}, GP {self.gp:.0%}, held-out excess {self.held_out_excess:.0%}, "
            f"{shift}PCA truncation {self.truncation:.0%} of the weights' variance"
        )
        if self.emulator <= self.noise:
            return f"the measurement noise limits these intervals ({shares})"
        if self.truncation >= self.gp + self.held_out_excess + self.parameter_shift:
            return (
                f"the emulator's PCA truncation, not your measurement, limits these intervals ({shares}): the "
                "field of view leaks the discarded components into the kept ones; refit the emulator with more "
                "components ('skinid surrogate fit --variance 0.999')"
            )
        near = ", ".join(f"{n} = {v:.3g}" for n, v in zip(PARAM_NAMES, params))
        return f"the emulator, not your measurement, limits these intervals ({shares}): refine the dataset near {near}"


class SkinPosterior:
    """Log posterior of (mu, k1, k2, kappa, theta[, sigma_c...][, lambda]) on an unconstrained vector.

    Args:
        noise: "halfcauchy" (unknown sigma per component) or "known" (from the measurement sd).
        noise_scale: HalfCauchy scale of sigma [PC-weight units].
        gp_variance: "mode" (fixed at the posterior mode, see module doc) or "exact".
        emulator_error: carry the held-out excess and the PCA truncation (module doc); off:
            the GP's own covariance only.
        emulator_scale: sample the material scale lambda of that error (module doc); needs
            ``emulator_error`` and an emulator that has fitted it.
        emulator_shift: carry the emulator's error as a parameter shift (module doc); needs
            ``emulator_error`` and an emulator that has fitted it.
    """

    def __init__(
        self,
        emulator: Emulator,
        observed: ObservedWeights,
        noise: str = "halfcauchy",
        noise_scale: float = 1.0,
        gp_variance: str = "exact",
        emulator_error: bool = True,
        emulator_scale: bool = False,
        emulator_shift: bool = False,
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
        self.emulator_error = emulator_error
        # trained on noisy strains, the GPs' white noise is the measurement's: carried by S_g only
        self.gp_white_noise = not emulator.white_noise_is_measurement
        bounds = emulator.param_bounds
        self.lower = torch.as_tensor(bounds[:, 0])
        self.span = torch.as_tensor(bounds[:, 1] - bounds[:, 0])
        self.design_inputs = torch.as_tensor(observed.design_inputs)
        self.weights = torch.as_tensor(observed.weights)
        self.component_of_weight = torch.as_tensor(
            np.concatenate([[k] * m for k, m in enumerate(emulator.n_weights.values())])
        )
        self.noise_var = None if observed.noise_var is None else torch.as_tensor(observed.noise_var)
        excess = emulator.held_out_excess
        self.shift = excess.parameter_shift if emulator_error and emulator_shift and excess else None
        if emulator_shift and self.shift is None:
            raise ValueError(
                "the parameter shift needs the emulator's error model (emulator_error on) and an emulator "
                f"that fitted it (on >= {SHIFT_MATERIALS} training materials): refit it with 'skinid surrogate fit'"
            )
        self.shift_root = None if self.shift is None else torch.as_tensor(psd_root(np.array(self.shift.covariance)))
        rho = np.ones(self.weights.shape[1]) if self.shift is None else self.shift.gp_share
        self.gp_share = torch.as_tensor(rho, dtype=torch.float64)  # rho_g (module doc)
        self.excess_cov, self.truncation_var = self._emulator_error_terms()
        self.scale_prior = excess.material_scale if emulator_error and emulator_scale and excess else None
        if emulator_scale and self.scale_prior is None:
            raise ValueError(
                "the emulator scale needs the emulator's error model (emulator_error on) and an emulator "
                "that fitted its material scale: refit it with 'skinid surrogate fit'"
            )
        self.fixed_gp_cov: torch.Tensor | None = None
        self.fixed_shift: torch.Tensor | None = None
        self._density = None

    def _emulator_error_terms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Held-out excess tau_g^2 s s^T R_g (G, n_obs, n_obs) and truncation variance (n_obs, G);
        zeros when ``emulator_error`` is off or the emulator has no held-out excess."""
        n_obs, n_weights = self.weights.shape
        excess = self.emulator.held_out_excess
        if self.emulator_error and excess is not None:
            tau2 = np.array(excess.variance if self.shift is None else self.shift.residual_variance)
            scale = excess.load_scale(self.observed.design_inputs)
        else:
            tau2, scale = np.zeros(n_weights), np.zeros(n_obs)
        correlation = self.emulator.error_correlation(self.observed.design_inputs) * np.outer(scale, scale)
        truncation = self.observed.truncation_var
        if not self.emulator_error or truncation is None:
            truncation = np.zeros((n_obs, n_weights))
        return torch.as_tensor(tau2[:, None, None] * correlation), torch.as_tensor(truncation)

    # -- parametrisation -------------------------------------------------------------------
    @property
    def n_sigma(self) -> int:
        return len(self.emulator.components) if self.noise == "halfcauchy" else 0

    @property
    def names(self) -> tuple[str, ...]:
        sigmas = tuple(f"sigma_{c}" for c in self.emulator.components[: self.n_sigma])
        return PARAM_NAMES + sigmas + (("emulator_scale",) if self.scale_prior else ())

    def latents(self, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Constrained (dim,) -> params (5,), sigma (n_sigma,), emulator scale lambda (scalar, 1 if fixed)."""
        if values.shape[-1] != self.dim:
            raise ValueError(f"expected {self.dim} values ({', '.join(self.names)}), got {values.shape[-1]}")
        scale = values[-1] if self.scale_prior else torch.ones((), dtype=values.dtype)
        return values[:5], values[5 : 5 + self.n_sigma], scale

    @property
    def dim(self) -> int:
        return len(self.names)

    def constrain(self, u: torch.Tensor) -> torch.Tensor:
        """Unconstrained (..., dim) -> (mu, k1, k2, kappa, theta [deg], sigma...) (..., dim)."""
        params = self.lower + torch.sigmoid(u[..., :5]) * self.span
        return torch.cat([params, torch.exp(u[..., 5:])], -1)

    def unconstrain(self, values: torch.Tensor) -> torch.Tensor:
        """(..., dim) parameters -> unbounded coordinates: logit of the five skin parameters'
        share of their prior box, log of the positive rest (noise sd, emulator scale)."""
        z = ((values[..., :5] - self.lower) / self.span).clamp(1e-9, 1 - 1e-9)
        return torch.cat([torch.logit(z), torch.log(values[..., 5:])], -1)

    # -- density ---------------------------------------------------------------------------
    def inputs(self, params: torch.Tensor) -> torch.Tensor:
        """Raw emulator inputs (n_obs, 7) of every observation at params (5,)."""
        return torch.cat([params.expand(len(self.design_inputs), 5), self.design_inputs], -1)

    @property
    def variance_is_fixed(self) -> bool:
        """True once the GP covariance is held at the mode (``gp_variance="mode"``)."""
        return self.gp_variance == "mode" and self.fixed_gp_cov is not None

    def gp_moments(self, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """GP mean (n_obs, G) and joint covariance over the observations (G, n_obs, n_obs)."""
        x = self.inputs(params)
        if self.variance_is_fixed:
            return self.emulator.predict_weights(x, return_var=False), self.fixed_gp_cov
        return self.emulator.predict_joint(x, white_noise=self.gp_white_noise)

    def shift_factor(self, params: torch.Tensor, differentiable: bool = True) -> torch.Tensor | None:
        """U (G, n_obs, 5) with J C J^T = U U^T (module doc), differentiable in params (5,) unless
        ``differentiable`` is False; fixed with the GP variance; None without the parameter shift."""
        if self.shift_root is None:
            return None
        if self.variance_is_fixed:
            return self.fixed_shift
        jac = torch.autograd.functional.jacobian(
            lambda p: self.emulator.predict_weights(self.inputs(p), return_var=False),
            params,
            create_graph=differentiable,
        )  # (n_obs, G, 5) in the raw parameters
        return ((jac * self.span) @ self.shift_root).permute(1, 0, 2)

    def noise_variance(self, sigma: torch.Tensor) -> torch.Tensor:
        """Observation-noise variance (n_obs, G) of every weight from sigma (n_sigma,)."""
        if sigma.shape[-1] != self.n_sigma:
            raise ValueError(f"expected {self.n_sigma} noise sigmas, got {sigma.shape[-1]} (see SkinPosterior.latents)")
        if self.noise == "known":
            return self.noise_var
        return (sigma[self.component_of_weight] ** 2).expand(self.weights.shape)

    def model_covariance(self, gp_cov: torch.Tensor, scale: torch.Tensor | float = 1.0) -> torch.Tensor:
        """Emulator covariance (G, n_obs, n_obs): lambda (rho GP + held-out excess + truncation),
        rho_g = 1 without the parameter shift."""
        gp = self.gp_share[:, None, None] * gp_cov
        return scale * (gp + self.excess_cov + torch.diag_embed(self.truncation_var.T))

    def moments(
        self, params: torch.Tensor, sigma: torch.Tensor, scale: torch.Tensor | float = 1.0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean (n_obs, G) and covariance over the observations (G, n_obs, n_obs) of the weights."""
        mean, gp_cov = self.gp_moments(params)
        return mean, self.model_covariance(gp_cov, scale) + torch.diag_embed(self.noise_variance(sigma).T)

    def whitened_residuals(
        self, params: torch.Tensor, sigma: torch.Tensor, scale: torch.Tensor | float = 1.0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """L_g^-1 (w_g - m_g) (n_obs, G) and log diag L_g (n_obs, G), L_g the Cholesky factor of
        weight g's covariance (with the parameter shift: of the covariance of every weight, in
        the order (g, o), reshaped); NaN where a covariance is not positive definite (non-finite
        parameters, as a line search may try)."""
        mean, cov = self.moments(params, sigma, scale)
        factor = self.shift_factor(params)
        if factor is not None:  # one covariance over every weight, in the order (g, o)
            cov = coupled_covariance(cov, factor, scale)
        chol, info = torch.linalg.cholesky_ex(cov)
        if bool(info.any()):
            nan = torch.full_like(mean, math.nan)
            return nan, nan
        resid = (self.weights - mean).T.reshape(cov.shape[:-1])[..., None]
        white = torch.linalg.solve_triangular(chol, resid, upper=False)[..., 0].reshape(mean.T.shape)
        return white.T, torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).reshape(mean.T.shape).T

    def log_likelihood(
        self, params: torch.Tensor, sigma: torch.Tensor, scale: torch.Tensor | float = 1.0
    ) -> torch.Tensor:
        """log p(observed weights | params (5,), sigma (n_sigma,) noise sd [strain], emulator ``scale``):
        a scalar, differentiable in every argument."""
        white, log_diag = self.whitened_residuals(params, sigma, scale)
        return -0.5 * torch.sum(white**2) - torch.sum(log_diag) - 0.5 * white.numel() * math.log(2 * math.pi)

    def pointwise_log_likelihood(self, values: torch.Tensor) -> torch.Tensor:
        """Log density (n_obs, G) of each whitened PC weight at constrained ``values`` (dim,).

        The weights of one PC are correlated across observations (module doc): the terms are
        those of L_g^-1 w_g, independent standard normals given the parameters, and sum to
        :meth:`log_likelihood`; with one observation they are the weights' own densities.
        """
        white, log_diag = self.whitened_residuals(*self.latents(values))
        return -0.5 * white**2 - log_diag - 0.5 * math.log(2 * math.pi)

    def log_prior_and_jacobian(self, u: torch.Tensor) -> torch.Tensor:
        """Log prior density of ``constrain(u)`` plus the log Jacobian of ``constrain``: (...,) for u (..., dim)."""
        log_z = torch.nn.functional.logsigmoid(u[..., :5]) + torch.nn.functional.logsigmoid(-u[..., :5])  # log z(1-z)
        log_jac = torch.sum(torch.log(self.span) + log_z, -1) + torch.sum(u[..., 5:], -1)
        log_prior = -torch.sum(torch.log(self.span))
        if self.n_sigma:
            sigma = torch.exp(u[..., 5 : 5 + self.n_sigma])
            log_prior = log_prior + torch.sum(
                dist.HalfCauchy(torch.tensor(self.noise_scale, dtype=u.dtype), validate_args=False).log_prob(sigma), -1
            )
        if self.scale_prior:
            log_prior = log_prior + self.scale_distribution(u.dtype).log_prob(torch.exp(u[..., -1]))
        return log_prior + log_jac

    def scale_quantile(self, level: float) -> float:
        """Quantile of the emulator scale's prior at ``level`` in (0, 1)."""
        a, b = self.scale_prior
        return float(invgamma(a, scale=b).ppf(level))

    def scale_distribution(self, dtype: torch.dtype = torch.float64) -> dist.InverseGamma:
        """The prior of the emulator scale lambda: InverseGamma(a, b) of the emulator's error model."""
        a, b = self.scale_prior
        return dist.InverseGamma(torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype), validate_args=False)

    def log_density(self, u: torch.Tensor) -> torch.Tensor:
        """Log posterior density of the unconstrained vector u (dim,), Jacobian included."""
        return self.log_likelihood(*self.latents(self.constrain(u))) + self.log_prior_and_jacobian(u)

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

    def fixed_eigen(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The fixed emulator covariance E_g (``gp_variance="mode"``) diagonalised together with the
        noise: (W (G, n_obs, n_obs), e (n_obs, G), log det of the known noise covariance).

        With ``noise="halfcauchy"`` W_g = Q_g, E_g = Q_g diag(e_g) Q_g^T and the covariance is
        W_g diag(lambda e_g + sigma^2) W_g^T; with known noise N_g (diagonal), W_g = N_g^-1/2 Q_g
        for N_g^-1/2 E_g N_g^-1/2 = Q_g diag(e_g) Q_g^T, and W_g^T w_g has covariance
        diag(lambda e_g + 1)."""
        fixed = self.model_covariance(self.fixed_gp_cov)
        if self.noise == "halfcauchy":
            eigenvalues, vectors = torch.linalg.eigh(fixed)
            return vectors.numpy(), eigenvalues.T.numpy(), 0.0
        inv_sd = torch.rsqrt(self.noise_var.T)  # (G, n_obs)
        eigenvalues, vectors = torch.linalg.eigh(fixed * inv_sd[:, :, None] * inv_sd[:, None, :])
        return (inv_sd[:, :, None] * vectors).numpy(), eigenvalues.T.numpy(), float(torch.log(self.noise_var).sum())

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_density": None}  # rebuilt where it is used

    # -- helpers ---------------------------------------------------------------------------
    def initial_latents(self) -> np.ndarray:
        """Unconstrained start of the positive latents (dim - 5,): log of :meth:`initial_sigma`
        and of the emulator scale's prior median."""
        sigma = np.log(self.initial_sigma()) if self.n_sigma else np.zeros(0)
        return np.append(sigma, np.log(self.scale_quantile(0.5))) if self.scale_prior else sigma

    def initial_sigma(self) -> np.ndarray:
        """A data-driven starting noise level per component: RMS of the observed weights / 10."""
        out = []
        for k in range(len(self.emulator.components)):
            w = self.weights[:, self.component_of_weight == k]
            out.append(float(torch.sqrt(torch.mean(w**2))) / 10 + 1e-6)
        return np.array(out)

    def fix_gp_variance(self, params: np.ndarray) -> None:
        """Hold the GP covariance (and the parameter shift's Jacobian) at their values at
        ``params`` (5,) (``gp_variance="mode"``)."""
        self.fixed_gp_cov = self.fixed_shift = None
        params = torch.as_tensor(params)
        shift = self.shift_factor(params, differentiable=False)
        with torch.no_grad():
            self.fixed_gp_cov = self.gp_moments(params)[1]
        self.fixed_shift = shift
        self._density = None

    def gp_variance_spread(self, draws: np.ndarray, n: int = 50, seed: int = 0) -> GpVarianceSpread:
        """How the GP variance (the covariance's diagonal) over ``n`` posterior draws (k, 5)
        compares with the fixed one."""
        rng = np.random.default_rng(seed)
        pick = draws[rng.choice(len(draws), size=min(n, len(draws)), replace=False)]
        fixed = torch.diagonal(self.fixed_gp_cov, dim1=-2, dim2=-1)
        with torch.no_grad():
            variances = [
                self.emulator.predict_weights(self.inputs(torch.as_tensor(p)), white_noise=self.gp_white_noise)[1]
                for p in pick
            ]
        ratios = np.stack([(v.T / fixed).numpy() for v in variances])
        return GpVarianceSpread(
            ratio_median=float(np.median(ratios)),
            ratio_5=float(np.percentile(ratios, 5)),
            ratio_95=float(np.percentile(ratios, 95)),
        )

    def model_warnings(self, scale_median: float | None = None) -> list[str]:
        """What the summary must say about the model itself: an emulator without a held-out
        excess, or observations it fits far worse than its held-out materials (the posterior
        median of the emulator scale, ``scale_median``, beyond its prior's 99 % quantile)."""
        if self.emulator_error and self.emulator.held_out_excess is None:
            return [
                "this emulator has no held-out error model (fitted before skinid measured it): its error "
                "beyond the GP variance is not in these intervals; refit it with 'skinid surrogate fit'"
            ]
        if self.scale_prior and scale_median is not None:
            limit = self.scale_quantile(0.99)
            if scale_median > limit:
                return [
                    f"the emulator scale is {scale_median:.3g} (its prior's 99 % quantile: {limit:.3g}): the "
                    "emulator fits these observations far worse than any held-out material, and the intervals "
                    "widen for it; check the measurement's frame, units and strain measure, and whether the "
                    "model lacks physics ('skinid check')"
                ]
        return []

    def error_budget(self, values: np.ndarray) -> ErrorBudget:
        """Which term dominates the weights' variance at constrained ``values`` (dim,)."""
        params, sigma, scale = self.latents(torch.as_tensor(values, dtype=torch.float64))
        with torch.no_grad():
            gp = self.gp_share * torch.diagonal(self.gp_moments(params)[1], dim1=-2, dim2=-1).T
            excess = torch.diagonal(self.excess_cov, dim1=-2, dim2=-1).T
            factor = self.shift_factor(params)
            shift = torch.zeros_like(gp) if factor is None else torch.sum(factor.detach() ** 2, -1).T
            terms = [self.noise_variance(sigma), scale * gp, scale * excess, scale * self.truncation_var, scale * shift]
            total = sum(terms)
            shares = [float(torch.mean(term / total)) for term in terms]
        return ErrorBudget(*shares)


def pyro_prior(posterior: SkinPosterior) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The priors in Pyro's language: params (5,), sigma (n_sigma,) (empty with known noise) and
    the emulator scale (1 when it is not sampled)."""
    lo, span = posterior.lower, posterior.span
    params = torch.stack(
        [pyro.sample(name, dist.Uniform(lo[i], lo[i] + span[i])) for i, name in enumerate(PARAM_NAMES)]
    )
    sigma = (
        torch.stack(
            [
                pyro.sample(name, dist.HalfCauchy(torch.tensor(posterior.noise_scale, dtype=torch.float64)))
                for name in posterior.names[5 : 5 + posterior.n_sigma]
            ]
        )
        if posterior.noise == "halfcauchy"
        else torch.zeros(0, dtype=torch.float64)
    )
    scale = (
        pyro.sample("emulator_scale", posterior.scale_distribution())
        if posterior.scale_prior
        else torch.ones((), dtype=torch.float64)
    )
    return params, sigma, scale


def prior_draws(posterior: SkinPosterior, n: int, seed: int) -> np.ndarray:
    """(n, dim) seeded draws of :func:`pyro_prior` (Pyro's ``Predictive``), theta in degrees."""
    from pyro.infer import Predictive

    with torch.random.fork_rng():
        torch.manual_seed(seed)
        draws = Predictive(pyro_prior, num_samples=n, return_sites=list(posterior.names))(posterior)
    return np.column_stack([draws[name].reshape(n).numpy() for name in posterior.names])


def draw_from_model(posterior: SkinPosterior, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One draw of the whole model: values (dim,) from the priors (theta in degrees) and PC
    weights (n_obs, G) from the likelihood at them (:func:`pyro_model` with its observation
    unconditioned, GP covariance and shift Jacobian at the drawn parameters). Data a posterior
    of ``posterior``'s setup is calibrated on by construction (simulation-based calibration)."""
    from pyro.infer import Predictive

    with torch.random.fork_rng():
        torch.manual_seed(seed)
        draw = Predictive(pyro.poutine.uncondition(pyro_model), num_samples=1)(posterior)
    values = np.array([float(draw[name].reshape(())) for name in posterior.names])
    n_obs, n_weights = posterior.weights.shape
    weights = draw["weights"].reshape(n_weights, n_obs).T  # the likelihood's order is (g, o)
    return values, weights.detach().numpy()


def psd_root(cov: np.ndarray) -> np.ndarray:
    """R (k, k) with R R^T = cov for a symmetric positive semi-definite cov (k, k)."""
    eigenvalues, vectors = np.linalg.eigh(cov)
    return vectors * np.sqrt(np.maximum(eigenvalues, 0.0))


def coupled_covariance(blocks: torch.Tensor, factor: torch.Tensor, scale: torch.Tensor | float) -> torch.Tensor:
    """(G n_obs, G n_obs) covariance of every weight, in the order (g, o): the per-weight
    ``blocks`` (G, n_obs, n_obs) plus lambda U U^T of the parameter shift, ``factor`` U (G, n_obs, k)."""
    flat = factor.reshape(-1, factor.shape[-1])
    return torch.block_diag(*blocks) + scale * flat @ flat.T


def pyro_model(posterior: SkinPosterior) -> None:
    """The same model in Pyro's language (reference for :class:`SkinPosterior`)."""
    params, sigma, scale = pyro_prior(posterior)
    mean, cov = posterior.moments(params, sigma, scale)
    factor = posterior.shift_factor(params)
    if factor is None:
        likelihood = dist.MultivariateNormal(mean.T, covariance_matrix=cov).to_event(1)
        pyro.sample("weights", likelihood, obs=posterior.weights.T)
        return
    likelihood = dist.MultivariateNormal(mean.T.reshape(-1), covariance_matrix=coupled_covariance(cov, factor, scale))
    pyro.sample("weights", likelihood, obs=posterior.weights.T.reshape(-1))
