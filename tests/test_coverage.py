"""The coverage study (inference.coverage): its cases, its statistics against their definitions,
and a resumable run on the small emulator's held-out materials."""

import json
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch

from inference import coverage
from inference.coverage import RANK_DRAWS, CaseResult, case_result, cases_of, coverage_study, noisy, summarise
from inference.model import ObservedWeights, draw_from_model
from inference.observations import from_dataset
from inference.studies import (
    EMULATOR_ERRORS,
    SamplerSettings,
    emulator_error_flags,
    emulator_error_of,
    resolve_emulator_error,
    skin_posterior,
    spread_designs,
)
from skinfem.io import StrainDataset
from surrogate.emulator import Emulator


@pytest.fixture(scope="module")
def data(small_dataset):
    return StrainDataset.open(small_dataset)


def test_cases_cover_every_test_material_and_starting_design(data):
    test = np.flatnonzero(data.split == 1)
    n_des = len(data.designs)
    single = cases_of(data, "single")
    assert len(single) == len(test) * n_des and {c.frames for c in single} == {(-1,)}
    frames = cases_of(data, "frames", n=2, noise_seeds=3)
    assert len(frames) == 3 * len(test) * n_des and {c.frames for c in frames} == {(-2, -1)}
    membranes = cases_of(data, "membranes", n=2)
    assert [c.designs for c in membranes[:n_des]] == [tuple(spread_designs(data.designs, j, 2)) for j in range(n_des)]
    with pytest.raises(ValueError, match="setup must be one of"):
        cases_of(data, "two frames")


def test_one_start_per_material_gives_independent_cases_over_every_design(data):
    materials = list(range(2 * len(data.designs) + 1))
    cases = cases_of(data, "single", materials=materials, starts=1)
    assert [c.material for c in cases] == materials  # one case per material
    counts = np.bincount([c.designs[0] for c in cases], minlength=len(data.designs))
    assert counts.max() - counts.min() <= 1  # the designs used evenly
    # a subset of the materials keeps its cases (a study split over processes)
    assert cases_of(data, "single", materials=materials[3:5], starts=1) == cases[3:5]
    assert len(cases_of(data, "single", materials=[0], starts=len(data.designs))) == len(data.designs)
    with pytest.raises(ValueError, match="starting designs per material must be in"):
        cases_of(data, "single", starts=0)


@pytest.mark.parametrize("choice", EMULATOR_ERRORS)
def test_the_error_model_named_on_a_study_is_the_one_its_settings_hold(choice):
    assert emulator_error_of(SamplerSettings(**emulator_error_flags(choice))) == choice


def test_the_scale_on_the_shift_is_named_as_both():  # benchmarks/coverage.py's diagnostic
    both = SamplerSettings(emulator_error=True, emulator_scale=True, emulator_shift=True)
    assert emulator_error_of(both) == "shift-scaled"


def test_the_default_error_model_is_the_parameter_shift_where_the_emulator_fitted_one(small_emulator, tmp_path):
    """The command line's '--emulator-error auto': the shift for an emulator that fitted it (and
    for the emulators a study fits itself), the per-weight error for one fitted before it."""
    import shutil

    assert resolve_emulator_error("auto", Emulator.load(small_emulator)) == "shift"
    assert resolve_emulator_error("auto", None) == "shift"
    older = tmp_path / "emu"
    shutil.copytree(small_emulator, older)
    meta = json.loads((older / "meta.json").read_text())
    meta["held_out_excess"].pop("parameter_shift")
    (older / "meta.json").write_text(json.dumps(meta))
    assert Emulator.load(older).held_out_excess is not None
    assert resolve_emulator_error("auto", Emulator.load(older)) == "on"
    assert all(resolve_emulator_error(choice, Emulator.load(older)) == choice for choice in EMULATOR_ERRORS)


