"""Gaussian-process regression of PC weights: scikit-learn fit, differentiable torch predictor.

One GP per PC weight, all on the same training rows. Inputs are the 7 model inputs
(mu, k1, k2, kappa, theta, alpha11*t, alpha22*t) scaled to the unit box. Kernel:

    k(x, x') = c * exp(-|(x - x') / l|^2 / 2) + w * [x == x']

(ARD RBF times a constant, plus white noise), fitted to targets standardised to zero mean and
unit variance. The standardisation is ours (:class:`StandardisedGP` keeps its mean and sd; the
regressor is fitted with ``normalize_y=False`` on the standardised targets), which is the model
scikit-learn fits with ``normalize_y=True`` -- same likelihood, hyper-parameters and predictions --
without reading its private ``_y_train_mean``/``_y_train_std``.
:class:`GPBank` evaluates all GPs at once in torch (float64) and returns the same predictive
mean and variance as :meth:`StandardisedGP.predict` (scikit-learn's ``predict(return_std=True)``
in target units) -- the variance includes the white-noise level -- with autograd gradients.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from joblib import Parallel, delayed
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel


def make_kernel(n_inputs: int):
    """Constant x ARD RBF + white noise, with bounds suited to unit-box inputs."""
    return ConstantKernel(1.0, (1e-3, 1e3)) * RBF(np.ones(n_inputs), (1e-2, 1e3)) + WhiteKernel(1e-4, (1e-10, 1e-1))


def standardisation(y: np.ndarray) -> tuple[float, float]:
    """Mean and sd of targets ``y`` (n,); an sd below 10 machine epsilons (constant targets) is
    replaced by 1, as scikit-learn's ``normalize_y=True`` does."""
    mean, std = float(np.mean(y)), float(np.std(y))
    return mean, (1.0 if std < 10 * np.finfo(float).eps else std)


@dataclass
class StandardisedGP:
    """A scikit-learn GP fitted (``normalize_y=False``) to the standardised targets
    ``(y - y_mean) / y_std``; :meth:`predict` answers in target units."""

    gp: GaussianProcessRegressor
    y_mean: float
    y_std: float

    def predict(self, x: np.ndarray, return_std: bool = False):
        """Predictive mean (B,) at unit-box inputs x (B, d) and, if asked, sd (B,) (white noise included)."""
        if not return_std:
            return self.y_std * self.gp.predict(x) + self.y_mean
        mean, std = self.gp.predict(x, return_std=True)
        return self.y_std * mean + self.y_mean, self.y_std * std


