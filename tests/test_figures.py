"""Figures from small synthetic inputs (no FE, no sampling): the posterior corner plot (ArviZ's
pair plot), the noise study's explained-variance and sensitivity figures and the surrogate's
explained-variance figure. Checked: a PNG is written; moduli are in MPa; cases or components that
coincide stay distinguishable (own style each, offset along M) and legends do not cover the data.

Each test captures the matplotlib figure on its way to ``save_figure`` to inspect it.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import inference.plots
import inference.studies
import surrogate.validation
from inference.plots import LABELS, corner_plot
from inference.studies import NoiseCase, case_name, explained_variance_plot, sensitivity_maps
from skinfem.outputs import save_figure
from surrogate.emulator import Emulator, EmulatorProvenance
from surrogate.gp import GPBank, fit_gps
from surrogate.pca import StrainPCA
from surrogate.validation import plot_explained_variance

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# the default prior box (skinfem.config): mu, k1 [MPa], k2, kappa [-], theta [deg]
BOUNDS = np.array([[0.000543, 0.00206], [0.0117, 0.0225], [8.31, 15.32], [0.27, 0.30], [0.0, 90.0]])
DESIGN = np.array([0.05, -0.05])


def assert_png(path: Path) -> None:
    assert path.is_file() and path.read_bytes()[:8] == PNG_MAGIC


@pytest.fixture
def captured(monkeypatch):
    """Figures passed to ``save_figure`` by the three modules (saved as usual)."""
    figures = []

    def capture(fig, path, **kwargs):
        figures.append(fig)
        return save_figure(fig, path, **kwargs)

    for module in (inference.plots, inference.studies, surrogate.validation):
        monkeypatch.setattr(module, "save_figure", capture)
    return figures


def axis_labels(fig) -> set[str]:
    return {label for ax in fig.axes for label in (ax.get_xlabel(), ax.get_ylabel())} - {""}


def legend_outside(fig, ax, legend) -> bool:
    """``legend`` lies right of the axes ``ax`` in the laid-out figure (closed figures lose their
    canvas: a new Agg canvas renders it)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()
    return legend.get_window_extent(renderer).x0 >= ax.get_window_extent(renderer).x1


def styles(lines) -> list[tuple]:
    return [(tuple(np.atleast_1d(line.get_color())), line.get_linestyle(), line.get_marker()) for line in lines]


# -- the posterior corner plot -------------------------------------------------------------------
def fake_samples(truth: bool) -> SimpleNamespace:
    """What corner_plot reads of PosteriorSamples: draws (chains, draws, dim), bounds, truth."""
    rng = np.random.default_rng(0)
    centre, spread = BOUNDS.mean(1), 0.1 * np.ptp(BOUNDS, 1)
    draws = rng.normal(centre, spread, size=(2, 300, 5)).clip(BOUNDS[:, 0], BOUNDS[:, 1])
    noise_scales = rng.lognormal(size=(2, 300, 2))  # the sampler's extra (non-skin) dimensions
    return SimpleNamespace(
        draws=np.concatenate([draws, noise_scales], -1), bounds=BOUNDS, truth=centre + 0.5 * spread if truth else None
    )


@pytest.mark.parametrize("truth", [True, False], ids=["with_truth", "without_truth"])
def test_corner_plot_labels_moduli_in_mpa_and_spans_the_prior_box(tmp_path, captured, truth):
    path = corner_plot(fake_samples(truth), tmp_path / "corner.png")
    assert path == tmp_path / "corner.png"
    assert_png(path)
    (fig,) = captured
    labels = axis_labels(fig)
    assert {LABELS[n] for n in LABELS} <= labels
    assert {"μ [MPa]", "k₁ [MPa]", "θ [deg]"} <= labels and not any("kPa" in s for s in labels)
    grid = np.array(fig.axes[:25], dtype=object).reshape(5, 5)  # ArviZ's row-major (y, x) grid
    assert grid[4, 0].get_xlabel() == "μ [MPa]" and grid[1, 0].get_ylabel() == "k₁ [MPa]"
    for j in range(5):
        np.testing.assert_allclose(grid[4, j].get_xlim(), BOUNDS[j])
    legend = [t.get_text() for t in grid[0, 0].get_legend().get_texts()]
    assert legend == (["prior", "true"] if truth else ["prior"])
    red_crosses = [line for ax in fig.axes for line in ax.get_lines() if line.get_marker() == "+"]
    assert len(red_crosses) == (10 if truth else 0)  # one per lower-triangle panel


# -- the noise study's explained variance --------------------------------------------------------
def fake_results(lengths=(0.1, 1.0, 5.0), levels=(0.01, 0.05, 0.10)) -> dict[str, NoiseCase]:
    """noise_study's results: every case with the clean curves (all coincide) plus its noise."""
    curve = np.cumsum([0.7, 0.2, 0.05, 0.03, 0.01, 0.005, 0.002, 0.001]).tolist()
    ev = {c: curve for c in ("xx", "yy", "xy")}

    def case(length: float | None, level: float | None) -> NoiseCase:
        return NoiseCase(None, length, level, study=None, explained_variance=ev, n_components={}, r2_per_pc={})

    results = {"clean": case(None, None)}
    for length in lengths:
        for level in levels:
            results[case_name(length, level)] = case(length, level)
    return results


