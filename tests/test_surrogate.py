"""The emulator of the small sweep: exact persistence, sklearn agreement, held-out accuracy."""

import json

import numpy as np
import pytest
import torch

from skinfem.io import StrainDataset
from surrogate.emulator import Emulator, model_inputs
from surrogate.validation import validate
from tests.cli_helpers import skinid


@pytest.fixture(scope="module")
def emulator(small_emulator):
    return Emulator.load(small_emulator)


def test_load_of_save_reproduces_predictions_exactly(emulator, tmp_path):
    copy = Emulator.load(emulator.save(tmp_path / "copy"))
    params = np.random.default_rng(0).uniform(emulator.lower[:5], emulator.upper[:5], size=(50, 5))
    a = emulator.predict_fields(params, [0.05, -0.05], 1.0)
    b = copy.predict_fields(params, [0.05, -0.05], 1.0)
    assert a.shape == (50, len(emulator.xy), 2)
    assert np.array_equal(a, b)


def test_torch_predictions_match_sklearn(emulator):
    params = np.random.default_rng(1).uniform(emulator.lower[:5], emulator.upper[:5], size=(20, 5))
    x = model_inputs(params, [-0.05, 0.05], 0.7)
    mean, var = emulator.predict_weights(torch.as_tensor(x))
    unit = emulator.scale(x)
    for g, gp in enumerate(emulator.sklearn_gps):
        m, s = gp.predict(unit, return_std=True)
        np.testing.assert_allclose(mean[:, g].detach().numpy(), m, rtol=0, atol=1e-8 * np.abs(m).max())
        np.testing.assert_allclose(var[:, g].detach().sqrt().numpy(), s, rtol=0, atol=1e-8 * s.max())


def test_held_out_materials_are_predicted(emulator, small_dataset):
    """R² >= 0.99 for every retained PC of the noiseless held-out materials."""
    report, arrays = validate(emulator, StrainDataset.open(small_dataset))
    for c, r in report.components.items():
        assert r.min_r2 >= 0.99, (c, r.r2_per_pc)
        # the emulator adds little to the PCA truncation error
        assert r.field_rmse <= 1.5 * r.pca_floor_rmse + 1e-4
    # standardised errors are of order one: the GP variance is calibrated (not over-confident by 10x)
    z = (arrays.true - arrays.pred) / arrays.sd
    assert 0.2 < np.sqrt(np.mean(z**2)) < 5


def test_pca_projection_round_trip(emulator, small_dataset):
    data = StrainDataset.open(small_dataset)
    fields = emulator.dataset_fields(data.strain(0, 0, -1))[None]
    w = emulator.weights_of_fields(fields)
    again = emulator.weights_of_fields(emulator.fields_of_weights(w))
    np.testing.assert_allclose(again, w, atol=1e-9)


def test_cli_fit_and_validate(small_dataset, tmp_path):
    out = tmp_path / "emu"
    res = skinid(
        "surrogate",
        "fit",
        "--data",
        small_dataset,
        "--out",
        out,
        "--n-components",
        "2",
        "--gp-fraction",
        "0.2",
        "--restarts",
        "0",
        "--cv-folds",
        "12",
    )
    assert res.returncode == 0, res.stderr
    assert "R² per PC" in res.stdout
    fitted = Emulator.load(out)
    assert fitted.provenance.held_out_excess.folds == len(fitted.provenance.train_materials) == 12  # one out
    assert fitted.n_weights == {"xx": 2, "yy": 2} and set(fitted.provenance.validation) == {"xx", "yy"}
    for name in ("validation.png", "explained_variance.png", "validation.json", "gp.npz", "pca.npz"):
        assert (out / name).exists()
    res = skinid("surrogate", "validate", "--emulator", out)  # fit validated it: replacing needs --force
    assert res.returncode == 2 and "validation.json exists; pass --force" in res.stderr
    res = skinid("surrogate", "validate", "--emulator", out, "--force")
    assert res.returncode == 0 and "E_yy" in res.stdout


def test_more_folds_than_training_materials_are_refused_before_the_gp_fit(small_dataset, monkeypatch):
    import surrogate.emulator

    def no_fit(*args, **kwargs):
        raise AssertionError("the GPs were fitted before the folds were checked")

    monkeypatch.setattr(surrogate.emulator, "fit_gps", no_fit)
    with pytest.raises(ValueError, match="needs >= 13 training materials, got 12"):
        surrogate.emulator.fit_emulator(StrainDataset.open(small_dataset), cv_folds=13)


def test_other_format_versions_are_refused(emulator, tmp_path):
    directory = emulator.save(tmp_path / "old")
    meta = json.loads((directory / "meta.json").read_text())
    meta["format_version"] = 99
    (directory / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="format 99"):
        Emulator.load(directory)
    with pytest.raises(FileNotFoundError, match="not an emulator"):
        Emulator.load(tmp_path)
    res = skinid("surrogate", "validate", "--emulator", tmp_path)
    assert res.returncode == 2 and "not an emulator" in res.stderr


def test_an_unscaled_pca_emulator_predicts_held_out_materials_and_keeps_its_scaling(small_dataset, tmp_path):
    """--pca-scaling none: the PCA in strain units (scale 1), held-out materials predicted as
    well as by the standardised emulator, the scaling kept through save and load, and a noise
    study refuses to reuse a case folder fitted with the other scaling."""
    from inference.studies import _case_emulator
    from surrogate.emulator import fit_emulator

    data = StrainDataset.open(small_dataset)
    emulator = fit_emulator(data, pca_scaling="none", gp_fraction=0.5, restarts=1, seed=0)
    assert all(np.array_equal(p.scale_, np.ones(len(data.xy))) for p in emulator.pcas.values())
    report, _ = validate(emulator, data)
    for c, r in report.components.items():
        assert r.min_r2 >= 0.99, (c, r.r2_per_pc)
    folder = emulator.save(tmp_path / "emu")
    assert Emulator.load(folder).pca_scaling == "none"
    assert _case_emulator(data, folder, {"pca_scaling": "none"}).pca_scaling == "none"
    with pytest.raises(ValueError, match="PCA scaling 'none', not 'cell'"):
        _case_emulator(data, folder, {"pca_scaling": "cell"})
