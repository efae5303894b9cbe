"""PCA and GP building blocks against independent references (scikit-learn, finite differences);
the emulator directory on a synthetic emulator."""

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from sklearn.decomposition import PCA
from sklearn.gaussian_process import GaussianProcessRegressor

from surrogate.emulator import Emulator, EmulatorProvenance, HeldOutScores
from surrogate.gp import GPBank, StandardisedGP, fit_gps, make_kernel
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
def gp_data():
    """Training inputs (80, 7) and two targets, one far from zero mean and unit variance."""
    rng = np.random.default_rng(3)
    x = rng.uniform(size=(80, 7))
    y = np.column_stack([np.sin(3 * x[:, 0]) + x[:, 4] ** 2, np.cos(2 * x[:, 1]) * x[:, 5]])
    y += 1e-3 * rng.normal(size=y.shape)
    y[:, 1] = 5 + 40 * y[:, 1]  # standardised, the same target as before; in its units far from N(0, 1)
    return x, y


@pytest.fixture(scope="module")
def fitted_gps(gp_data):
    return fit_gps(*gp_data, restarts=1, n_jobs=1)


def _sklearn_normalize_y(x, y, **options):
    gp = GaussianProcessRegressor(normalize_y=True, **options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # hyper-parameters at a bound
        return gp.fit(x, y)


def test_own_standardisation_is_sklearns_normalize_y_model(gp_data, fitted_gps):
    """Targets standardised by us + normalize_y=False = scikit-learn's normalize_y=True: the same
    hyper-parameters from the same seeded fit, and the same predictive mean and variance (in
    target units) as a normalize_y=True regressor with those hyper-parameters fixed."""
    x, y = gp_data
    x_new = np.random.default_rng(4).uniform(-0.1, 1.1, size=(50, 7))
    bank = GPBank.from_sklearn(fitted_gps)
    bank_mean, bank_var = (t.numpy() for t in bank(torch.as_tensor(x_new)))
    for g, fitted in enumerate(fitted_gps):
        refit = _sklearn_normalize_y(x, y[:, g], kernel=make_kernel(7), n_restarts_optimizer=1, random_state=g)
        np.testing.assert_allclose(fitted.gp.kernel_.theta, refit.kernel_.theta, rtol=1e-10, atol=0)
        fixed = _sklearn_normalize_y(x, y[:, g], kernel=fitted.gp.kernel_, optimizer=None)
        m_ref, s_ref = fixed.predict(x_new, return_std=True)
        m, s = fitted.predict(x_new, return_std=True)
        np.testing.assert_allclose(m, m_ref, rtol=1e-10, atol=0)
        np.testing.assert_allclose(s**2, s_ref**2, rtol=1e-10, atol=0)
        np.testing.assert_allclose(fitted.predict(x_new), m_ref, rtol=1e-10, atol=0)
        # the torch bank (its float64 distances sum in another order: ill-conditioned, looser)
        np.testing.assert_allclose(bank_mean[:, g], m_ref, rtol=0, atol=1e-8 * np.abs(m_ref).max())
        np.testing.assert_allclose(bank_var[:, g], s_ref**2, rtol=0, atol=1e-8 * (s_ref**2).max())


def test_bank_of_bare_regressors_needs_unnormalised_targets(gp_data, fitted_gps):
    x, y = gp_data
    bare = _sklearn_normalize_y(x, y[:, 0], kernel=fitted_gps[0].gp.kernel_, optimizer=None)
    with pytest.raises(ValueError, match="normalize_y=True"):
        GPBank.from_sklearn([bare])
    raw = [fitted.gp for fitted in fitted_gps]  # normalize_y=False: mean 0, sd 1
    bank = GPBank.from_sklearn(raw)
    x_new = torch.as_tensor(np.random.default_rng(7).uniform(size=(5, 7)))
    mean = np.column_stack([gp.predict(x_new.numpy()) for gp in raw])
    np.testing.assert_allclose(bank(x_new, return_var=False).numpy(), mean, rtol=0, atol=1e-8 * np.abs(mean).max())


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


# -- emulator directory (synthetic emulator: no dataset, no FE) -----------------------------------
PROVENANCE_KEYS = [
    "dataset",
    "dataset_config",
    "mesh_sha256",
    "block_half_length",
    "train_materials",
    "test_materials",
    "n_training_rows",
    "n_gp_rows",
    "gp_fraction",
    "restarts",
    "seed",
    "explained_variance_ratio",
    "fit_seconds",
    "versions",
]
FORMAT_KEYS = ["format", "format_version", "inputs", "lower", "upper", "components", "n_weights"]


@pytest.fixture
def tiny_emulator(fitted_gps):
    """One component ("xx", 2 PCs of 40 cells) on the two GPs of ``fitted_gps``."""
    pca = StrainPCA(n_components=2).fit(low_rank_fields(rank=2))
    provenance = EmulatorProvenance(
        dataset=Path("/data/tiny.h5"),
        dataset_config='name = "tiny"\n\n[mesh]\nlength = 40.0\n',
        mesh_sha256="0" * 64,
        block_half_length=20.0,
        train_materials=(0, 1, 2),
        test_materials=(3,),
        n_training_rows=240,
        n_gp_rows=80,
        gp_fraction=1 / 3,
        restarts=1,
        seed=0,
        explained_variance_ratio={"xx": tuple(pca.explained_variance_ratio_[:20].tolist())},
        fit_seconds={"pca": 0.25, "total": 1.5},
        versions={"skinid": "0.0.0", "numpy": np.__version__},
    )
    xy = np.random.default_rng(6).uniform(-20, 20, size=(40, 2))
    return Emulator(
        pcas={"xx": pca},
        gps=GPBank.from_sklearn(fitted_gps),
        lower=np.zeros(7),
        upper=np.ones(7),
        xy=xy,
        volume=np.full(40, 0.5),
        provenance=provenance,
    )


@pytest.mark.parametrize("validated", [False, True], ids=["fitted", "validated"])
def test_provenance_round_trips_through_save_and_load(tiny_emulator, tmp_path, validated):
    if validated:
        scores = {"xx": HeldOutScores(min_r2=0.995, field_rmse=1e-4, field_rmse_relative=0.01)}
        tiny_emulator.provenance = tiny_emulator.provenance.validated(scores)
    directory = tiny_emulator.save(tmp_path / "emu")
    text = (directory / "meta.json").read_text()
    assert list(json.loads(text)) == PROVENANCE_KEYS + ["validation"] * validated + FORMAT_KEYS
    loaded = Emulator.load(directory)
    assert loaded.provenance == tiny_emulator.provenance
    assert (loaded.save(tmp_path / "again") / "meta.json").read_text() == text
    np.testing.assert_array_equal(
        loaded.predict_fields(np.full((3, 5), 0.5), [0.1, 0.2], 1.0),
        tiny_emulator.predict_fields(np.full((3, 5), 0.5), [0.1, 0.2], 1.0),
    )


@pytest.mark.parametrize("fitted_by", ["standardised", "normalize_y"])
def test_reference_regressors_round_trip_in_target_units(tiny_emulator, fitted_gps, gp_data, tmp_path, fitted_by):
    """``sklearn_gps.joblib`` holds :class:`StandardisedGP` (this version) or scikit-learn
    normalize_y=True regressors (earlier versions); both load and predict in target units."""
    x, y = gp_data
    if fitted_by == "standardised":
        tiny_emulator.sklearn_gps = fitted_gps
    else:
        tiny_emulator.sklearn_gps = [
            _sklearn_normalize_y(x, y[:, g], kernel=f.gp.kernel_, optimizer=None) for g, f in enumerate(fitted_gps)
        ]
    loaded = Emulator.load(tiny_emulator.save(tmp_path / "emu"))
    assert all(isinstance(gp, StandardisedGP) == (fitted_by == "standardised") for gp in loaded.sklearn_gps)
    x_new = np.random.default_rng(8).uniform(size=(10, 7))
    mean, var = (t.numpy() for t in loaded.gps(torch.as_tensor(x_new)))
    for g, gp in enumerate(loaded.sklearn_gps):
        m, s = gp.predict(x_new, return_std=True)
        np.testing.assert_allclose(m, mean[:, g], rtol=0, atol=1e-8 * np.abs(m).max())
        np.testing.assert_allclose(s**2, var[:, g], rtol=0, atol=1e-8 * (s**2).max())


def test_emulators_fitted_before_block_half_length_was_recorded_still_load(tiny_emulator, tmp_path):
    directory = tiny_emulator.save(tmp_path / "emu")
    meta = json.loads((directory / "meta.json").read_text())
    del meta["block_half_length"]
    (directory / "meta.json").write_text(json.dumps(meta))
    assert Emulator.load(directory).provenance.block_half_length == 20.0  # mesh.length / 2 of its config


def _truncate(path):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _drop_cholesky(path):
    with np.load(path) as arrays:
        kept = {k: arrays[k] for k in arrays.files if k != "chol"}
    np.savez(path, **kept)


def _empty(path):
    path.write_bytes(b"")


@pytest.mark.parametrize(
    "name, damage",
    [("gp.npz", _truncate), ("pca.npz", _truncate), ("gp.npz", _drop_cholesky), ("gp.npz", _empty)],
    ids=["truncated-gp", "truncated-pca", "missing-array", "empty-gp"],
)
def test_corrupt_array_files_are_one_value_error_naming_the_file(tiny_emulator, tmp_path, name, damage):
    directory = tiny_emulator.save(tmp_path / "emu")
    damage(directory / name)
    with pytest.raises(ValueError, match=re.escape(f"'{directory / name}' is truncated or corrupt")) as info:
        Emulator.load(directory)
    assert "\n" not in str(info.value)


def test_an_emulator_of_a_uniaxial_design_alone_fits_predicts_and_gives_a_posterior(tmp_path):
    """alpha22 t is 0 in every training row of the design (0.05, 0): its input box has no width.
    It scales to 0 (not 0 / 0 = NaN, which the GP refused and which made NUTS fail on the
    posterior's closed-form density), the predictions at the design follow the fields, and the
    closed-form log density is finite and equals autograd's."""
    import torch

    from inference.density import FusedLogDensity
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset
    from skinfem.config import load_config
    from skinfem.io import STATUS_OK, StrainDataset, create_dataset, write_simulation
    from skinfem.sweep import latin_hypercube
    from surrogate.emulator import fit_emulator

    config = load_config("small").with_changes(sweep={"n_materials": 16, "n_test": 2, "designs": [[0.05, 0.0]]})
    params = latin_hypercube(config.sweep.box, 16, seed=1)
    t = np.arange(1, 6) / 5
    xy = np.random.default_rng(4).uniform(-20, 20, size=(30, 2))
    path = tmp_path / "uniaxial.h5"
    split = np.isin(np.arange(16), [3, 6]).astype(np.int8)
    create_dataset(path, config, params, np.array([[0.05, 0.0]]), t, xy, np.ones(30), split, "0" * 64)

    def field(p):  # (frames, cells, 3): linear in mu and in the load
        pattern = np.stack([np.cos(xy[:, 0] / 7), np.sin(xy[:, 1] / 5), xy[:, 0] * xy[:, 1] / 400], -1)
        return 0.05 * t[:, None, None] * pattern * p[0] / 1e-3

    for i, p in enumerate(params):
        write_simulation(path, i, 0, field(p), STATUS_OK)
    emulator = fit_emulator(StrainDataset.open(path), gp_fraction=1.0, restarts=0, seed=0, cv_folds=3)
    predicted = emulator.predict_fields(params[[3, 6]], (0.05, 0.0), 1.0)
    truth = np.stack([field(params[i])[-1][:, :2] for i in (3, 6)])
    assert np.all(np.isfinite(predicted))
    assert np.abs(predicted - truth).max() < 0.05 * np.abs(truth).max()
    data = StrainDataset.open(path)
    posterior = SkinPosterior(emulator, ObservedWeights.project(emulator, from_dataset(data, 3)), gp_variance="mode")
    posterior.fix_gp_variance(params[3])
    u = np.random.default_rng(5).normal(size=posterior.dim)
    value, _ = FusedLogDensity(posterior)(u)
    assert np.isfinite(value) and value == pytest.approx(float(posterior.log_density(torch.tensor(u))), rel=1e-8)