def test_explained_variance_plot_keeps_coinciding_cases_apart(tmp_path, captured):
    results = fake_results()
    path = explained_variance_plot(results, tmp_path / "explained_variance.png")
    assert_png(path)
    (fig,) = captured
    assert len(fig.axes) == 3
    for ax in fig.axes:
        lines = [line for line in ax.get_lines() if line.get_label() != "99 %" and len(line.get_xdata()) > 2]
        assert len(lines) == len(results)
        assert len(set(styles(lines))) == len(results)  # own colour / line style / marker per case
        starts = [line.get_xdata()[0] for line in lines]
        assert len(set(starts)) == len(results) and max(starts) - min(starts) < 1  # offset, M still readable
    legend = fig.axes[-1].get_legend()
    texts = [t.get_text() for t in legend.get_texts()]
    assert texts[0] == "clean" and texts[1].startswith("s1: ℓ = 0.1 mm, level 1 %") and texts[-1] == "99 %"
    assert legend_outside(fig, fig.axes[-1], legend)


def test_explained_variance_plot_of_a_single_noisy_case(tmp_path, captured):
    """The integration test's study: clean plus one case."""
    path = explained_variance_plot(fake_results((1.0,), (0.05,)), tmp_path / "explained_variance.png")
    assert_png(path)
    (fig,) = captured
    lines = [line for line in fig.axes[0].get_lines() if line.get_label() != "99 %"]
    assert [line.get_label() for line in lines] == ["clean", "m5: ℓ = 1 mm, level 5 %"]


# -- synthetic emulator (PCA + GPs on smooth fake weights: no dataset, no FE) ---------------------
def synthetic_emulator(seed: int = 0) -> Emulator:
    """Three components with 3, 2 and 2 PCs of 40 cells over the default prior box."""
    rng = np.random.default_rng(seed)
    pcas = {}
    for c, m, decay in (("xx", 3, 0.5), ("yy", 2, 0.45), ("xy", 2, 0.4)):  # similar spectra: curves close
        fields = rng.normal(size=(50, 10)) * decay ** np.arange(10) @ rng.normal(size=(10, 40))
        pcas[c] = StrainPCA(n_components=m).fit(fields + 0.01 * rng.normal(size=(50, 40)))
    x = rng.uniform(size=(40, 7))  # unit box
    n_weights = sum(p.n_components_ for p in pcas.values())
    y = np.column_stack([np.sin(3 * x[:, 0] + g) + (g + 1) * x[:, 1] ** 2 for g in range(n_weights)])
    gps = GPBank.from_sklearn(fit_gps(x, y, restarts=0, n_jobs=1))
    provenance = EmulatorProvenance(
        dataset=Path("/data/synthetic.h5"),
        dataset_config='name = "synthetic"\n',
        mesh_sha256="0" * 64,
        block_half_length=20.0,
        train_materials=(0, 1),
        test_materials=(2,),
        n_training_rows=50,
        n_gp_rows=40,
        gp_fraction=0.8,
        restarts=0,
        seed=seed,
        explained_variance_ratio={c: tuple(p.explained_variance_ratio_[:20].tolist()) for c, p in pcas.items()},
        fit_seconds={"total": 0.0},
        versions={"skinid": "0.0.0"},
    )
    lower = np.r_[BOUNDS[:, 0], -0.05, -0.05]
    upper = np.r_[BOUNDS[:, 1], 0.05, 0.05]
    return Emulator(
        pcas=pcas,
        gps=gps,
        lower=lower,
        upper=upper,
        xy=rng.uniform(-20, 20, size=(40, 2)),
        volume=np.full(40, 0.5),
        provenance=provenance,
    )


@pytest.fixture(scope="module")
def emulator() -> Emulator:
    return synthetic_emulator()


def test_sensitivity_maps_are_over_mu_and_k1_in_mpa(tmp_path, captured, emulator):
    cases = ["clean", "m1"]
    for name in cases:
        emulator.save(tmp_path / "cases" / name / "emulator")
    path = sensitivity_maps(tmp_path, cases, 0, DESIGN, tmp_path / "sensitivity.png", n=11)
    assert_png(path)
    (fig,) = captured
    maps = [ax for ax in fig.axes if ax.get_title()]
    assert len(maps) == 4
    for ax in maps:
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("μ [MPa]", "k₁ [MPa]")
        np.testing.assert_allclose(ax.get_xlim(), BOUNDS[0])  # the box in MPa, not scaled to kPa
        np.testing.assert_allclose(ax.get_ylim(), BOUNDS[1])


# -- the surrogate's explained variance ----------------------------------------------------------
def test_surrogate_explained_variance_gives_each_component_its_own_style(tmp_path, captured, emulator):
    path = plot_explained_variance(emulator, tmp_path / "explained_variance.png")
    assert_png(path)
    (fig,) = captured
    (ax,) = fig.axes
    curves = [line for line in ax.get_lines() if line.get_label().startswith("E_")]
    assert [line.get_label() for line in curves] == ["E_xx (M = 3)", "E_yy (M = 2)", "E_xy (M = 2)"]
    assert len(set(styles(curves))) == 3
    assert len({line.get_xdata()[0] for line in curves}) == 3  # shifted apart along M
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert texts == ["E_xx (M = 3)", "E_yy (M = 2)", "E_xy (M = 2)", "99 %"]