def test_summary_is_the_share_of_cases_covered_with_its_binomial_sd():
    hits = [True] * 45 + [False] * 5  # 90 % of 50
    results = [
        CaseResult(
            rank=(1,) * 5, covered_50=(h,) * 5, covered_95=(True,) * 5, interval_share_95=(0.5,) * 5, divergences=0
        )
        for h in hits
    ]
    summary = summarise(results, "single", 3, 0.0, SamplerSettings(), materials=list(range(50)))
    mu = summary.parameters["mu"]
    assert summary.n_cases == 50 and summary.n_materials == 50
    assert mu.coverage_50 == 0.9 and mu.binomial_sd_50 == pytest.approx(np.sqrt(0.9 * 0.1 / 50))
    assert mu.coverage_95 == 1.0 and not mu.meets_goal  # 50 % intervals holding 90 %: too wide
    # the same 50 materials seen through 4 designs each: 200 cases, no more information
    again = summarise(results * 4, "single", 3, 0.0, SamplerSettings(), materials=list(range(50)) * 4)
    assert again.n_cases == 200 and again.n_materials == 50
    assert again.parameters["mu"].binomial_sd_50 == pytest.approx(mu.binomial_sd_50)
    # posteriors run again with smaller steps are counted with their first runs' divergences
    rerun = [replace(r, divergences=1, divergences_before_resampling=40) for r in results[:3]]
    resampled = summarise(rerun + results[3:], "single", 3, 0.0, SamplerSettings(), materials=list(range(50)))
    assert (resampled.cases_resampled, resampled.divergences_before_resampling, resampled.divergences) == (3, 120, 3)
    assert (summary.cases_resampled, summary.divergences_before_resampling) == (0, 0)


@pytest.mark.slow
def test_a_study_ranks_the_truth_and_resumes_without_recomputing(small_emulator, data, tmp_path, monkeypatch):
    emulator = Emulator.load(small_emulator)
    settings = SamplerSettings(chains=2, warmup=100, draws=100, n_jobs=2, gp_variance="mode", progress=False)
    first = int(np.flatnonzero(data.split == 1)[0])
    summary = coverage_study(emulator, data, "single", settings, tmp_path, materials=[first])
    n_cases = len(data.designs)
    assert summary.n_cases == n_cases and (tmp_path / "ranks.png").stat().st_size > 10_000
    cases = sorted((tmp_path / "cases").glob("*.json"))
    assert len(cases) == n_cases
    for path in cases:
        case = json.loads(path.read_text())
        assert all(0 <= r <= RANK_DRAWS for r in case["rank"])
        # a truth inside the central 50 % lies between the 25th and 75th percentile ranks
        for rank, inside in zip(case["rank"], case["covered_50"]):
            if inside:
                assert 0.12 * RANK_DRAWS <= rank <= 0.88 * RANK_DRAWS  # thinning: +-4 sd
    monkeypatch.setattr(coverage, "run_case", lambda *a, **k: pytest.fail("a finished case was recomputed"))
    again = coverage_study(emulator, data, "single", settings, tmp_path, materials=[first])
    assert again.parameters == summary.parameters
    assert (
        json.loads((tmp_path / "coverage.json").read_text())["parameters"]["mu"]["coverage_95"]
        == summary.parameters["mu"].coverage_95
    )


def test_a_draw_from_the_model_is_its_likelihood_at_the_drawn_parameters(small_emulator, data):
    """draw_from_model (Pyro's Predictive over the reference model, two observations: the
    likelihood's (g, o) order) against the posterior's own whitening of the same covariance
    (Cholesky, another route): at the drawn values the whitened weights are standard normal,
    and the values are uniform over the prior box."""
    emulator = Emulator.load(small_emulator)
    material = int(np.flatnonzero(data.split == 1)[0])
    observations = noisy(from_dataset(data, material, [0, 1], [-1]), 1e-4, 0)
    settings = SamplerSettings(**emulator_error_flags("shift"))
    posterior = skin_posterior(emulator, ObservedWeights.project(emulator, observations), settings, "known")
    values, white = [], []
    for seed in range(200):
        v, weights = draw_from_model(posterior, seed)
        if seed == 7:
            seventh = weights
        drawn = skin_posterior(emulator, replace(posterior.observed, weights=weights), settings, "known")
        w, _ = drawn.whitened_residuals(*drawn.latents(torch.as_tensor(v)))
        values.append(v)
        white.append(w.detach().numpy().ravel())
    white, share = (
        np.concatenate(white),
        (np.array(values) - emulator.param_bounds[:, 0]) / np.ptp(emulator.param_bounds, axis=1),
    )
    n = white.size
    assert abs(white.mean()) < 4 / np.sqrt(n) and abs(white.var() - 1) < 4 * np.sqrt(2 / n)
    assert np.all((share >= 0) & (share <= 1)) and np.all(np.abs(share.mean(0) - 0.5) < 4 * np.sqrt(1 / 12 / 200))
    again = draw_from_model(posterior, 7)  # seeded
    assert np.array_equal(again[0], values[7]) and np.array_equal(again[1], seventh)


