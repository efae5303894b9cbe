"""The PCA's per-cell scaling and the information ladder of benchmarks/information_loss.py,
against closed forms, scikit-learn and the full field's Fisher information."""

import numpy as np
import pytest
from sklearn.decomposition import PCA

from surrogate.pca import StrainPCA
from tests.scripts import ROOT, load_script


@pytest.fixture(scope="module")
def loss():
    return load_script(ROOT / "benchmarks" / "information_loss.py", "information_loss")


def membrane_like_fields(n_rows=80, seed=0):
    """Fields (n_rows, 60) of two parameters p (n_rows, 2) in [0, 1]: 40 "band" cells carry
    0.05 p1 a + 0.05 p2 b; 20 "flat" cells (as under a membrane) hold ln 1.05 plus a variation
    between materials of 1e-6 unrelated to p. Returns fields, p and the band's d field / d p (60, 2)."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(size=(n_rows, 2))
    modes = rng.normal(size=(2, 40))
    jacobian = np.zeros((60, 2))
    jacobian[:40] = 0.05 * modes.T
    fields = np.empty((n_rows, 60))
    fields[:, :40] = p @ jacobian[:40].T
    fields[:, 40:] = np.log(1.05) + 1e-6 * rng.normal(size=(n_rows, 20))
    return fields, p, jacobian


def test_unscaled_pca_is_sklearns_pca_of_the_centred_fields():
    fields, _, _ = membrane_like_fields()
    pca = StrainPCA(2, scaling="none").fit(fields)
    ref = PCA(n_components=2).fit(fields)
    np.testing.assert_array_equal(pca.scale_, 1.0)
    np.testing.assert_allclose(np.abs(pca.transform(fields)), np.abs(ref.transform(fields)), atol=1e-10)
    np.testing.assert_allclose(pca.components_ @ pca.components_.T, np.eye(2), atol=1e-12)


def test_scaling_round_trips_through_the_saved_arrays():
    fields, _, _ = membrane_like_fields()
    for scaling in StrainPCA.SCALINGS:
        pca = StrainPCA(2, scaling=scaling).fit(fields)
        assert StrainPCA.from_arrays(pca.to_arrays("xx_"), "xx_").scaling == scaling


def test_unknown_scaling_is_refused():
    with pytest.raises(ValueError, match="PCA scaling must be one of"):
        StrainPCA(2, scaling="volume")


def test_width_of_one_parameter_is_the_closed_form(loss):
    j = np.array([[0.3], [0.4]])  # |J| = 0.5
    fisher = loss.gaussian_fisher(j, 0.01**2 * np.eye(2))
    assert loss.width_95(fisher)[0] == pytest.approx(2 * 1.959964 * 0.01 / 0.5, rel=1e-6)


def test_an_invertible_map_keeps_the_information_and_a_projection_cannot_add_any(loss):
    rng = np.random.default_rng(2)
    j, cov = rng.normal(size=(30, 5)), 0.1 * np.eye(30)
    full = loss.width_95(loss.gaussian_fisher(j, cov))
    invertible = rng.normal(size=(30, 30))
    mapped = loss.width_95(loss.gaussian_fisher(invertible @ j, invertible @ cov @ invertible.T))
    np.testing.assert_allclose(mapped, full, rtol=1e-8)
    rows = rng.normal(size=(8, 30))
    assert np.all(loss.width_95(loss.gaussian_fisher(rows @ j, rows @ cov @ rows.T)) >= full * (1 - 1e-12))


def test_per_cell_scaling_amplifies_noise_where_the_fields_barely_vary(loss):
    """The mechanism the paper-mesh studies lose their information by: under white noise the two
    retained weights of the unscaled PCA carry the whole field's information about p; per-cell
    scaling divides the noise in the flat cells by their 1e-6 spread, and keeps little of it."""
    fields, _, jacobian = membrane_like_fields()
    sigma = 1e-3
    field = loss.width_95(loss.gaussian_fisher(jacobian, sigma**2 * np.eye(60)))
    widths = {}
    for scaling in StrainPCA.SCALINGS:
        pca = StrainPCA(2, scaling=scaling).fit(fields)
        m = loss.weight_map(pca.components_, pca.scale_)
        widths[scaling] = loss.width_95(loss.gaussian_fisher(m @ jacobian, sigma**2 * m @ m.T))
    np.testing.assert_allclose(widths["none"], field, rtol=1e-3)
    assert np.all(widths["cell"] > 5 * field)


def test_the_ladder_is_flat_when_every_step_is_exact(loss):
    """Unscaled PCs that span the field's derivative, the noise sd the weights really have, no
    emulator error and the emulator's derivative equal to the field's: every step keeps the
    field's widths."""
    fields, _, jacobian = membrane_like_fields()
    j5 = np.pad(jacobian, ((0, 0), (0, 3)))  # three parameters the field does not inform
    j5[:40, 2:] = 0.02 * np.random.default_rng(4).normal(size=(40, 3))
    fields = fields + np.random.default_rng(5).uniform(size=(80, 3)) @ j5[:, 2:].T
    pca = StrainPCA(5, scaling="none").fit(fields)
    m = loss.weight_map(pca.components_, pca.scale_)
    steps = loss.ladder({"xx": j5}, {"xx": m}, {"xx": 2e-3}, np.eye(60), {"xx": 2e-3}, np.zeros(5), m @ j5)
    for widths in steps:
        np.testing.assert_allclose(widths, steps[0], rtol=1e-6)
    with_error = loss.ladder({"xx": j5}, {"xx": m}, {"xx": 2e-3}, np.eye(60), {"xx": 2e-3}, np.full(5, 4e-6), m @ j5)
    np.testing.assert_allclose(with_error[3], np.sqrt(2) * steps[0], rtol=1e-6)