def fit_gp(x: np.ndarray, y: np.ndarray, restarts: int = 2, seed: int = 0, kernel=None) -> StandardisedGP:
    """Fit one GP: ``x`` (n, d) in the unit box, ``y`` (n,) one PC weight; the optimizer starts
    from ``kernel`` (a fitted GP's ``kernel_``, same bounds) or from :func:`make_kernel`."""
    y_mean, y_std = standardisation(y)
    gp = GaussianProcessRegressor(
        kernel=make_kernel(x.shape[1]) if kernel is None else kernel,
        normalize_y=False,  # standardised here: the same model as normalize_y=True
        n_restarts_optimizer=restarts,
        random_state=seed,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # hyper-parameters at a bound
        gp.fit(x, (y - y_mean) / y_std)
    return StandardisedGP(gp, y_mean, y_std)


def fit_gps(
    x: np.ndarray, y: np.ndarray, restarts: int = 2, seed: int = 0, n_jobs: int = -1, kernels: list | None = None
) -> list[StandardisedGP]:
    """Fit one GP per column of ``y`` (n, G), in parallel processes; ``kernels``: the optimizer's
    starting kernel per GP (see :func:`fit_gp`)."""
    kernels = [None] * y.shape[1] if kernels is None else kernels
    return Parallel(n_jobs=n_jobs)(
        delayed(fit_gp)(x, y[:, g], restarts, seed + g, kernels[g]) for g in range(y.shape[1])
    )


def kernel_parameters(gp: GaussianProcessRegressor) -> tuple[float, np.ndarray, float]:
    """(constant c, length scales l (d,), white-noise level w) of a fitted GP."""
    params = gp.kernel_.get_params()
    return (
        float(params["k1__k1__constant_value"]),
        np.atleast_1d(params["k1__k2__length_scale"]).astype(float),
        float(params["k2__noise_level"]),
    )


def _unnormalised(gp: GaussianProcessRegressor) -> StandardisedGP:
    if gp.normalize_y:
        raise ValueError(
            "a GaussianProcessRegressor fitted with normalize_y=True keeps its target mean and sd in "
            "private attributes; fit it with surrogate.gp.fit_gp (or normalize_y=False)"
        )
    return StandardisedGP(gp, 0.0, 1.0)


class GPBank(torch.nn.Module):
    """G fitted GPs sharing training inputs, evaluated together in torch (float64).

    Buffers (all float64): ``x_train`` (n, d), ``length_scale`` (G, d), ``constant`` (G,),
    ``noise`` (G,), ``alpha`` (G, n), ``chol`` (G, n, n) lower Cholesky factor of the
    training covariance, ``y_mean``/``y_std`` (G,) target normalisation.
    """

    ARRAYS = ("x_train", "length_scale", "constant", "noise", "alpha", "chol", "y_mean", "y_std")

    def __init__(self, arrays: Mapping[str, np.ndarray]):
        super().__init__()
        for name in self.ARRAYS:
            self.register_buffer(name, torch.as_tensor(np.asarray(arrays[name]), dtype=torch.float64))
        # training inputs in length-scale units and their squared norms (G, n, d), (G, n)
        scaled = self.x_train[None] / self.length_scale[:, None]
        self.register_buffer("scaled_train", scaled, persistent=False)
        self.register_buffer("scaled_train_sq", (scaled**2).sum(-1), persistent=False)

    @classmethod
    def from_sklearn(cls, gps: list[StandardisedGP]) -> GPBank:
        """Bank of fitted GPs (:func:`fit_gps`); a bare ``GaussianProcessRegressor`` is accepted
        when fitted with ``normalize_y=False`` (target mean 0, sd 1)."""
        gps = [gp if isinstance(gp, StandardisedGP) else _unnormalised(gp) for gp in gps]
        x_train = gps[0].gp.X_train_
        for g in gps[1:]:
            if not np.array_equal(g.gp.X_train_, x_train):
                raise ValueError("all GPs of a bank must share their training inputs")
        kernels = [kernel_parameters(g.gp) for g in gps]
        return cls(
            {
                "x_train": x_train,
                "length_scale": np.stack([k[1] for k in kernels]),
                "constant": np.array([k[0] for k in kernels]),
                "noise": np.array([k[2] for k in kernels]),
                "alpha": np.stack([g.gp.alpha_ for g in gps]),
                "chol": np.stack([g.gp.L_ for g in gps]),
                "y_mean": np.array([g.y_mean for g in gps], dtype=float),
                "y_std": np.array([g.y_std for g in gps], dtype=float),
            }
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name).cpu().numpy() for name in self.ARRAYS}

    @property
    def n_gps(self) -> int:
        return len(self.constant)

    def cross_covariance(self, x: torch.Tensor) -> torch.Tensor:
        """k(x, x_train) without the white noise: (G, B, n) for x (B, d)."""
        a = x[None] / self.length_scale[:, None]  # (G, B, d)
        base = (a**2).sum(-1, keepdim=True) + self.scaled_train_sq[:, None]  # (G, B, n)
        sq = torch.baddbmm(base, a, self.scaled_train.transpose(1, 2), alpha=-2.0)
        if not sq.requires_grad:  # prediction only: in place, no temporaries
            return torch.exp_(sq.clamp_min_(0.0).mul_(-0.5)).mul_(self.constant[:, None, None])
        return self.constant[:, None, None] * torch.exp(-0.5 * sq.clamp_min(0.0))

    def joint(self, x: torch.Tensor, white_noise: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean (B, G) and joint covariance (G, B, B) of each GP at unit-box inputs
        x (B, d); the white noise, unless ``white_noise`` is False (the latent function's
        covariance), is on the diagonal only. ``forward``'s variance is its diagonal."""
        x = x.to(torch.float64)
        k = self.cross_covariance(x)
        mean = torch.einsum("gbn,gn->bg", k, self.alpha) * self.y_std + self.y_mean
        v = torch.linalg.solve_triangular(self.chol, k.transpose(1, 2), upper=False)  # (G, n, B)
        a = x[None] / self.length_scale[:, None]  # (G, B, d)
        sq = ((a[:, :, None] - a[:, None]) ** 2).sum(-1)
        prior = self.constant[:, None, None] * torch.exp(-0.5 * sq)
        if white_noise:
            prior = prior + torch.diag_embed(self.noise[:, None].expand(-1, len(x)))
        return mean, (prior - v.transpose(1, 2) @ v) * (self.y_std**2)[:, None, None]

    def forward(self, x: torch.Tensor, return_var: bool = True, white_noise: bool = True):
        """Predictive mean (B, G) and, if asked, variance (B, G) at unit-box inputs x (B, d), with
        the white-noise level unless ``white_noise`` is False (the latent function's variance)."""
        k = self.cross_covariance(x.to(torch.float64))
        mean = torch.einsum("gbn,gn->bg", k, self.alpha) * self.y_std + self.y_mean
        if not return_var:
            return mean
        v = torch.linalg.solve_triangular(self.chol, k.transpose(1, 2), upper=False)  # (G, n, B)
        var = (self.constant + self.noise * white_noise)[:, None] - (v**2).sum(1)
        return mean, var.clamp_min(0.0).T * self.y_std**2
