"""Correlated noise: covariance against the RBF kernel, amplitude, seeding, the noisy dataset."""

import json

import h5py
import numpy as np
import pytest

from inference.noise import correlation_factor, noise_amplitude, noise_fields
from skinfem.io import AddedNoise, StrainDataset
from skinfem.sweep import merge_datasets
from surrogate.emulator import Emulator
from tests.cli_helpers import skinid


def test_noise_has_the_rbf_covariance():
    xy = np.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [0.0, 2.0], [3.0, 3.0]])
    length = 1.0
    factor = correlation_factor(xy, length)
    amplitude = np.array([0.01, 0.02, 0.005])
    samples = noise_fields(factor, amplitude, (40000,), np.random.default_rng(0))  # (40000, 5, 3)
    for c in range(3):
        cov = np.cov(samples[..., c].T)
        d2 = ((xy[:, None] - xy[None]) ** 2).sum(-1)
        expected = amplitude[c] ** 2 * np.exp(-d2 / (2 * length**2))
        np.testing.assert_allclose(cov, expected, atol=0.03 * amplitude[c] ** 2)
    # components are independent
    corr = np.corrcoef(samples[:, 0, 0], samples[:, 0, 1])[0, 1]
    assert abs(corr) < 0.03


def test_short_length_scales_give_white_noise_and_bad_lengths_are_refused():
    xy = np.random.default_rng(1).uniform(-10, 10, size=(50, 2))
    factor = correlation_factor(xy, 1e-3)
    np.testing.assert_allclose(factor @ factor.T, np.eye(50), atol=1e-6)
    with pytest.raises(ValueError, match="length scale"):
        correlation_factor(xy, 0.0)


def test_noisy_dataset(small_dataset, tmp_path):
    out = tmp_path / "noisy.h5"
    res = skinid("noise", "--data", small_dataset, "--length", "1.0", "--level", "0.05", "--seed", "3", "--out", out)
    assert res.returncode == 0, res.stderr
    clean, noisy = StrainDataset.open(small_dataset), StrainDataset.open(out)
    assert np.array_equal(clean.split, noisy.split) and np.array_equal(clean.params, noisy.params)
    diff = noisy.strain() - clean.strain()
    amplitude = noise_amplitude(clean, 0.05)
    assert np.all(amplitude > 0)
    np.testing.assert_allclose(diff.reshape(-1, 3).std(0), amplitude, rtol=0.1)
    with h5py.File(out) as f:
        meta = json.loads(f.attrs["noise"])
    assert meta["length_mm"] == 1.0 and meta["seed"] == 3
    assert noisy.added_noise == AddedNoise(1.0, 0.05, tuple(amplitude)) and clean.added_noise is None
    merged = merge_datasets([out], tmp_path / "merged.h5")  # a copy made from the noisy data says so too
    assert merged.added_noise == noisy.added_noise and np.array_equal(merged.strain(), noisy.strain())
    with pytest.raises(ValueError, match="another added noise"):
        merge_datasets([small_dataset, out], tmp_path / "mixed.h5")
    again = tmp_path / "again.h5"
    res = skinid("noise", "--data", small_dataset, "--length", "1.0", "--level", "0.05", "--seed", "3", "--out", again)
    assert res.returncode == 0
    assert np.array_equal(StrainDataset.open(again).strain(), noisy.strain())
    res = skinid("noise", "--data", small_dataset, "--length", "-1", "--level", "0.05", "--out", tmp_path / "bad.h5")
    assert res.returncode == 2 and "length scale must be > 0" in res.stderr


def test_noise_study_runs_end_to_end(small_dataset, tmp_path):
    """One noise case next to the clean data: noise lowers the variance the leading PCs explain
    (the paper's Fig. 4) and the report has its tables and figures."""
    from inference.studies import SamplerSettings, noise_study, read_noise_study

    data = StrainDataset.open(small_dataset)
    material = int(np.flatnonzero(data.split)[0])
    settings = SamplerSettings(chains=2, warmup=100, draws=100, n_jobs=2, gp_variance="mode", progress=False)
    results = noise_study(
        data,
        tmp_path,
        design=2,
        settings=settings,
        lengths=(1.0,),
        levels=(0.05,),
        materials=[material],
        fit_options={"gp_fraction": 0.3, "restarts": 0},
    )
    assert set(results) == {"clean", "m5"}
    for c in ("xx", "yy"):
        assert results["m5"].explained_variance[c][2] < results["clean"].explained_variance[c][2]
    report = (tmp_path / "README.md").read_text()
    assert "| m5 |" in report and "Paper (noise)" in report
    for name in ("explained_variance.png", "sensitivity.png", "noise_study.json", "cases/m5/posteriors/accuracy.png"):
        assert (tmp_path / name).exists(), name
    cases = read_noise_study(tmp_path / "noise_study.json")
    assert cases == results  # the file holds what the study returns
    assert (cases["clean"].level, cases["m5"].length_mm, cases["m5"].level) == (None, 1.0, 0.05)
    assert cases["m5"].data == str(tmp_path / "cases" / "m5" / "data.h5")
    assert cases["m5"].study.designs == [2] and cases["m5"].study.materials == [material]
    # the noisy case's emulator knows its GPs' white noise is the measurement's (counted once)
    noisy_emulator = Emulator.load(tmp_path / "cases" / "m5" / "emulator")
    assert noisy_emulator.provenance.training_noise.level == 0.05 and noisy_emulator.white_noise_is_measurement
    assert not Emulator.load(tmp_path / "cases" / "clean" / "emulator").white_noise_is_measurement
