"""benchmarks/paper_mesh.py: the cell subset of the cells hypothesis and the side-by-side table (no FE)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.scripts import ROOT, load_script


@pytest.fixture(scope="module")
def paper_mesh():
    return load_script(ROOT / "benchmarks" / "paper_mesh.py", "paper_mesh")


def graded_grid(n: int = 62) -> np.ndarray:
    """(n * n, 2) centres of a symmetric graded tensor grid [mm] (finest at the centre)."""
    edges = np.sinh(np.linspace(-3, 3, n + 1)) * 2.0
    centres = 0.5 * (edges[1:] + edges[:-1])
    return np.stack(np.meshgrid(centres, centres), -1).reshape(-1, 2)


def test_grid_subset_keeps_every_fourth_row_and_column_symmetrically(paper_mesh):
    xy = graded_grid()
    cells = paper_mesh.grid_subset(xy, 4)
    assert len(cells) == 16 * 16  # the study mesh's skin cell count from the paper mesh's 62 x 62
    kept_x = np.unique(xy[cells, 0])
    np.testing.assert_allclose(kept_x, -kept_x[::-1], atol=1e-9)  # symmetric about the membrane centre
    assert kept_x[0] == xy[:, 0].min() and kept_x[-1] == xy[:, 0].max()
    with pytest.raises(ValueError, match="not a tensor-product grid"):
        paper_mesh.grid_subset(np.random.default_rng(0).uniform(size=(50, 2)), 4)


def test_a_subset_dataset_holds_the_same_values_on_the_kept_cells(paper_mesh, tmp_path):
    from skinfem.config import load_config
    from skinfem.io import STATUS_FAILED, STATUS_OK, StrainDataset, create_dataset, write_simulation

    config, xy = load_config("small"), graded_grid(8)
    rng = np.random.default_rng(1)
    params = rng.uniform(size=(3, 5))
    path = tmp_path / "full.h5"
    create_dataset(
        path,
        config,
        params,
        np.array([[0.05, -0.05]]),
        np.array([0.5, 1.0]),
        xy,
        np.ones(len(xy)),
        np.array([0, 0, 1]),
        "sha",
        np.stack([np.zeros(5), np.ones(5)], 1),
    )
    fields = rng.normal(size=(2, 2, len(xy), 3))
    write_simulation(path, 0, 0, fields[0], STATUS_OK)
    write_simulation(path, 1, 0, None, STATUS_FAILED, "diverged")
    write_simulation(path, 2, 0, fields[1], STATUS_OK)
    cells = paper_mesh.grid_subset(xy, 2)
    sub = StrainDataset.open(paper_mesh.write_subset(path, cells, tmp_path / "sub.h5"))
    assert sub.shape == (3, 1, 2, len(cells)) and sub.mesh_sha256 == f"sha:cells{len(cells)}"
    np.testing.assert_array_equal(sub.status, [[STATUS_OK], [STATUS_FAILED], [STATUS_OK]])
    np.testing.assert_allclose(sub.strain(2, 0), fields[1][:, cells].astype(np.float32))
    np.testing.assert_array_equal(sub.xy, xy[cells])


def test_the_side_by_side_table_has_a_row_per_case_and_run(paper_mesh, tmp_path):
    def study(width: float, covered: float, identified: bool) -> dict:
        names = paper_mesh.PARAMS
        return {
            "noise": None,
            "explained_variance": {},
            "n_components": {},
            "r2_per_pc": {},
            "study": {
                "setup": {"designs": [0], "frames": [-1], "label": "design 0"},
                "materials": [1, 2],
                "coverage_95": dict.fromkeys(names, covered),
                "median_interval_share_of_prior": dict.fromkeys(names, width),
                "identified": dict.fromkeys(names, identified),
                "max_r_hat": 1.01,
            },
        }

    for label, results in (
        ("a", {"clean": study(0.1, 1.0, True), "s1": study(0.9, 0.95, False)}),
        ("b", {"clean": study(0.2, 0.9, True)}),
    ):
        (tmp_path / label).mkdir()
        (tmp_path / label / "noise_study.json").write_text(json.dumps(results))
    runs = [paper_mesh.StudyRun.read(f"{k}={tmp_path / k}") for k in "ab"]
    lines = paper_mesh.side_by_side(runs).splitlines()
    assert lines[2] == "| clean | a | " + "0.10 / 100% | " * 5 + "μ, k₁, k₂, κ, θ |"
    assert lines[3].startswith("| clean | b | 0.20 / 90%") and lines[4].endswith("| none |")
    assert len(lines) == 5  # header, rule, clean a, clean b, s1 a (b has no s1)


def test_the_coverage_table_counts_each_case_and_pools_the_noisy_ones(paper_mesh):
    from inference.coverage import case_result

    rng = np.random.default_rng(3)
    bounds = np.array([[0.0, 1.0]] * 5)
    draws = rng.uniform(0.4, 0.6, size=(400, 5))  # 50 % interval ~[0.45, 0.55], 95 % ~[0.405, 0.595]
    inside, outside = np.full(5, 0.5), np.full(5, 0.9)
    hit, miss = case_result(draws, inside, bounds, 0), case_result(draws, outside, bounds, 2)
    assert hit.covered_50 == (True,) * 5 and miss.covered_95 == (False,) * 5 and miss.rank == (99,) * 5
    table, record = paper_mesh.coverage_table({"clean": [hit, hit], "s1": [hit, miss], "l10": [miss, miss]})
    assert record["clean"]["coverage_95"]["mu"] == 1.0 and record["s1"]["coverage_50"]["theta"] == 0.5
    assert record["all noisy cases"] == {
        "n": 4,
        "coverage_50": dict.fromkeys(paper_mesh.PARAMS, 0.25),
        "coverage_95": dict.fromkeys(paper_mesh.PARAMS, 0.25),
    }
    assert table.splitlines()[-1].startswith("| all noisy cases | 4 | 0.25 / 0.25")


def test_posteriors_equal_to_the_prior_cover_the_materials_in_its_central_half(paper_mesh):
    """Closed form: truths at 0.5, 0.9 and 0.99 of a uniform prior's range lie inside its central
    50 % / 95 % intervals [0.25, 0.75] / [0.025, 0.975] for 1 / 2 of the 3 materials."""
    bounds = np.tile([[0.0, 2.0]], (3, 5, 1))
    truths = np.outer([0.5, 0.9, 0.99], np.full(5, 2.0))
    _, record = paper_mesh.coverage_table({"s1": []}, paper_mesh.prior_alone(truths, bounds))
    assert record["prior alone"]["n"] == 3
    assert record["prior alone"]["coverage_50"] == dict.fromkeys(paper_mesh.PARAMS, 0.333)
    assert record["prior alone"]["coverage_95"] == dict.fromkeys(paper_mesh.PARAMS, 0.667)


def test_white_noise_keeps_its_sd_on_the_weights_and_correlated_noise_exceeds_it(paper_mesh, small_dataset, tmp_path):
    """An orthonormal PCA basis keeps white noise's variance on every weight (sd / amplitude = 1,
    up to the sampling error of 400 fields, 3.5 %); noise correlated over 5 mm lies along the
    smooth leading PCs and puts several times its amplitude on them."""
    from inference.noise import add_noise
    from skinfem.io import StrainDataset
    from surrogate.emulator import fit_emulator

    clean = StrainDataset.open(small_dataset)
    for case, length in (("white", 1e-3), ("long", 5.0)):
        folder = tmp_path / "cases" / case
        folder.mkdir(parents=True)
        noisy = StrainDataset.open(add_noise(clean, folder / "data.h5", length, 0.01, seed=1))
        fit_emulator(noisy, n_components=3, pca_scaling="none", restarts=0, cv_folds=2).save(folder / "emulator")
    white, long = (paper_mesh.noise_on_weights(tmp_path, case) for case in ("white", "long"))
    assert white["draws"] == 400 and white["length_mm"] == 1e-3
    for c in ("xx", "yy"):
        assert all(0.88 < r < 1.12 for r in white[c]["sd_over_amplitude"]), white[c]
        assert long[c]["sd_over_amplitude"][0] > 2.5, long[c]


def test_prior_alone_takes_the_noisy_cases_materials_or_the_clean_ones_in_a_clean_study(paper_mesh, tmp_path):
    from inference.posterior_file import ParameterSummary, PosteriorSummary

    def summary(study: str, case: str, material: int, truth: float) -> None:
        estimate = ParameterSummary(0.5, 0.1, 0.9, 1.0, 400.0, 400.0, (0.0, 2.0), 0.4, truth, True)
        folder = tmp_path / study / "cases" / case / "posteriors" / f"material_{material:03d}"
        folder.mkdir(parents=True)
        parameters = dict.fromkeys(paper_mesh.PARAMS, estimate)
        PosteriorSummary(parameters, 4, 100, 0, (0.1,) * 4, (0.8,) * 4, 1.0, None, None, None, ()).write(
            folder / "summary.json"
        )

    for study in ("clean only", "with noise"):
        summary(study, "clean", 3, 0.2)
        summary(study, "clean", 5, 0.4)
    summary("with noise", "s1", 7, 0.6)
    truths, bounds = paper_mesh.noisy_truths(tmp_path / "clean only")
    np.testing.assert_allclose(np.sort(truths[:, 0]), [0.2, 0.4])
    np.testing.assert_allclose(bounds, np.tile([0.0, 2.0], (2, 5, 1)))
    truths, _ = paper_mesh.noisy_truths(tmp_path / "with noise")
    np.testing.assert_allclose(truths, np.full((1, 5), 0.6))
