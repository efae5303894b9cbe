"""The emulator's error model (surrogate.error_model) against independent routes: scikit-learn's
joint predictive covariance and refits, closed forms, and fresh draws of a known error."""

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from surrogate.error_model import (
    cross_validated_excess,
    design_correlation,
    excess_variance,
    fit_material_scale,
    material_quadratic_forms,
    truncation_variance,
)
from surrogate.gp import GPBank, StandardisedGP
from surrogate.pca import StrainPCA


def fixed_gp(x, y, length=0.4, constant=1.0, noise=1e-6):
    """A scikit-learn GP with fixed hyper-parameters (no optimisation) on standardised targets."""
    kernel = ConstantKernel(constant) * RBF(np.full(x.shape[1], length)) + WhiteKernel(noise)
    mean, sd = float(y.mean()), float(y.std())
    gp = GaussianProcessRegressor(kernel, optimizer=None, normalize_y=False).fit(x, (y - mean) / sd)
    return StandardisedGP(gp, mean, sd)


def material_rows(rng, n_materials, rows_per_material, offset_sd):
    """Unit-box inputs (n, 7): 5 material inputs shared by a material's rows, 2 design inputs per
    row; targets: a smooth function plus an offset per material (the error a GP cannot see)."""
    params = np.repeat(rng.uniform(size=(n_materials, 5)), rows_per_material, axis=0)
    design = rng.uniform(size=(len(params), 2))
    x = np.column_stack([params, design])
    materials = np.repeat(np.arange(n_materials), rows_per_material)
    offsets = rng.normal(0, offset_sd, n_materials)[materials]
    y = np.sin(3 * x[:, 0]) + x[:, 5] ** 2 - 0.5 * x[:, 1] * x[:, 6]
    return x, np.column_stack([y + offsets, 2 * y - offsets]), materials


