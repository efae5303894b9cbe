"""Gaussian-process regression of PC weights: scikit-learn fit, differentiable torch predictor.

One GP per PC weight, all on the same training rows. Inputs are the 7 model inputs
(mu, k1, k2, kappa, theta, alpha11*t, alpha22*t) scaled to the unit box. Kernel:

    k(x, x') = c * exp(-|(x - x') / l|^2 / 2) + w * [x == x']

(ARD RBF times a constant, plus white noise), targets normalised to zero mean and unit variance.
:class:`GPBank` evaluates all GPs at once in torch (float64) and returns the same predictive
mean and variance as scikit-learn's ``predict(return_std=True)`` -- the variance includes the
white-noise level -- with autograd gradients.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import numpy as np
import torch
from joblib import Parallel, delayed
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel


def make_kernel(n_inputs: int):
    """Constant x ARD RBF + white noise, with bounds suited to unit-box inputs."""
    return ConstantKernel(1.0, (1e-3, 1e3)) * RBF(
        np.ones(n_inputs), (1e-2, 1e3)
    ) + WhiteKernel(1e-4, (1e-10, 1e-1))


def fit_gp(x: np.ndarray, y: np.ndarray, restarts: int = 2, seed: int = 0) -> GaussianProcessRegressor:
    """Fit one GP: ``x`` (n, d) in the unit box, ``y`` (n,) one PC weight."""
    gp = GaussianProcessRegressor(
        kernel=make_kernel(x.shape[1]),
        normalize_y=True,
        n_restarts_optimizer=restarts,
        random_state=seed,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # hyper-parameters at a bound
        gp.fit(x, y)
    return gp


def fit_gps(
    x: np.ndarray, y: np.ndarray, restarts: int = 2, seed: int = 0, n_jobs: int = -1
) -> list[GaussianProcessRegressor]:
    """Fit one GP per column of ``y`` (n, G), in parallel processes."""
    return Parallel(n_jobs=n_jobs)(
        delayed(fit_gp)(x, y[:, g], restarts, seed + g) for g in range(y.shape[1])
    )


def kernel_parameters(gp: GaussianProcessRegressor) -> tuple[float, np.ndarray, float]:
    """(constant c, length scales l (d,), white-noise level w) of a fitted GP."""
    params = gp.kernel_.get_params()
    return (
        float(params["k1__k1__constant_value"]),
        np.atleast_1d(params["k1__k2__length_scale"]).astype(float),
        float(params["k2__noise_level"]),
    )


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
    def from_sklearn(cls, gps: list[GaussianProcessRegressor]) -> GPBank:
        x_train = gps[0].X_train_
        for gp in gps[1:]:
            if not np.array_equal(gp.X_train_, x_train):
                raise ValueError("all GPs of a bank must share their training inputs")
        kernels = [kernel_parameters(gp) for gp in gps]
        return cls(
            {
                "x_train": x_train,
                "length_scale": np.stack([k[1] for k in kernels]),
                "constant": np.array([k[0] for k in kernels]),
                "noise": np.array([k[2] for k in kernels]),
                "alpha": np.stack([gp.alpha_ for gp in gps]),
                "chol": np.stack([gp.L_ for gp in gps]),
                "y_mean": np.array([np.squeeze(gp._y_train_mean) for gp in gps]),
                "y_std": np.array([np.squeeze(gp._y_train_std) for gp in gps]),
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

    def forward(self, x: torch.Tensor, return_var: bool = True):
        """Predictive mean (B, G) and, if asked, variance (B, G) at unit-box inputs x (B, d)."""
        k = self.cross_covariance(x.to(torch.float64))
        mean = torch.einsum("gbn,gn->bg", k, self.alpha) * self.y_std + self.y_mean
        if not return_var:
            return mean
        v = torch.linalg.solve_triangular(self.chol, k.transpose(1, 2), upper=False)  # (G, n, B)
        var = (self.constant + self.noise)[:, None] - (v**2).sum(1)
        return mean, var.clamp_min(0.0).T * self.y_std**2
