"""Measured fields and their noise: the stated noise model, whitening, the model-error term.

Noise model: independent strain components with the stated standard deviations sd_c and a
spatial correlation (1 - w) RBF(l) + w I between points (:func:`inference.noise.correlation_matrix`).
Whitening uses the symmetric inverse square root of the covariance, so whitened values stay
attached to their points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from inference.noise import correlation_matrix, noise_fields


@dataclass(frozen=True)
class NoiseModel:
    """Stated measurement noise: sd (3,) per strain component, correlation length [mm], nugget.
    Frozen: its cache of matrix roots holds for these values only."""

    sd: np.ndarray
    length: float = 0.0
    nugget: float = 1.0
    _roots: dict = field(default_factory=dict, repr=False, compare=False)  # cached matrix (inverse) square roots

    def __post_init__(self):
        object.__setattr__(self, "sd", np.asarray(self.sd, dtype=float))
        if self.sd.shape != (3,) or not np.all(self.sd > 0):
            raise ValueError(f"noise sd must be three positive numbers (xx, yy, xy), got {self.sd}")
        correlation_matrix(np.zeros((1, 2)), self.length, self.nugget)  # validates both

    def whiteners(
        self, xy: np.ndarray, model_sd: np.ndarray | None = None, model_correlation: tuple[float, float] = (0.0, 1.0)
    ) -> list[np.ndarray]:
        """Symmetric Sigma_c^(-1/2) (m, m) per component c for points xy (m, 2), cached.

        Sigma_c = sd_c^2 R + D_c R_m D_c: the correlated noise plus a model-form error of
        standard deviation D_c = diag(``model_sd[:, c]``) (m, 3) and correlation R_m of
        ``model_correlation`` = (length [mm], nugget) (``model_sd`` None: no model error).
        """
        key = ("whiten", xy.tobytes(), None if model_sd is None else model_sd.tobytes(), model_correlation)
        if key not in self._roots:
            corr = correlation_matrix(xy, self.length, self.nugget)
            if model_sd is None:
                root = inverse_sqrt(corr)
                self._roots[key] = [root / s for s in self.sd]
            else:
                model_corr = correlation_matrix(xy, *model_correlation)
                self._roots[key] = [
                    inverse_sqrt(s**2 * corr + model_sd[:, c, None] * model_corr * model_sd[None, :, c])
                    for c, s in enumerate(self.sd)
                ]
        return self._roots[key]

    def noise_scaling(
        self, residual: np.ndarray, xy: np.ndarray, model_sd: np.ndarray, model_correlation: tuple[float, float]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(z, mu), each (3m,): r^T (s^2 Sigma_c + D_c R_m D_c)^-1 r summed over the components c
        of ``residual`` (m, 3) at points xy (m, 2) equals sum z^2 / (s^2 + mu) for every noise
        factor s (model error as in :meth:`whiteners`). With W_c = Sigma_c^(-1/2) and
        W_c D_c R_m D_c W_c = Q diag(mu) Q^T: z = Q^T W_c r; one eigen-decomposition per
        component instead of one whitening per factor."""
        model_corr = correlation_matrix(xy, *model_correlation)
        z, mu = [], []
        for c, root in enumerate(self.whiteners(xy)):
            model = model_sd[:, c, None] * model_corr * model_sd[None, :, c]
            values, vectors = np.linalg.eigh(root @ model @ root)
            z.append(vectors.T @ (root @ residual[:, c]))
            mu.append(np.maximum(values, 0.0))
        return np.concatenate(z), np.concatenate(mu)

    def whiten(
        self, residual: np.ndarray, xy: np.ndarray, masks: np.ndarray, model_error: ModelError | None = None
    ) -> np.ndarray:
        """(n_obs, n_pts, 3) residual -> whitened residual (NaN off the mask).

        ``xy`` (n_obs, n_pts, 2) points, ``masks`` (n_obs, n_pts), ``model_error`` or None: see
        :meth:`whiteners`."""
        out = np.full(residual.shape, np.nan)
        for o, mask in enumerate(masks):
            extra = None if model_error is None else model_error.sd[o, mask]
            correlation = (0.0, 1.0) if model_error is None else (model_error.length, model_error.nugget)
            for c, root in enumerate(self.whiteners(xy[o, mask], extra, correlation)):
                out[o, mask, c] = root @ residual[o, mask, c]
        return out

    def sample(self, xy: np.ndarray, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """Noise fields (*shape, m, 3) drawn from this model at points xy (m, 2)."""
        key = ("root", xy.tobytes())
        if key not in self._roots:  # eigen-root: also valid for length 0 or nugget 1
            w, v = np.linalg.eigh(correlation_matrix(xy, self.length, self.nugget))
            self._roots[key] = v * np.sqrt(np.maximum(w, 0))
        return noise_fields(self._roots[key], self.sd, shape, rng)


@dataclass(frozen=True)
class ModelError:
    """The model's own error at the measured points (e.g. its discretisation error), carried
    next to the noise as a Gaussian field: sd (n_obs, n_pts, 3) [strain] and the correlation
    (1 - nugget) RBF(length) + nugget I between points (length 0: independent)."""

    sd: np.ndarray
    length: float = 0.0
    nugget: float = 0.0

    @cached_property
    def _unit_field(self) -> NoiseModel:
        """A unit-sd field with this correlation (its square roots cached per point set)."""
        return NoiseModel(np.ones(3), self.length, self.nugget)

    def sample(
        self, xy: np.ndarray, o: int, mask: np.ndarray, shape: tuple[int, ...], rng: np.random.Generator
    ) -> np.ndarray:
        """Draws (*shape, m, 3) of observation ``o``'s error at its measured points xy (m, 2)."""
        return self._unit_field.sample(xy, shape, rng) * self.sd[o, mask]


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
        fields: (n_obs, n_pts, 3) log strain, NaN off the mask (observations NaN-padded to the
            largest point count; their xy zero-padded).
        masks: (n_obs, n_pts) True where a point is measured.
        xy: (n_obs, n_pts, 2) points [mm].
        noise: the stated measurement noise.
        model_error: the model's own error at the points (discretisation) or None, carried as
            a correlated variance next to the noise.
    """

    fields: np.ndarray
    masks: np.ndarray
    xy: np.ndarray
    noise: NoiseModel
    model_error: ModelError | None = None

    @classmethod
    def from_points(cls, observations: list, noise: NoiseModel) -> Data:
        """From observations with ``xy`` (n_o, 2) and ``strain`` (n_o, 3) (e.g. measurements)."""
        n = max(len(o.xy) for o in observations)
        fields = np.full((len(observations), n, 3), np.nan)
        xy = np.zeros((len(observations), n, 2))
        masks = np.zeros((len(observations), n), bool)
        for i, o in enumerate(observations):
            fields[i, : len(o.xy)], xy[i, : len(o.xy)], masks[i, : len(o.xy)] = o.strain, o.xy, True
        return cls(fields, masks, xy, noise)

    def with_model_error(self, model_error: ModelError | None) -> Data:
        return Data(self.fields, self.masks, self.xy, self.noise, model_error)

    def with_noise_factor(self, factor: float) -> Data:
        """The same data with the stated noise sd multiplied by ``factor`` (the model error kept)."""
        noise = NoiseModel(self.noise.sd * factor, self.noise.length, self.noise.nugget)
        return Data(self.fields, self.masks, self.xy, noise, self.model_error)

    @property
    def n(self) -> int:
        return int(self.masks.sum()) * 3

    @property
    def total_sd(self) -> np.ndarray:
        """(n_obs, n_pts, 3) per-point sd of noise and model error together."""
        sd = np.broadcast_to(self.noise.sd, self.fields.shape)
        return sd if self.model_error is None else np.sqrt(sd**2 + self.model_error.sd**2)

    def standardised(self, model_fields: np.ndarray) -> np.ndarray:
        """(data - model) / total sd per component, NaN off the mask (still spatially correlated)."""
        return (self.fields - model_fields) / self.total_sd

    def point_mean_square(self, model_fields: np.ndarray) -> np.ndarray:
        """(n_obs, n_pts) mean over the three components of the squared standardised residual
        (noise and carried model error alone: 1 on average), NaN off the mask."""
        return np.nanmean(self.standardised(model_fields) ** 2, axis=2)

    def whitened_residual(self, model_fields: np.ndarray) -> np.ndarray:
        """(n_obs, n_pts, 3) model fields -> the measurement's whitened residual, same shape (NaN
        off the mask), under the stated noise and the carried model error."""
        return self.noise.whiten(self.fields - model_fields, self.xy, self.masks, self.model_error)

    def chi2_of_noise_factor(self, model_fields: np.ndarray) -> Callable[[float], float]:
        """chi^2(s) of the residual when the stated noise sd is multiplied by s and the carried
        model error kept (:meth:`model_error_spectrum`: one decomposition for every s)."""
        if self.model_error is None:
            r = stack(self.whitened_residual(model_fields), self.masks)
            return lambda s: float(r @ r) / s**2
        z, mu = self.model_error_spectrum(model_fields)
        return lambda s: float(np.sum(z**2 / (s**2 + mu)))

    def model_error_spectrum(self, model_fields: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(z, mu), each (n,), of the residual ``fields - model_fields`` (n_obs, n_pts, 3): with
        the stated noise sd times s and the carried model error times k its chi^2 is
        sum z^2 / (s^2 + k^2 mu), and the log-determinant of that covariance is
        sum log(s^2 + k^2 mu) plus a constant (:meth:`NoiseModel.noise_scaling`).

        Raises:
            ValueError: the data carry no model error."""
        if self.model_error is None:
            raise ValueError("no model error is carried")
        error, parts = self.model_error, []
        correlation = (error.length, error.nugget)
        for o, mask in enumerate(self.masks):
            residual = (self.fields - model_fields)[o, mask]
            parts.append(self.noise.noise_scaling(residual, self.xy[o, mask], error.sd[o, mask], correlation))
        z, mu = (np.concatenate(a) for a in zip(*parts))
        return z, mu

    def whiten(self, fields: np.ndarray) -> np.ndarray:
        """Stacked whitened (n,) of any (n_obs, n_pts, 3) field difference."""
        return stack(self.noise.whiten(fields, self.xy, self.masks, self.model_error), self.masks)
