"""The figures of the model-criticism report: residual maps, regions, the error falling as
effects are added, the candidates' scores."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from inference.criticism.check import CheckResult
from inference.criticism.diagnosis import STRONG_EVIDENCE
from inference.criticism.metrics import MembraneRegions
from inference.plots import field_grid, pyplot, save_figure
from skinfem.config import THETA

COMPONENT_LABELS = ("E_xx", "E_yy", "E_xy")


def residual_maps(result: CheckResult, version: int, path: Path) -> list[Path]:
    """Measured | model | residual per component (rows), one PNG per observation."""
    cal = result.versions[version].calibration
    paths = []
    for o, obs in enumerate(result.observations):
        mask = result.data.masks[o]
        rows, titles = [], []
        for k, c in enumerate(COMPONENT_LABELS):
            measured, model = result.data.fields[o, mask, k], cal.model_fields[o, mask, k]
            rows.append([measured, model, measured - model])
            titles.append([f"measured {c}", f"model {c} ({cal.label})", f"residual {c}"])
        out = path.with_name(f"{path.stem}_obs{o}.png")
        field_grid(
            result.data.xy[o, mask],
            rows,
            titles,
            out,
            result.membrane.half,
            float(cal.x[THETA]),
            window=2 * result.membrane.half,
            suptitle=f"{cal.label}: α = ({obs.alpha[0]:g}, {obs.alpha[1]:g}), t = {obs.t:g}; "
            f"residual RMSE {result.versions[version].metrics.rmse:.2e}",
        )
        paths.append(out)
    return paths


def draw_regions(ax, membrane: MembraneRegions, theta: float) -> None:
    """The membrane (|x|, |y| = ``membrane.half`` [mm], dashed), its edge strip (± ``membrane.band``
    [mm], dotted) and the fiber direction ``theta`` [rad] (cyan) on ``ax``."""
    h, b = membrane.half, membrane.band
    for d, style in ((h, "k--"), (h - b, "k:"), (h + b, "k:")):
        ax.plot([-d, d, d, -d, -d], [-d, -d, d, d, -d], style, lw=1)
    r = 2.2 * h
    for sign in (1, -1):
        ax.plot([0, sign * r * np.cos(theta)], [0, sign * r * np.sin(theta)], "c-", lw=1, alpha=0.8)


def regions_map(result: CheckResult, version: int, path: Path) -> Path:
    """Per-point RMS standardised residual (all observations) with the region outlines and, for
    the baseline, the diagnosis's hotspot circled."""
    plt = pyplot()

    v = result.versions[version]
    data = result.data
    per_point = np.sqrt(data.point_mean_square(v.calibration.model_fields))[data.masks]
    xy = data.xy[data.masks]
    fig, ax = plt.subplots(figsize=(7.5, 6))
    im = ax.scatter(xy[:, 0], xy[:, 1], c=per_point, s=6, cmap="magma", vmin=0, vmax=max(3.0, per_point.max()))
    fig.colorbar(im, ax=ax, label="RMS residual / sd [-]  (noise and model error alone: 1)")
    h = result.membrane.half
    draw_regions(ax, result.membrane, np.radians(v.calibration.x[THETA]))
    if version == 0:
        spot = result.diagnosis.hotspot
        label = f"hotspot: {spot.rms_sigma:.1f} σ over its {spot.points} nearest points"
        ax.add_patch(plt.Circle((spot.x, spot.y), spot.radius, fill=False, color="lime", lw=1.5, label=label))
        ax.legend(loc="lower right", fontsize=8)
    ax.text(
        0.02,
        0.98,
        "\n".join(f"{i + 1}. {g.region}: {g.rms_sigma:.1f} σ" for i, g in enumerate(v.regions)),
        transform=ax.transAxes,
        fontsize=8,
        va="top",
        bbox=dict(facecolor="w", alpha=0.85, lw=0),
    )
    ax.set_xlim(-2.5 * h, 2.5 * h)
    ax.set_ylim(-2.5 * h, 2.5 * h)
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_title(
        f"where the {v.calibration.label} model fails (dashed: membrane, dotted: edge strip, cyan: fibers)", fontsize=9
    )
    return save_figure(fig, path)


def error_falls_plot(result: CheckResult, path: Path) -> Path:
    """RMSE and chi^2/dof of each model version against the noise level."""
    plt = pyplot()
    labels = [v.calibration.label.replace(" + ", "\n+ ") for v in result.versions]
    rmse = [v.metrics.rmse for v in result.versions]
    chi = [v.metrics.chi2_per_dof for v in result.versions]
    fig, axes = plt.subplots(1, 2, figsize=(4 + 1.6 * len(labels), 3.8))
    x = np.arange(len(labels))
    axes[0].bar(x, rmse, color="C0")
    axes[0].axhline(result.versions[0].metrics.noise_rms, color="k", ls="--", label="noise sd used (RMS)")
    axes[0].set_ylabel("residual RMSE [log strain]")
    axes[0].legend(fontsize=8)
    axes[1].bar(x, chi, color="C1")
    axes[1].axhline(1.0, color="k", ls="--", label="noise alone")
    axes[1].set_ylabel("χ² / dof [-]")
    axes[1].legend(fontsize=8)
    for ax in axes:
        ax.set_xticks(x, labels, fontsize=8)
    fig.suptitle("the error falls as missing physics is added", fontsize=11)
    return save_figure(fig, path)


def candidates_plot(result: CheckResult, path: Path) -> Path:
    """Delta BIC of every candidate (symlog), coloured by whether it explains the residual, with
    the strong-evidence threshold and the competing larger model error when there is one."""
    plt = pyplot()
    scores = result.diagnosis.scores
    fig, ax = plt.subplots(figsize=(7.5, 0.6 * len(scores) + 1.6))
    y = np.arange(len(scores))[::-1]
    colors = ["C2" if s.explains else "C1" if s.mesh_like else "0.6" for s in scores]
    ax.barh(y, [s.delta_bic for s in scores], color=colors)
    ax.axvline(STRONG_EVIDENCE, color="k", ls="--", lw=1, label=f"strong evidence (ΔBIC = {STRONG_EVIDENCE:g})")
    larger = result.diagnosis.larger_model_error
    if larger is not None:  # what a candidate must also beat (diagnosis.larger_model_error)
        label = f"the carried mesh error × {larger.factor:.2f} (ΔBIC = {larger.delta_bic:+.0f})"
        ax.axvline(larger.delta_bic, color="C3", ls=":", lw=1.5, label=label)
    ax.set_xscale("symlog", linthresh=10)
    ax.set_yticks(
        y,
        [f"{s.effect}\n({s.share_explained:.0%} of excess, {'fit' if s.fitted else 'lin.'})" for s in scores],
        fontsize=8,
    )
    ax.set_xlabel("ΔBIC of adding the effect [-] (> 0 favours it)")
    ax.set_title(
        "which effect is missing (green: explains the residual; orange: so would the mesh's error)", fontsize=10
    )
    ax.legend(fontsize=8, loc="lower right")  # the bars start at the top
    return save_figure(fig, path)
