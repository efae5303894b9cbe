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


def test_points_on_a_grid_at_exactly_the_largest_distance_are_fitted():
    """A DIC export on a round-millimetre grid has point pairs exactly 4 h apart, on the last
    bin's edge: they are left out like farther pairs (they indexed past the bins), and the fit
    recovers the field's correlation as on a scattered cloud (length within 20 %, nugget 0.1)."""
    rng = np.random.default_rng(3)
    g = np.arange(-18.0, 18.5, 1.0)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    masks = np.ones((1, len(grid)), bool)
    field = ModelError(np.ones((1, len(grid), 3)), 3.0, 0.3).sample(grid, 0, masks[0], (), rng)[None]
    for h in (1.0, 1.5, 2.0):
        length, nugget = correlation_fit(field, grid[None], masks, h)
        assert abs(length - 3.0) < 0.6 and abs(nugget - 0.3) < 0.1, h


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


class ConvergingForward(ForwardModel):
    """The exact field plus a discretisation error C h^p g (g a fixed smooth field, h the mesh's
    edge cell size [mm]): what a mesh of order p gives near its asymptotic range."""

    def __init__(self, config, exact: np.ndarray, g: np.ndarray, order: float):
        self.config, self.exact, self.g, self.order = config, exact, g, order
        self.names, self.bounds, self.null = ["x"], np.array([[-1.0, 1.0]]), np.zeros(1)

    def evaluate_many(self, points):
        from skinfem.mesh import edge_cell_size

        return [self.exact + edge_cell_size(self.config.mesh) ** self.order * self.g for _ in points]


def smooth_field_and_error(seed: int):
    """A DIC point cloud (xy (1, n, 2), masks), a smooth exact field and a smooth error shape g
    (1, n, 3) [strain], and the exact field as data with a 1e-3 noise model."""
    xy = np.stack([dic_points(18.0, 1.0, np.random.default_rng(seed))])
    masks = np.ones(xy.shape[:2], bool)
    exact = np.stack([np.sin(xy[0] @ [0.2, 0.1])[:, None] * [1e-2, -5e-3, 2e-3]])
    g = np.stack([np.cos(xy[0] @ [0.1, -0.3])[:, None] * [4e-3, 2e-3, 1e-3]])
    return xy, masks, exact, g, Data(exact, masks, xy, NoiseModel(np.full(3, 1e-3), 2.0, 0.3))


def test_the_two_mesh_estimate_at_the_measured_order_gives_each_meshs_error():
    """Meshes converging at the order the check assumes for Q2: from the check mesh and its
    edge refinement alone, the estimate gives the check mesh's error, the refined (carried)
    one, and the edge cell size whose error is half the noise -- each against the closed form.
    A quadratic mesh with two skin layers is advised only a finer edge."""
    from inference.criticism.discretisation import estimate, observed_order, refined_config
    from skinfem.config import load_config
    from skinfem.mesh import edge_cell_size

    config = load_config("small").with_changes(solver={"element_degree": 2}, mesh={"h_edge": 1.0, "skin_layers": 2})
    p = observed_order(config)
    xy, masks, exact, g, data = smooth_field_and_error(3)
    coarse, fine = (ConvergingForward(c, exact, g, p) for c in (config, refined_config(config, "edge")))
    disc = estimate(coarse, fine, np.zeros(1), data, "edge")

    def error_rms(h: float) -> float:
        return float(np.sqrt(np.mean((h**p * g) ** 2)))

    h = edge_cell_size(config.mesh)
    rms = float(np.sqrt(np.mean(exact**2)))
    assert np.isclose(disc.relative, error_rms(h) / rms)
    assert np.isclose(disc.remaining_relative, error_rms(h / 2) / rms)
    assert np.isclose(disc.remaining_sigma, error_rms(h / 2) / 1e-3)
    sd = disc.sd(xy, masks)  # the carried sd: the refined mesh's local error envelope
    assert np.isclose(np.sqrt(np.mean(sd**2)), error_rms(h / 2), rtol=0.15)
    assert np.isclose(error_rms(disc.suggested_h_edge()) / 1e-3, 0.5)
    assert disc.resolved == (disc.remaining_sigma <= 0.5)
    assert not disc.resolved and "mesh.h_edge <=" in disc.summary() and "--config check" not in disc.summary()


class ScaledErrorForward(ConvergingForward):
    """The exact field plus an error ``scale`` g: a mesh whose error has the shape g."""

    def __init__(self, config, exact: np.ndarray, g: np.ndarray, scale: float):
        super().__init__(config, exact, g, 0.0)
        self.scale = scale

    def evaluate_many(self, points):
        return [self.exact + self.scale * self.g for _ in points]


def test_a_quadratic_reference_with_a_share_of_the_error_gives_each_meshs_error():
    """A linear check mesh with error g and a quadratic reference with the assumed share r of it
    (same shape): the estimate gives both meshes' errors and extrapolates at 1 / (1 - r),
    against the closed form."""
    from inference.criticism.discretisation import error_ratio, estimate, refined_config
    from skinfem.config import load_config

    config = load_config("paper")
    r = error_ratio(config, "quadratic")[0]
    _, _, exact, g, data = smooth_field_and_error(4)
    coarse = ScaledErrorForward(config, exact, g, 1.0)
    reference = ScaledErrorForward(refined_config(config, "quadratic"), exact, g, r)
    disc = estimate(coarse, reference, np.zeros(1), data, "quadratic")
    g_rms = float(np.sqrt(np.mean(g**2)))
    assert np.isclose(disc.relative, g_rms / np.sqrt(np.mean(exact**2)))
    assert np.isclose(disc.sigma, g_rms / 1e-3) and np.isclose(disc.remaining_sigma, r * g_rms / 1e-3)
    np.testing.assert_allclose(disc.extrapolated * disc.shift, -g, atol=1e-15)  # f_h + a shift = exact
    assert f"{r:.0%} of the check mesh's" in disc.summary()
    assert not disc.resolved and "quadratic elements (solver.element_degree = 2)" in disc.summary()