def test_data_from_the_model_need_a_stated_noise(small_emulator, data, tmp_path):
    with pytest.raises(ValueError, match="need a stated noise sd"):
        coverage_study(Emulator.load(small_emulator), data, "single", SamplerSettings(), tmp_path, data_from="model")
    with pytest.raises(ValueError, match="data_from must be one of"):
        coverage_study(Emulator.load(small_emulator), data, "single", SamplerSettings(), tmp_path, data_from="dic")


def test_a_case_keeps_its_truth_and_the_draws_it_was_ranked_among():
    """The rank is recomputed from the kept draws and truth; a case file written before they
    were kept still loads."""
    draws = np.random.default_rng(0).normal(size=(4000, 5)) * [1e-4, 1e-3, 1.0, 0.01, 5.0] + [1e-3, 0.02, 10, 0.2, 30]
    truth = np.array([1.05e-3, 0.019, 10.5, 0.2, 36.0])
    bounds = np.array([[5e-4, 2e-3], [0.0, 0.05], [1, 20], [0, 1 / 3], [0, 90]])
    result = case_result(draws, truth, bounds, 0)
    kept = np.array(result.thinned_draws)
    assert kept.shape == (RANK_DRAWS, 5) and np.array_equal(result.truth, truth)
    assert tuple(np.sum(kept < truth, axis=0)) == result.rank
    again = CaseResult(**json.loads(json.dumps(asdict(result))))
    assert np.array_equal(again.thinned_draws, result.thinned_draws)
    older = {k: v for k, v in asdict(result).items() if k not in ("truth", "thinned_draws")}
    assert CaseResult(**older).truth == ()


def test_rms_z_tells_too_wide_from_calibrated_intervals():
    """Truths drawn from N(0, 1) posteriors: RMS z near 1; the same truths with posteriors twice
    as wide: near 0.5, though their 95 % intervals still cover."""
    rng = np.random.default_rng(1)
    bounds = np.array([[-10.0, 10.0]] * 5)
    truths = rng.normal(size=(400, 5))
    for width, expected in ((1.0, 1.0), (2.0, 0.5)):
        results = [case_result(width * rng.normal(size=(1000, 5)), t, bounds, 0) for t in truths]
        summary = summarise(results, "single", 3, 0.0, SamplerSettings(), materials=list(range(400)))
        rms = np.array([p.rms_z for p in summary.parameters.values()])
        assert np.allclose(rms, expected, rtol=0.12)  # 400 cases, mean and sd from 99 thinned draws
        assert all(p.coverage_95 >= 0.93 for p in summary.parameters.values())
    pinned = [replace(r, thinned_draws=tuple((*row[:4], 30.0) for row in r.thinned_draws)) for r in results]
    summary = summarise(pinned, "single", 3, 0.0, SamplerSettings(), materials=list(range(400)))
    assert summary.parameters["theta"].rms_z is None  # draws that do not vary: no z, no NaN
    assert summary.parameters["mu"].rms_z == pytest.approx(0.5, rel=0.12)
    older = [replace(r, thinned_draws=()) for r in results]
    without = summarise(older, "single", 3, 0.0, SamplerSettings(), materials=list(range(400)))
    assert without.parameters["mu"].rms_z is None
