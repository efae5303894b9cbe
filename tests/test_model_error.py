"""The model's own error carried as a correlated field: its length, and calibrated intervals."""

from __future__ import annotations

import numpy as np

from inference.criticism import Data, NoiseModel, calibrate
from inference.criticism.data import ModelError
from inference.criticism.discretisation import correlation_fit
from inference.forward import ForwardModel
from inference.synthetic import dic_points


class SmoothLinearForward(ForwardModel):
    """fields = sum_i x_i g_i with smooth (Gaussian-bump) signatures g_i: like the FE model's
    parameter signatures, they overlap with a correlated model error."""

    def __init__(self, xy: np.ndarray, n: int = 3):
        rng = np.random.default_rng(1)
        centres, widths = rng.uniform(-12, 12, (n, 2)), rng.uniform(4, 8, n)
        bumps = np.exp(-((xy[:, None] - centres) ** 2).sum(-1) / (2 * widths**2))  # (m, n)
        self.A = np.einsum("mn,c->mcn", bumps, [1.0, -0.5, 0.3]).reshape(-1, n) * 1e-2
        self.names = [f"x{i}" for i in range(n)]
        self.bounds, self.null = np.array([[-5.0, 5.0]] * n), np.zeros(n)

    def evaluate_many(self, points):
        return [(self.A @ np.asarray(x)).reshape(1, -1, 3) for x in points]


def test_correlation_of_a_sampled_field_is_recovered():
    """Fields drawn with 70 % of their variance correlated over 3 mm (RBF) at a DIC-like cloud:
    length within 20 %, nugget within 0.1."""
    rng = np.random.default_rng(0)
    points = dic_points(18.0, 1.0, rng)
    xy = np.stack([points, points])
    masks = np.ones(xy.shape[:2], bool)
    error = ModelError(np.ones((2, xy.shape[1], 3)), 3.0, 0.3)
    field = np.stack([error.sample(xy[o], o, masks[o], (), rng) for o in range(2)])
    length, nugget = correlation_fit(field, xy, masks, h=2.0)
    assert abs(length - 3.0) < 0.6 and abs(nugget - 0.3) < 0.1
    white = rng.standard_normal(field.shape)
    assert correlation_fit(white, xy, masks, h=2.0)[1] > 0.95  # independent points


def test_a_correlated_model_error_carried_as_such_gives_calibrated_intervals():
    """Data = model + a correlated model error (sd 1e-3, 4 mm) + small noise, 100 draws. With
    the error carried at its correlation the calibrated parameters' z-scores have unit variance;
    carried as independent per point (the old treatment) their sd is far too small."""
    rng = np.random.default_rng(2)
    xy = dic_points(18.0, 2.0, rng, holes=0)
    world = SmoothLinearForward(xy)
    truth = np.array([1.0, -0.5, 2.0])
    noise, masks = NoiseModel(np.full(3, 1e-4)), np.ones((1, len(xy)), bool)
    sd = np.full((1, len(xy), 3), 1e-3)
    z2 = {0.0: [], 4.0: []}
    for _ in range(100):
        error = ModelError(sd, 4.0).sample(xy, 0, masks[0], (), rng)[None]
        y = world(truth) + error + noise.sample(xy, (1,), rng)
        for length in z2:
            data = Data(y, masks, xy[None], noise, ModelError(sd, length))
            cal = calibrate(world, data, world.null, [0, 1, 2], max_iterations=10)
            z2[length].append(((cal.x - truth) / cal.sd) ** 2)
    assert 0.6 < np.mean(z2[4.0]) < 1.5
    assert np.mean(z2[0.0]) > 3
