"""PCA and GP building blocks against independent references (scikit-learn, finite differences)."""

import numpy as np
import pytest
import torch
from sklearn.decomposition import PCA

from surrogate.gp import GPBank, fit_gps
from surrogate.pca import StrainPCA


def low_rank_fields(n_rows=60, n_cells=40, rank=3, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n_rows, rank)) @ rng.normal(size=(rank, n_cells)) + rng.normal(size=n_cells)


def test_pca_matches_sklearn_on_standardised_fields():
    x = low_rank_fields(rank=6) + 0.01 * np.random.default_rng(1).normal(size=(60, 40))
    pca = StrainPCA(n_components=5).fit(x)
    z = (x - x.mean(0)) / x.std(0)
    ref = PCA(n_components=5).fit(z)
    np.testing.assert_allclose(pca.explained_variance_ratio_[:5], ref.explained_variance_ratio_, rtol=1e-10)
    np.testing.assert_allclose(np.abs(pca.transform(x)), np.abs(ref.transform(z)), atol=1e-9)


def test_pca_threshold_picks_the_rank_and_reconstructs_exactly():
    x = low_rank_fields(rank=3)
    pca = StrainPCA(0.99).fit(x)
    assert pca.n_components_ == 3
    np.testing.assert_allclose(pca.inverse_transform(pca.transform(x)), x, atol=1e-10)
    assert pca.explained_variance(x)[-1] == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("bad", [0, 1.5, 100, "a"])
def test_pca_refuses_bad_component_counts(bad):
    with pytest.raises(ValueError, match="n_components"):
        StrainPCA(bad).fit(low_rank_fields())


def test_pca_refuses_nan():
    x = low_rank_fields()
    x[3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        StrainPCA().fit(x)


@pytest.fixture(scope="module")
def fitted_gps():
    rng = np.random.default_rng(3)
    x = rng.uniform(size=(80, 7))
    y = np.column_stack([np.sin(3 * x[:, 0]) + x[:, 4] ** 2, np.cos(2 * x[:, 1]) * x[:, 5]])
    y += 1e-3 * rng.normal(size=y.shape)
    return fit_gps(x, y, restarts=1, n_jobs=1)


def test_torch_bank_matches_sklearn_mean_and_variance(fitted_gps):
    bank = GPBank.from_sklearn(fitted_gps)
    x = np.random.default_rng(4).uniform(-0.1, 1.1, size=(50, 7))
    mean, var = bank(torch.as_tensor(x))
    for g, gp in enumerate(fitted_gps):
        m, s = gp.predict(x, return_std=True)
        np.testing.assert_allclose(mean[:, g].numpy(), m, rtol=0, atol=1e-8 * np.abs(m).max())
        np.testing.assert_allclose(np.sqrt(var[:, g].numpy()), s, rtol=0, atol=1e-8 * s.max())


@pytest.mark.parametrize("output", [0, 1], ids=["mean", "variance"])
def test_torch_bank_gradients_match_central_differences(fitted_gps, output):
    bank = GPBank.from_sklearn(fitted_gps)
    x = torch.tensor(np.random.default_rng(5).uniform(size=(3, 7)), requires_grad=True)
    f = lambda z: bank(z)[output].sum()  # noqa: E731
    (grad,) = torch.autograd.grad(f(x), x)
    h = 1e-5
    numeric = np.zeros((3, 7))
    for i in range(3):
        for j in range(7):
            step = torch.zeros(3, 7, dtype=torch.float64)
            step[i, j] = h
            numeric[i, j] = (f(x + step) - f(x - step)).item() / (2 * h)
    np.testing.assert_allclose(grad.numpy(), numeric, rtol=0, atol=1e-5 * np.abs(numeric).max())
