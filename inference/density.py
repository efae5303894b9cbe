"""The log posterior of :class:`~inference.model.SkinPosterior` and its gradient in closed form.

NUTS evaluates the density and its gradient tens of times per draw; torch's per-operation
overhead (~30 small operations and their backward) dominates those tiny computations. Here
the density with the GP variance held fixed (``gp_variance="mode"``) is written out in numpy
with its analytic gradient (RBF GP mean, likelihood, priors, Jacobian of the transform),
about 3x faster, and wrapped as a torch autograd function so Pyro's NUTS uses it unchanged.
With ``gp_variance="exact"`` the autograd density is used (its O(n^2) triangular solves
dominate and are more stable than any closed form through K^-1). The tests compare both.

Notation: u unconstrained (dim,), z = sigmoid(u[:5]), params = lower + z * span,
x the 7 emulator inputs of each observation in the emulator's unit box. In the rotated weights
W_g^T w_g (W_g, e_g fixed: :meth:`SkinPosterior.fixed_eigen`) the likelihood is a product of
independent normals of variance lambda e_g + s_g, lambda the emulator scale (1 when it is not
sampled) and s_g = sigma_c(g)^2 (HalfCauchy noise) or 1 (known noise, whitened by W_g). With the
parameter shift (``emulator_shift``) the rotated weights also share lambda U U^T (U rotated the
same way, fixed with the GP variance), a rank-5 term: the Gaussian is then evaluated by the
Woodbury identity and the matrix determinant lemma with a 5 x 5 capacitance matrix.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.special import gammaln


class FusedLogDensity:
    """Numpy log density and gradient of a :class:`SkinPosterior` (same value, same inputs)."""

    def __init__(self, posterior):
        emu = posterior.emulator
        bank = emu.gps
        self.x_train = bank.x_train.cpu().numpy()
        self.length_scale = bank.length_scale.cpu().numpy()  # (G, d)
        self.inv_l2 = 1.0 / self.length_scale**2
        self.constant = bank.constant.cpu().numpy()
        self.alpha = bank.alpha.cpu().numpy()
        self.y_mean, self.y_std = bank.y_mean.cpu().numpy(), bank.y_std.cpu().numpy()
        self.scaled_train_t = np.ascontiguousarray(bank.scaled_train.cpu().numpy().transpose(0, 2, 1))  # (G, d, n)
        self.scaled_train_sq = bank.scaled_train_sq.cpu().numpy()  # (G, n): |x_train / l|^2
        if posterior.gp_variance != "mode":
            raise ValueError("the closed form covers gp_variance='mode'; 'exact' uses autograd")
        self.in_lower, self.in_span = emu.lower, emu.input_span
        self.lower, self.span = posterior.lower.numpy(), posterior.span.numpy()
        self.design_unit = (posterior.design_inputs.numpy() - self.in_lower[5:]) / self.in_span[5:]  # (n_obs, 2)
        self.param_scale = self.span / self.in_span[:5]  # d(unit input) / dz
        # W (G, n_obs, n_obs), e (n_obs, G), log det of the known noise (0 with HalfCauchy noise)
        self.rotation, self.fixed_var, self.log_det_noise = posterior.fixed_eigen()
        self.weights = self.rotate(posterior.weights.numpy())
        self.component = posterior.component_of_weight.numpy()
        self.n_comp = len(emu.components)
        self.halfcauchy = posterior.noise == "halfcauchy"
        self.noise_scale = posterior.noise_scale
        self.n_sigma = posterior.n_sigma
        self.scale_prior = posterior.scale_prior
        shift = posterior.fixed_shift  # (G, n_obs, 5) or None
        self.shift = None if shift is None else self.rotate(shift.numpy().transpose(1, 0, 2)).reshape(-1, 5)

    def rotate(self, a: np.ndarray) -> np.ndarray:
        """W_g^T a_g for every weight g: a (n_obs, G, ...) -> (n_obs, G, ...)."""
        return np.einsum("gpo,pg...->og...", self.rotation, a)

    def gp_mean(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """GP mean (n_obs, G) and its gradient (n_obs, G, 7) at unit inputs x (n_obs, 7)."""
        a = x[None] / self.length_scale[:, None]  # (G, n_obs, d), as in GPBank
        sq = (a**2).sum(-1)[..., None] + self.scaled_train_sq[:, None] - 2 * a @ self.scaled_train_t
        beta = np.exp(-0.5 * np.maximum(sq, 0.0)) * (self.constant[:, None] * self.alpha)[:, None]  # (G, n_obs, n)
        s0 = beta.sum(-1)
        s1 = beta @ self.x_train  # (G, n_obs, d)
        mean = (s0 * self.y_std[:, None] + self.y_mean[:, None]).T
        dmean = -(self.y_std[:, None, None] * (s0[..., None] * x[None] - s1) * self.inv_l2[:, None]).transpose(1, 0, 2)
        return mean, dmean

    def __call__(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        """(log density, gradient (dim,)) at the unconstrained vector u."""
        z = 1.0 / (1.0 + np.exp(-u[:5]))
        unit = (self.lower + z * self.span - self.in_lower[:5]) / self.in_span[:5]
        x = np.concatenate([np.broadcast_to(unit, (len(self.design_unit), 5)), self.design_unit], axis=1)
        mean, dmean = self.gp_mean(x)
        mean, dmean = self.rotate(mean), self.rotate(dmean)
        sigma = np.exp(u[5 : 5 + self.n_sigma])
        scale = np.exp(u[-1]) if self.scale_prior else 1.0
        total = scale * self.fixed_var + (sigma[self.component] ** 2 if self.halfcauchy else 1.0)
        r = self.weights - mean
        loglik, d_mean, d_total, d_shared = self.gaussian(r, total, scale)
        loglik -= 0.5 * self.log_det_noise
        dx = np.einsum("og,ogd->d", d_mean, dmean)
        grad = np.zeros_like(u)
        dz = z * (1 - z)
        grad[:5] = dx[:5] * self.param_scale * dz + (1 - 2 * z)
        # uniform prior -sum log span + Jacobian sum log(span z (1 - z)): the spans cancel
        value = loglik - np.sum(np.logaddexp(0, -u[:5]) + np.logaddexp(0, u[:5]))
        if self.halfcauchy:
            s = self.noise_scale
            value += np.sum(np.log(2 / (np.pi * s)) - np.log1p((sigma / s) ** 2)) + np.sum(u[5 : 5 + self.n_sigma])
            d_sigma = np.bincount(
                self.component, weights=(d_total * 2 * sigma[self.component]).sum(0), minlength=self.n_comp
            )
            d_sigma += -2 * sigma / (s**2 + sigma**2)
            grad[5 : 5 + self.n_sigma] = d_sigma * sigma + 1.0
        if self.scale_prior:  # InverseGamma(a, b) of lambda = e^v, with the Jacobian e^v
            a, b = self.scale_prior
            value += a * np.log(b) - gammaln(a) - a * u[-1] - b / scale
            grad[-1] = (np.sum(d_total * self.fixed_var) + d_shared) * scale - a + b / scale
        return float(value), grad

    def gaussian(self, r: np.ndarray, total: np.ndarray, scale: float) -> tuple[float, np.ndarray, np.ndarray, float]:
        """Log density of the rotated residuals r (n_obs, G) with variances ``total`` (n_obs, G)
        (plus ``scale`` U U^T with the parameter shift), and its derivatives in the mean
        (n_obs, G), in ``total`` (n_obs, G) and in lambda through U U^T (scalar)."""
        if self.shift is None:
            loglik = -0.5 * np.sum(r**2 / total + np.log(2 * np.pi * total))
            return loglik, r / total, 0.5 * (r**2 / total**2 - 1 / total), 0.0
        d, rr, shift = total.ravel(), r.ravel(), self.shift  # Sigma = D + scale U U^T
        scaled = shift / d[:, None]  # D^-1 U (N, 5)
        inner = shift.T @ scaled  # U^T D^-1 U (5, 5)
        capacitance_inv = np.linalg.inv(np.eye(5) + scale * inner)
        projected = scaled @ capacitance_inv  # D^-1 U C^-1
        v = rr / d - scale * projected @ (scaled.T @ rr)  # Sigma^-1 r
        log_det = np.sum(np.log(d)) - np.linalg.slogdet(capacitance_inv)[1]
        loglik = -0.5 * (rr @ v + log_det + rr.size * np.log(2 * np.pi))
        inv_diag = 1 / d - scale * np.sum(projected * scaled, axis=1)  # diag Sigma^-1
        # sum(U * Sigma^-1 U) = tr(U^T D^-1 U) - scale tr(U^T D^-1 U C^-1 U^T D^-1 U)
        trace = np.trace(inner) - scale * np.sum((inner @ capacitance_inv) * inner)
        d_shared = 0.5 * (np.sum((shift.T @ v) ** 2) - trace)
        return loglik, v.reshape(r.shape), 0.5 * (v**2 - inv_diag).reshape(r.shape), d_shared


class _Potential(torch.autograd.Function):
    """Minus the log density as a torch scalar whose gradient comes from the closed form."""

    @staticmethod
    def forward(ctx, u, density):
        value, grad = density(u.detach().numpy())
        ctx.save_for_backward(torch.as_tensor(-grad))
        return torch.tensor(-value, dtype=u.dtype)

    @staticmethod
    def backward(ctx, grad_output):
        (grad,) = ctx.saved_tensors
        return grad_output * grad, None


def fused_potential(u: torch.Tensor, density: FusedLogDensity) -> torch.Tensor:
    return _Potential.apply(u, density)