def test_joint_covariance_is_scikit_learns_and_its_diagonal_the_variance():
    rng = np.random.default_rng(0)
    x, y, _ = material_rows(rng, 12, 5, 0.0)
    gps = [fixed_gp(x, y[:, g], length=0.5 + 0.2 * g, noise=1e-4) for g in range(2)]
    bank = GPBank.from_sklearn(gps)
    x_new = rng.uniform(size=(4, 7))
    mean, cov = bank.joint(torch.as_tensor(x_new))
    for g, gp in enumerate(gps):
        m_ref, c_ref = gp.gp.predict(x_new, return_cov=True)
        np.testing.assert_allclose(mean[:, g].numpy(), gp.y_std * m_ref + gp.y_mean, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(cov[g].numpy(), gp.y_std**2 * c_ref, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(
        torch.diagonal(cov, dim1=-2, dim2=-1).T.numpy(), bank(torch.as_tensor(x_new))[1].numpy(), rtol=1e-10, atol=1e-14
    )


def test_latent_covariance_leaves_out_the_white_noise_level():
    """The latent function's covariance, by hand from scikit-learn's fitted kernel parts:
    k1(x, x) - k1(x, X) K^-1 k1(X, x), K the training covariance with its white noise; it is the
    joint covariance less the white-noise level on the diagonal."""
    rng = np.random.default_rng(2)
    x, y, _ = material_rows(rng, 10, 4, 0.0)
    gp = fixed_gp(x, y[:, 0], noise=0.05)
    bank = GPBank.from_sklearn([gp])
    x_new = rng.uniform(size=(3, 7))
    signal = gp.gp.kernel_.k1
    cross = signal(x_new, x)
    expected = signal(x_new) - cross @ np.linalg.solve(gp.gp.kernel_(x), cross.T)
    _, latent = bank.joint(torch.as_tensor(x_new), white_noise=False)
    np.testing.assert_allclose(latent[0].numpy(), gp.y_std**2 * expected, rtol=1e-8, atol=1e-12)
    _, full = bank.joint(torch.as_tensor(x_new))
    np.testing.assert_allclose((full - latent)[0].numpy(), gp.y_std**2 * 0.05 * np.eye(3), atol=1e-12)
    _, variance = bank(torch.as_tensor(x_new), white_noise=False)
    np.testing.assert_allclose(variance[:, 0].numpy(), np.diag(latent[0].numpy()), rtol=1e-10)


def test_excess_variance_is_the_maximum_likelihood_closed_form():
    """With one GP variance v and one load scale s the likelihood of N(0, v + tau^2 s^2) is
    maximal at tau^2 = (mean(r^2) - v) / s^2, or 0 when v already exceeds mean(r^2)."""
    error = np.array([0.3, -0.1, 0.2, -0.4])
    for s in (1.0, 0.5):
        tau2 = excess_variance(error, np.full(4, 0.01), np.full(4, s))
        assert tau2 == pytest.approx((np.mean(error**2) - 0.01) / s**2, rel=1e-5)
    assert excess_variance(error, np.full(4, 1.0), np.ones(4)) == 0.0


def test_an_error_that_grows_with_the_load_is_calibrated_at_the_largest_loads():
    """Errors proportional to the load (sd 0.1 s) and a small constant GP variance: the excess
    scaled by s fits the rows of largest load, where a constant excess would be too small."""
    rng = np.random.default_rng(8)
    scale = rng.uniform(0.1, 1.0, 4000)
    error, variance = 0.1 * scale * rng.normal(size=4000), np.full(4000, 1e-4)
    tau2 = excess_variance(error, variance, scale)
    assert tau2 == pytest.approx(0.01, rel=0.1)
    top = scale > 0.8
    assert np.sqrt(np.mean(error[top] ** 2 / (variance[top] + tau2 * scale[top] ** 2))) == pytest.approx(1, abs=0.1)
    constant = excess_variance(error, variance, np.ones(4000))
    assert np.sqrt(np.mean(error[top] ** 2 / (variance[top] + constant))) > 1.3


def test_cross_validated_excess_calibrates_an_overconfident_gp_on_fresh_materials():
    """Each material carries an offset the GP cannot know (sd 0.15) and the GP (a fixed kernel:
    too long a length scale, no noise) is sure of itself: by material-wise cross-validation the
    excess is found, and on materials drawn afresh the standardised errors have an RMS of 1 with
    it (within the +-35 % that 60 training materials allow), ten times more without."""
    rng = np.random.default_rng(2)
    x, y, materials = material_rows(rng, 60, 6, 0.15)
    subset = np.sort(rng.choice(len(x), 200, replace=False))

    def fit(x_rows, y_rows):
        return GPBank.from_sklearn([fixed_gp(x_rows, y_rows[:, g], length=1.0) for g in range(2)])

    bank = fit(x[subset], y[subset])
    excess = cross_validated_excess(
        fit, x, y, materials, np.ones((len(x), 2)), subset, np.ones(len(x), bool), independent, seed=0
    )
    assert excess.n_rows == len(x) and excess.folds == 5 and excess.load_reference == pytest.approx(np.sqrt(2))
    x_new, y_new, _ = material_rows(np.random.default_rng(3), 200, 3, 0.15)
    with torch.no_grad():
        mean, var = bank(torch.as_tensor(x_new))
    error = y_new - mean.numpy()
    before = np.sqrt(np.mean(error**2 / var.numpy(), axis=0))
    after = np.sqrt(np.mean(error**2 / (var.numpy() + np.array(excess.variance)), axis=0))
    assert np.all(before > 5), before
    np.testing.assert_allclose(after, 1.0, atol=0.35)
    np.testing.assert_allclose(excess.z_rms, before, rtol=0.5)


def independent(design: np.ndarray) -> np.ndarray:
    """(2, k, k) identity correlation of k rows: errors independent between a material's rows."""
    return np.broadcast_to(np.eye(len(design)), (2, len(design), len(design)))


def inverse_gamma_materials(rng, a, b, n_materials, n_values):
    """Errors (n_materials, n_values) of materials whose variance lambda ~ InverseGamma(a, b)."""
    scale = b / rng.gamma(a, 1.0, n_materials)
    return rng.normal(size=(n_materials, n_values)) * np.sqrt(scale[:, None])


def test_material_scale_recovers_a_known_inverse_gamma_and_the_gaussian_limit():
    """Errors drawn with a per-material variance from InverseGamma(3, 2) (mean 1): the fit
    recovers the shape within the sampling error of 400 materials, at any overall level (x 4);
    one common variance gives a large shape (the Gaussian model)."""
    rng = np.random.default_rng(5)
    error = inverse_gamma_materials(rng, 3.0, 2.0, 400, 8)
    q, n = np.sum(error**2, axis=1), np.full(400, 8)
    for level in (1.0, 4.0):
        a, b = fit_material_scale(level * q, n)
        assert a == pytest.approx(3.0, rel=0.25) and b == a - 1
    same = rng.normal(0, np.sqrt(0.5), (400, 8))
    a, _ = fit_material_scale(np.sum(same**2, axis=1), n)
    assert a > 100
    with pytest.raises(ValueError, match=">= 3 materials"):
        fit_material_scale(q[:2], n[:2])


def test_material_quadratic_forms_whiten_by_the_correlation_between_a_materials_rows():
    """Two rows of one material with correlation rho: q is e^T C^-1 e (closed form of a 2 x 2
    inverse), and rows of other materials do not mix in."""
    rho, variance = 0.6, np.array([[0.5, 2.0], [0.5, 2.0], [1.0, 1.0]])
    error = np.array([[0.3, -1.0], [0.1, 0.4], [2.0, 0.0]])
    materials = np.array([7, 7, 9])

    def correlation(rows):
        r = np.where(np.eye(len(rows)) > 0, 1.0, rho)
        return np.broadcast_to(r, (2, len(rows), len(rows)))

    q, n = material_quadratic_forms(error, variance, materials, correlation)
    expected = 0.0
    for g in range(2):
        e, v = error[:2, g], variance[0, g]
        expected += (e[0] ** 2 - 2 * rho * e[0] * e[1] + e[1] ** 2) / (v * (1 - rho**2))
    np.testing.assert_allclose(q, [expected, 4.0], rtol=1e-12)
    np.testing.assert_array_equal(n, [4, 2])


def test_design_correlation_is_the_kernel_along_the_design_inputs():
    rng = np.random.default_rng(4)
    x, y, _ = material_rows(rng, 8, 4, 0.0)
    bank = GPBank.from_sklearn([fixed_gp(x, y[:, 0], length=0.3)])
    design = np.array([[0.1, 0.2], [0.5, 0.2], [0.1, 0.2]])
    r = design_correlation(bank, design)[0]
    np.testing.assert_allclose(np.diag(r), 1.0)
    assert r[0, 2] == pytest.approx(1.0) and r[0, 1] == pytest.approx(np.exp(-0.5 * (0.4 / 0.3) ** 2))
    assert np.all(np.linalg.eigvalsh(r) > -1e-12)


def test_truncation_variance_is_zero_for_a_full_field_and_the_training_leak_when_masked():
    """Rank-12 training fields, 3 PCs kept: the 9 discarded directions hold all the rest, so the
    predicted variance of the masked projection's weights equals the mean square of the
    discarded part of the training fields carried through the same projection."""
    rng = np.random.default_rng(5)
    fields = rng.normal(size=(200, 12)) * np.geomspace(1, 0.01, 12) @ np.linalg.qr(rng.normal(size=(40, 12)))[0].T
    pca = StrainPCA(3).fit(fields)
    full = np.ones(40, dtype=bool)
    _, projector = pca.transform_masked(fields[0], full)
    assert np.all(truncation_variance(pca, projector, full) < 1e-25)
    mask = rng.uniform(size=40) > 0.3
    _, projector = pca.transform_masked(fields[0], mask)
    z = (fields - pca.mean_) / pca.scale_
    discarded = z - (z @ pca.components_.T) @ pca.components_
    leak = discarded[:, mask] @ projector.T  # (rows, 3)
    predicted = truncation_variance(pca, projector, mask)
    assert np.all(predicted > 1e-6)
    np.testing.assert_allclose(predicted, np.mean(leak**2, axis=0), rtol=1e-8)


@pytest.mark.parametrize("noisy_training", [False, True])
def test_likelihood_is_the_multivariate_normal_of_the_summed_covariances(emulator_and_observation, noisy_training):
    """Two observations of one material: the log likelihood equals scipy's multivariate normal
    with the covariance built term by term (GP joint + held-out excess x correlation +
    truncation + known noise) for every PC weight. An emulator trained on noisy strains carries
    the GPs' latent covariance: their white-noise level is that noise, counted once, as the
    measurement's."""
    from dataclasses import replace

    from inference.model import SkinPosterior
    from skinfem.io import AddedNoise

    emulator, observed = emulator_and_observation
    if noisy_training:
        noise = AddedNoise(0.1, 0.01, (1e-3, 1e-3, 1e-3))
        emulator = replace(emulator, provenance=replace(emulator.provenance, training_noise=noise))
    post = SkinPosterior(emulator, observed, noise="known")
    params = torch.as_tensor(emulator.param_bounds.mean(1))
    x = torch.cat([params.expand(2, 5), torch.as_tensor(observed.design_inputs)], -1)
    mean, gp_cov = emulator.predict_joint(x, white_noise=not noisy_training)
    white = emulator.gps.noise * emulator.gps.y_std**2
    assert torch.allclose(emulator.predict_joint(x)[1] - gp_cov, noisy_training * white[:, None, None] * torch.eye(2))
    tau2 = np.array(emulator.held_out_excess.variance)
    load = np.linalg.norm(observed.design_inputs, axis=1) / 1.2  # |alpha t| / the reference load
    correlation = emulator.error_correlation(observed.design_inputs) * np.outer(load, load)
    expected = 0.0
    for g in range(mean.shape[1]):
        cov = (
            gp_cov[g].detach().numpy()
            + tau2[g] * correlation[g]
            + np.diag(observed.truncation_var[:, g])
            + np.diag(observed.noise_var[:, g])
        )
        expected += multivariate_normal(mean[:, g].detach().numpy(), cov).logpdf(observed.weights[:, g])
    assert float(post.log_likelihood(params, torch.zeros(0))) == pytest.approx(expected, rel=1e-9)


def test_an_emulator_without_a_held_out_excess_is_named_in_the_warnings(emulator_and_observation):
    from dataclasses import replace

    from inference.model import SkinPosterior

    emulator, observed = emulator_and_observation
    assert SkinPosterior(emulator, observed).model_warnings() == []
    old = replace(emulator, provenance=replace(emulator.provenance, held_out_excess=None))
    (message,) = SkinPosterior(old, observed).model_warnings()
    assert "no held-out error model" in message and "skinid surrogate fit" in message
    assert SkinPosterior(old, observed, emulator_error=False).model_warnings() == []


@pytest.fixture
def emulator_and_observation():
    """A two-GP emulator with a held-out excess, and two masked observations with stated sd."""
    from dataclasses import replace

    from inference.model import ObservedWeights
    from inference.observations import Observation
    from surrogate.emulator import Emulator, EmulatorProvenance
    from surrogate.error_model import HeldOutExcess

    rng = np.random.default_rng(6)
    n_cells = 30
    fields = rng.normal(size=(80, 8)) * np.geomspace(1, 0.05, 8) @ np.linalg.qr(rng.normal(size=(n_cells, 8)))[0].T
    pca = StrainPCA(2).fit(fields)
    x = rng.uniform(size=(80, 7))
    bank = GPBank.from_sklearn([fixed_gp(x, pca.transform(fields)[:, g], noise=1e-3) for g in range(2)])
    provenance = EmulatorProvenance(
        dataset="d.h5",
        dataset_config="",
        mesh_sha256="",
        block_half_length=20.0,
        train_materials=(),
        test_materials=(),
        n_training_rows=80,
        n_gp_rows=80,
        gp_fraction=1.0,
        restarts=0,
        seed=0,
        explained_variance_ratio={},
        fit_seconds={},
        versions={},
    )
    emulator = Emulator(
        pcas={"xx": pca},
        gps=bank,
        lower=np.zeros(7),
        upper=np.ones(7),
        xy=rng.uniform(-20, 20, size=(n_cells, 2)),
        volume=np.ones(n_cells),
        provenance=replace(provenance, held_out_excess=HeldOutExcess((0.02, 0.005), (2.0, 1.4), 5, 80, 1.2)),
    )
    strain = np.zeros((n_cells, 3))
    mask = rng.uniform(size=n_cells) > 0.25
    observations = [
        Observation(
            alpha=np.array([0.4, 0.5]),
            t=t,
            fields=strain + fields[k, :, None],
            mask=mask,
            sd=np.array([0.05, 0.05, 0.05]),
            truth=None,
            source=f"o{k}",
        )
        for k, t in enumerate((0.5, 1.0))
    ]
    return emulator, ObservedWeights.project(emulator, observations)


def test_the_budget_statement_names_the_term_that_limits_the_intervals():
    """Noise ahead: the measurement; GP + excess ahead: refine the dataset near the point;
    truncation ahead of the rest of the emulator: keep more components."""
    from inference.model import ErrorBudget

    params = np.array([1e-3, 0.015, 10.0, 0.28, 30.0])
    assert "measurement noise limits" in ErrorBudget(0.6, 0.2, 0.1, 0.1).statement(params)
    near = ErrorBudget(0.2, 0.4, 0.3, 0.1).statement(params)
    assert "refine the dataset near mu = 0.001" in near and "--variance" not in near
    leak = ErrorBudget(0.2, 0.1, 0.1, 0.6).statement(params)
    assert "PCA truncation" in leak and "--variance 0.999" in leak


def test_parameter_shift_recovers_a_known_shift_covariance_and_the_residual_excess():
    """Errors e = J delta_m + eps with delta_m ~ N(0, C) per material (300 materials, 20 rows,
    2 weights) and eps of sd 0.01 s: C is recovered within the sampling error of 300 draws
    (sd ~8 % on a variance, 0.06 on a correlation), the residual's excess within 10 %, and the shift explains the share
    of |e|^2 it carries (computed here from the draws)."""
    from surrogate.error_model import fit_parameter_shift

    rng = np.random.default_rng(11)
    n_materials, rows = 300, 20
    root = np.diag([0.1, 0.2, 0.05, 0.3, 0.1])
    root[3, 1] = 0.1
    cov = root @ root.T
    materials = np.repeat(np.arange(n_materials), rows)
    jacobian = rng.normal(size=(len(materials), 2, 5))
    delta = rng.normal(size=(n_materials, 5)) @ root.T
    scale = rng.uniform(0.1, 1.0, len(materials))
    noise = 0.01 * scale[:, None] * rng.normal(size=(len(materials), 2))
    error = np.einsum("ngk,nk->ng", jacobian, delta[materials]) + noise
    shift = fit_parameter_shift(error, np.full(error.shape, 1e-8), jacobian, materials, scale, np.full(2, 0.05))
    fitted = np.array(shift.covariance)
    np.testing.assert_allclose(np.diag(fitted), np.diag(cov), rtol=0.2)
    sd, sd_true = np.sqrt(np.diag(fitted)), np.sqrt(np.diag(cov))
    np.testing.assert_allclose(fitted / np.outer(sd, sd), cov / np.outer(sd_true, sd_true), atol=0.2)  # ~3.5 sd
    np.testing.assert_allclose(shift.residual_variance, 1e-4, rtol=0.1)
    explained = np.sum(np.einsum("ngk,nk->ng", jacobian, delta[materials]) ** 2) / np.sum(error**2)
    assert shift.absorbed_share == pytest.approx(explained, abs=0.02)
    assert shift == type(shift).from_json(shift.to_json())


def test_shift_residual_model_recovers_the_gp_share_and_the_excess():
    """Residuals of variance rho v + tau^2 s^2 with rho = 0.15, tau^2 = 2e-3 (20,000 draws; v and s
    independent, so the two are told apart): both within 10 % (sampling sd ~2-3 %). A residual
    of 2.5 times the GP variance keeps rho at its cap 1 and gives more than the excess to tau^2."""
    from surrogate.error_model import shift_residual_model

    rng = np.random.default_rng(3)
    n = 20_000
    variance, scale = rng.uniform(0.5e-2, 2e-2, n), rng.uniform(0.1, 1.0, n)
    residual = rng.normal(size=n) * np.sqrt(0.15 * variance + 2e-3 * scale**2)
    rho, tau2 = shift_residual_model(residual, variance, scale)
    assert rho == pytest.approx(0.15, rel=0.1) and tau2 == pytest.approx(2e-3, rel=0.1)
    larger = rng.normal(size=n) * np.sqrt(2.5 * variance + 5e-3 * scale**2)
    rho, tau2 = shift_residual_model(larger, variance, scale)
    assert rho == pytest.approx(1.0, abs=1e-3) and tau2 > 5e-3


def test_shift_covariance_predicts_a_new_materials_shift_from_twelve():
    """Shifts of 12 materials drawn from a known C, 4,000 times: a new material's Mahalanobis
    square under the predicted C averages 5, as a calibrated covariance's must (Monte Carlo sd
    ~0.1), where the 12 shifts' own second moment gives twice that (Hotelling: 5 * 12 / 6). Fewer
    than 7 materials are refused."""
    from surrogate.error_model import shift_covariance, shift_second_moment

    rng = np.random.default_rng(8)
    root = np.diag([0.02, 0.2, 0.6, 0.1, 0.1]) + 0.05 * rng.normal(size=(5, 5))
    no_fit_error = np.zeros((12, 5, 5))
    predicted, plain = [], []
    for _ in range(4000):
        shifts, new = rng.normal(size=(12, 5)) @ root.T, root @ rng.normal(size=5)
        predicted.append(new @ np.linalg.solve(shift_covariance(shifts, no_fit_error), new))
        plain.append(new @ np.linalg.solve(shift_second_moment(shifts, no_fit_error), new))
    assert np.mean(predicted) == pytest.approx(5.0, abs=0.4)
    assert np.mean(plain) == pytest.approx(10.0, abs=0.8)
    with pytest.raises(ValueError, match=">= 7"):
        shift_covariance(shifts[:6], no_fit_error[:6])


def test_an_emulator_fitted_before_the_gp_share_carries_the_gp_variance_in_full():
    from surrogate.error_model import ParameterShift

    entry = {"covariance": np.eye(5).tolist(), "residual_variance": [1e-3, 2e-3], "absorbed_share": 0.8}
    assert ParameterShift.from_json(entry).gp_share == (1.0, 1.0)


def test_shift_covariance_removes_the_fit_error_of_a_weakly_informed_direction():
    """One column of J 50x smaller than the others: each material's fitted shift along it is
    mostly its fit's noise (fit-error variance ~0.16 against a true 0.1). mean delta delta^T
    would report ~0.26; C less the fit errors recovers 0.1 (1,000 materials: sampling sd of the
    estimate ~12 %), and the well-informed directions are unchanged."""
    from surrogate.error_model import fit_parameter_shift

    rng = np.random.default_rng(5)
    n_materials, rows = 1000, 20
    sd_true = np.array([0.1, 0.2, 0.05, np.sqrt(0.1), 0.1])
    materials = np.repeat(np.arange(n_materials), rows)
    jacobian = rng.normal(size=(len(materials), 2, 5))
    jacobian[..., 3] *= 0.02
    delta = rng.normal(size=(n_materials, 5)) * sd_true
    error = np.einsum("ngk,nk->ng", jacobian, delta[materials]) + 0.05 * rng.normal(size=(len(materials), 2))
    shift = fit_parameter_shift(
        error, np.full(error.shape, 2.5e-3), jacobian, materials, np.ones(len(materials)), [0, 0]
    )
    fitted = np.diag(shift.covariance)
    naive = np.mean(
        [
            np.linalg.lstsq(jacobian[materials == m].reshape(-1, 5), error[materials == m].ravel(), rcond=None)[0][3]
            ** 2
            for m in range(n_materials)
        ]
    )
    assert naive > 2 * sd_true[3] ** 2  # the fit error dominates the raw second moment
    np.testing.assert_allclose(fitted, sd_true**2, rtol=0.3)
