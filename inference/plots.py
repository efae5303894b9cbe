"""Figures of the inference package (matplotlib, written to PNG under a temporary name, then renamed)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from skinfem.io import COMPONENTS
from skinfem.outputs import save_figure

if TYPE_CHECKING:
    from inference.posterior_file import PosteriorSummary

LABELS = {
    "mu": "μ [MPa]",
    "k1": "k₁ [MPa]",
    "k2": "k₂ [-]",
    "kappa": "κ [-]",
    "theta": "θ [deg]",
}


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (figures are written to files)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def corner_plot(samples, path: Path | str, title: str | None = None) -> Path:
    """Posterior pairs of the five skin parameters over the prior box (the paper's Fig. 7).

    Drawn by ArviZ's pair plot (:func:`arviz.plot_pair`): diagonal, the posterior's KDE against the
    uniform prior density (grey); below it, the draws with their 25/50/90 % KDE contours. Axes span
    the prior box. The true value, when known, is drawn in red.
    """
    pyplot()  # the Agg backend, selected before ArviZ imports pyplot
    import arviz as az
    from arviz_base.labels import MapLabeller

    names = list(LABELS)
    bounds = samples.bounds
    truth = samples.truth
    dt = az.from_dict({"posterior": {n: samples.draws[..., k] for k, n in enumerate(names)}})
    matrix = az.plot_pair(
        dt,
        marginal=True,
        marginal_kind="kde",
        triangle="lower",
        backend="matplotlib",
        labeller=MapLabeller(var_name_map=LABELS),
        visuals={"scatter": {"alpha": 0.1, "color": "C0"}, "contour": {"color": "k"}},
        figure_kwargs={"figsize": (10, 10)},
    )
    fig = matrix.viz["figure"].item()
    axes = matrix.viz["plot"].values  # (row, col): y variable, x variable
    for i in range(5):
        for j in range(i + 1):
            ax = axes[i, j]
            ax.set_xlim(bounds[j])
            if i == j:
                prior = 1 / np.ptp(bounds[i])
                ax.axhline(prior, color="0.5", lw=1.5, label="prior")
                ax.set_ylim(0, max(ax.get_ylim()[1], 1.2 * prior))
                if truth is not None:
                    ax.axvline(truth[i], color="r", lw=1.5, label="true")
                ax.set_yticks([])
                ax.set_ylabel("")
            else:
                ax.set_ylim(bounds[i])
                if truth is not None:
                    ax.plot(truth[j], truth[i], "r+", ms=12, mew=2)
                if j > 0:
                    ax.tick_params(labelleft=False)
            ax.tick_params(labelsize=8)
            ax.xaxis.label.set_fontsize(11)
            ax.yaxis.label.set_fontsize(11)
    axes[0, 0].legend(fontsize=8, loc="upper right")
    fig.suptitle(title or "posterior (blue) against the uniform prior (grey); truth in red", fontsize=12)
    return save_figure(fig, path)


def accuracy_plot(summaries: list[PosteriorSummary], bounds: np.ndarray, path: Path | str, title: str) -> Path:
    """True value vs posterior median with 95 % intervals, one panel per parameter (Fig. 9);
    one point per posterior summary (its truth must be known)."""
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    names = list(LABELS)
    fig, axes = plt.subplots(1, 5, figsize=(17, 3.6))
    for k, (ax, n) in enumerate(zip(axes, names)):
        true = np.array([s.parameters[n].true for s in summaries], dtype=float)
        med = np.array([s.parameters[n].median for s in summaries])
        lo = np.array([s.parameters[n].q2_5 for s in summaries])
        hi = np.array([s.parameters[n].q97_5 for s in summaries])
        covered = (lo <= true) & (true <= hi)
        ax.errorbar(true, med, yerr=[med - lo, hi - med], fmt="o", ms=4, capsize=2, color="C0", ecolor="C0", alpha=0.8)
        ax.plot(
            true[~covered],
            med[~covered],
            "o",
            mfc="none",
            mec="r",
            mew=1.5,
            ms=9,
            label="truth outside the 95 % interval",
        )
        ax.plot(bounds[k], bounds[k], "k--", lw=0.8)
        ax.set_xlim(bounds[k])
        ax.set_ylim(bounds[k])
        ax.set_xlabel(f"true {LABELS[n]}")
        ax.set_ylabel(f"posterior {LABELS[n]}")
        ax.set_title(f"coverage {covered.mean():.0%}", fontsize=10)
        ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.tick_params(labelsize=8)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle(title, fontsize=11)
    return save_figure(fig, path)


def strain_maps(
    xy: np.ndarray,
    fields: list[np.ndarray],
    titles: list[str],
    path: Path | str,
    membrane_half: float = 10.0,
    theta_deg: float | None = None,
    window: float = 20.0,
    symmetric: bool = True,
    suptitle: str = "",
) -> Path:
    """One row of cell-wise strain maps (see :func:`field_grid`)."""
    return field_grid(xy, [fields], [titles], path, membrane_half, theta_deg, window, symmetric, suptitle)


def field_grid(
    xy: np.ndarray,
    rows: list[list[np.ndarray]],
    titles: list[list[str]],
    path: Path | str,
    membrane_half: float = 10.0,
    theta_deg: float | None = None,
    window: float = 20.0,
    symmetric: bool = True,
    suptitle: str = "",
) -> Path:
    """Cell-wise maps in a grid, membrane outline dashed, fiber direction arrowed.

    Args:
        xy: (n_cells, 2) centroids [mm]; rows: lists of (n_cells,) values (NaN = not observed).
        window: half-width of the shown region [mm].
        symmetric: diverging colour map centred on 0 (else sequential from the minimum).

    Longer than a screen: one panel's drawing steps (field, outline, fibers, colour bar) in order.
    """
    plt = pyplot()
    from matplotlib.tri import Triangulation

    tri = Triangulation(xy[:, 0], xy[:, 1])
    n_rows, n_cols = len(rows), max(len(r) for r in rows)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(4.3 * n_cols, 3.9 * n_rows), squeeze=False)
    for r, (row, row_titles) in enumerate(zip(rows, titles)):
        for ax, values, title in zip(axes[r], row, row_titles):
            vmax = np.nanmax(np.abs(values))
            shown = np.where(np.isfinite(values), values, 0.0)
            masked = ~np.all(np.isfinite(values[tri.triangles]), axis=1)
            tri.set_mask(masked)
            im = ax.tripcolor(
                tri,
                shown,
                shading="gouraud",
                cmap="RdBu_r" if symmetric else "viridis",
                vmin=-vmax if symmetric else None,
                vmax=vmax,
            )
            tri.set_mask(None)
            membrane_outline(ax, membrane_half)
            if theta_deg is not None:
                t = np.radians(theta_deg)
                tail = -0.9 * window
                ax.annotate(
                    "",
                    xy=(tail + 0.35 * window * np.cos(t), tail + 0.35 * window * np.sin(t)),
                    xytext=(tail, tail),
                    arrowprops=dict(arrowstyle="->", color="k", lw=1.5),
                )
                ax.text(tail + 0.4 * window, tail, f"fibers {theta_deg:.0f}°", fontsize=8, va="center")
            ax.set_xlim(-window, window)
            ax.set_ylim(-window, window)
            ax.set_aspect("equal")
            ax.set_xlabel("x [mm]")
            ax.set_ylabel("y [mm]")
            ax.set_title(title, fontsize=10)
            fig.colorbar(im, ax=ax, label="log strain [-]", shrink=0.85)
        for ax in axes[r, len(row) :]:
            ax.axis("off")
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    return save_figure(fig, path)


def membrane_outline(ax, half: float) -> None:
    """The membrane's square outline (half side ``half`` [mm]), dashed."""
    ax.plot([-half, half, half, -half, -half], [-half, -half, half, half, -half], "k--", lw=1)


def plot_field(xy: np.ndarray, strain: np.ndarray, path: Path | str, membrane_half: float, title: str = "") -> Path:
    """Scatter maps of log strain xx, yy, xy at the points (n, 2) [mm], membrane outline dashed."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    h = membrane_half
    for ax, values, name in zip(axes, strain.T, COMPONENTS):
        vmax = max(float(np.abs(values).max()), 1e-12)
        im = ax.scatter(xy[:, 0], xy[:, 1], c=values, s=12, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        membrane_outline(ax, h)
        ax.annotate("", xy=(0.6 * h, 0), xytext=(0, 0), arrowprops=dict(arrowstyle="->", lw=1.2))
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm] (α11 direction)")
        ax.set_ylabel("y [mm]")
        ax.set_title(f"log strain {name}", fontsize=10)
        fig.colorbar(im, ax=ax, shrink=0.85)
    if title:
        lines = [wrapped for line in title.splitlines() for wrapped in textwrap.wrap(line, 130)]
        fig.suptitle("\n".join(lines), fontsize=10)
    return save_figure(fig, path)
