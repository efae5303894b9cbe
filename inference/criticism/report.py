"""The model-criticism report: report.md, report.json and its figures; :func:`read_report` reads
report.json back."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from inference.criticism.calibration import Estimate
from inference.criticism.check import CheckResult, CheckTimings
from inference.criticism.diagnosis import CandidateScore, Diagnosis, LargerModelError
from inference.criticism.metrics import Hotspot, RegionResidual, ResidualMetrics
from inference.plots import field_grid, pyplot, save_figure
from skinfem.effects import EFFECTS, get_effect
from skinfem.outputs import write_text

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
            result.half,
            float(cal.x[4]),
            window=2 * result.half,
            suptitle=f"{cal.label}: α = ({obs.alpha[0]:g}, {obs.alpha[1]:g}), t = {obs.t:g}; "
            f"residual RMSE {result.versions[version].metrics.rmse:.2e}",
        )
        paths.append(out)
    return paths


def regions_map(result: CheckResult, version: int, path: Path) -> Path:
    """Per-point RMS standardised residual (all observations) with the region outlines and, for
    the baseline, the diagnosis's hotspot circled."""
    plt = pyplot()

    v = result.versions[version]
    data = result.data
    per_point = np.sqrt(np.nanmean(data.standardised(v.calibration.model_fields) ** 2, axis=2))[data.masks]
    xy = data.xy[data.masks]
    fig, ax = plt.subplots(figsize=(7.5, 6))
    im = ax.scatter(xy[:, 0], xy[:, 1], c=per_point, s=6, cmap="magma", vmin=0, vmax=max(3.0, per_point.max()))
    fig.colorbar(im, ax=ax, label="RMS residual / sd [-]  (noise and model error alone: 1)")
    h = result.half
    band = result.band
    for d, style in ((h, "k--"), (h - band, "k:"), (h + band, "k:")):
        ax.plot([-d, d, d, -d, -d], [-d, -d, d, d, -d], style, lw=1)
    theta = np.radians(v.calibration.x[4])
    r = 2.2 * h
    for sign in (1, -1):
        ax.plot([0, sign * r * np.cos(theta)], [0, sign * r * np.sin(theta)], "c-", lw=1, alpha=0.8)
    if version == 0:
        spot = result.diagnosis.hotspot
        ax.add_patch(
            plt.Circle(
                (spot.x, spot.y),
                spot.radius,
                fill=False,
                color="lime",
                lw=1.5,
                label=f"hotspot: {spot.rms_sigma:.1f} σ over its {spot.points} nearest points",
            )
        )
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
    axes[0].axhline(result.versions[0].metrics.noise_rms, color="k", ls="--", label="stated noise sd (RMS)")
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
    colors = ["C2" if s.explains else "0.6" for s in scores]
    ax.barh(y, [s.delta_bic for s in scores], color=colors)
    ax.axvline(6, color="k", ls="--", lw=1, label="strong evidence (ΔBIC = 6)")
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
    ax.set_title("which effect is missing (green: explains the residual)", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")  # the bars start at the top
    return save_figure(fig, path)


def discretisation_lines(result: CheckResult) -> list[str]:
    disc = result.discretisation
    if disc is None:
        return ["Discretisation error: not estimated (--no-discretisation).", ""]
    return [
        "### The check's own discretisation error",
        "",
        disc.summary(),
        "",
        "| | RMS, share of the field | RMS [noise sd] |",
        "|---|---|---|",
        f"| check mesh ({disc.mesh}) | {disc.relative:.1%} | {disc.sigma:.2f} |",
        f"| after the fitted correction (carried in the covariance) | {disc.remaining_relative:.1%} "
        f"| {disc.remaining_sigma:.2f} |",
        "",
        f"The carried error is correlated between points like the two meshes' difference: "
        f"{1 - result.data.model_error.nugget:.0%} of its variance over {result.data.model_error.length:.2g} mm, "
        "the rest independent.",
        "",
    ]


def failure_lines(result: CheckResult) -> list[str]:
    if not result.failures:
        return ["Every FE run converged.", ""]
    lines = [
        f"{len(result.failures)} FE run(s) did not converge; each was a rejected step (the calibration "
        "shortened its step) or a one-sided signature difference:",
        "",
    ]
    return (
        lines
        + [f"- {', '.join(f'{n} = {v:.4g}' for n, v in zip(result.names, f.x))}: {f.message}" for f in result.failures]
        + [""]
    )


def _fmt(value: float) -> str:
    return f"{value:.4g}"


def write_report(result: CheckResult, out: Path | str) -> Path:
    """Write report.md, report.json and the PNGs into ``out``; returns the report path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    last = len(result.versions) - 1
    baseline_maps = residual_maps(result, 0, out / "residual_baseline.png")
    final_maps = residual_maps(result, last, out / "residual_final.png") if last else []
    regions_map(result, 0, out / "regions.png")
    candidates_plot(result, out / "candidates.png")
    error_falls_plot(result, out / "error_falls.png")
    lines = (
        compare_lines(result)
        + discretisation_lines(result)
        + failure_lines(result)
        + [f"![baseline residual, observation {i}]({p.name})" for i, p in enumerate(baseline_maps)]
        + region_lines(result)
        + candidate_lines(result)
        + version_lines(result, final_maps)
        + next_round_lines(result)
        + cost_lines(result)
    )
    path = out / "report.md"
    write_text(out / "report.json", json.dumps(finite_or_null(report_dict(result)), indent=2, allow_nan=False) + "\n")
    write_text(path, "\n".join(lines))  # last: a report.md means a complete report
    return path


def compare_lines(result: CheckResult) -> list[str]:
    """Title, noise, verdict and section 1's metrics table of the baseline."""
    base = result.versions[0].metrics
    return [
        "# Model criticism report",
        "",
        f"{len(result.observations)} observation(s), {result.data.n} data values; noise sd "
        f"{'(estimated, see the verdict) ' if not result.noise_statement.consistent else ''}"
        f"{', '.join(f'{s:.2g}' for s in result.data.noise.sd)} (xx, yy, xy), correlation length "
        f"{result.data.noise.length:g} mm, uncorrelated share {result.data.noise.nugget:g}.",
        "",
        "## Verdict",
        "",
        result.diagnosis.text,
        "",
        "## 1. Compare: the calibrated baseline against the measurements",
        "",
        f"Calibrated on the FE model (Levenberg–Marquardt from the {result.start_from}; Laplace posterior), "
        f"measured like the DIC system: {result.gauge_text}.",
        "",
        "| metric | value | noise alone |",
        "|---|---|---|",
        f"| residual RMSE [log strain] | {_fmt(base.rmse)} | {_fmt(base.noise_rms)} |",
        f"| χ²/dof (whitened, dof = {base.dof}) | {base.chi2_per_dof:.3f} | 1 ± {np.sqrt(2 / base.dof):.3f} |",
        f"| posterior-predictive p-value | {base.ppc_p:.3f} | uniform on [0, 1] |",
        f"| Moran's I of the residual / sd (z vs the noise model) | {base.moran_I:.3f} "
        f"(z = {base.moran_z:.1f}) | z ~ N(0, 1) |",
        "",
    ]


def region_lines(result: CheckResult) -> list[str]:
    """Section 2: the regions ranked by their residual."""
    lines = [
        "",
        "## 2. Where the model fails",
        "",
        "RMS of (measured − model) / sd over each region's points (noise and carried model error alone give 1):",
        "",
        "| rank | region | points | RMS [σ] |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {i + 1} | {g.region} | {g.points} | {g.rms_sigma:.2f} |" for i, g in enumerate(result.diagnosis.regions)
    ]
    spot = result.diagnosis.hotspot
    return lines + ["", f"The largest residual is {spot.summary()}.", "", "![regions](regions.png)"]


def candidate_lines(result: CheckResult) -> list[str]:
    """Section 3: the candidate effects' scores."""
    lines = [
        "",
        "## 3. Which effect is missing",
        "",
        "Each candidate's field signature at the calibrated parameters, with what re-tuning the skin "
        "parameters absorbs projected out; ΔBIC > 6 is strong evidence; 'fitted' rows were calibrated with "
        "the effect added.",
        "",
    ]
    return lines + candidate_table(result.diagnosis.scores) + ["", "![candidates](candidates.png)"]


def candidate_table(scores: list[CandidateScore]) -> list[str]:
    lines = [
        "| effect | ΔBIC | share of excess residual | confounding | score T (dof) | p | estimate | explains |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        est = ", ".join(f"{k.split('.')[-1]} = {v:.3g}" for k, v in s.estimate.items())
        lines.append(
            f"| {s.effect} | {s.delta_bic:+.1f} ({'fit' if s.fitted else 'linearised'}) | "
            f"{s.share_explained:.0%} | {s.confounding:.0%} | {s.statistic:.1f} ({s.dof}) | {s.p_value:.2g} | "
            f"{est} | {'**yes**' if s.explains else 'no'} |"
        )
    return lines


def next_round_lines(result: CheckResult) -> list[str]:
    """Section 6: what is still missing after the added effects (only with --add)."""
    d = result.next_round
    if d is None:
        return []
    return (
        [
            "",
            f"## 6. Next round: what is still missing with {result.versions[-1].calibration.label}",
            "",
            d.text,
            "",
            "| rank | region | points | RMS [σ] |",
            "|---|---|---|---|",
        ]
        + [f"| {i + 1} | {g.region} | {g.points} | {g.rms_sigma:.2f} |" for i, g in enumerate(d.regions)]
        + [""]
        + (candidate_table(d.scores) if d.scores else ["No candidate is left to test."])
    )


def version_lines(result: CheckResult, final_maps: list[Path]) -> list[str]:
    """Sections 4–5: each model version's metrics and estimates, the added effects, the final maps."""
    base = result.versions[0].metrics
    lines = [
        "",
        "## 4–5. Model versions: the error falls",
        "",
        "| version | parameters | RMSE | χ²/dof | PPC p | Moran z | ΔBIC vs baseline | consistent with noise |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for v in result.versions:
        m = v.metrics
        lines.append(
            f"| {v.calibration.label} | {m.n_params} | {_fmt(m.rmse)} | {m.chi2_per_dof:.3f} | "
            f"{m.ppc_p:.3f} | {m.moran_z:.1f} | {base.bic - m.bic:+.1f} | "
            f"{'yes' if not m.structured else 'no'} |"
        )
    lines += [
        "",
        "![error falls](error_falls.png)",
        "",
        "Parameter estimates (± 1 sd, Laplace):",
        "",
        "| parameter | " + " | ".join(v.calibration.label for v in result.versions) + " |",
        "|---|" + "---|" * len(result.versions),
    ]
    free = list(dict.fromkeys(n for v in result.versions for n in v.calibration.free_names))
    for name in free:
        cells = []
        for v in result.versions:
            e = v.calibration.estimates().get(name)
            cells.append(f"{_fmt(e.value)} ± {_fmt(e.sd)}" if e else "—")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    final = result.versions[-1].calibration
    added = [name for name in dict.fromkeys(n.split(".")[0] for n in final.free_names[5:]) if name in EFFECTS]
    for name in added:
        values = {q.split(".", 1)[1]: float(final.x[final.names.index(q)]) for q in get_effect(name).qualified_names()}
        lines += ["", f"{name} in the final version: {get_effect(name).describe(values)}"]
    if final_maps:
        lines += ["", f"Final version ({final.label}), residual maps:", ""]
        lines += [f"![final residual, observation {i}]({p.name})" for i, p in enumerate(final_maps)]
    return lines


def cost_lines(result: CheckResult) -> list[str]:
    """The wall time and FE runs of each phase."""
    t = result.timings
    return [
        "",
        "## Cost",
        "",
        f"compare {t.compare_s:.0f} s ({t.compare_fe_runs} FE runs), diagnose {t.diagnose_s:.0f} s "
        f"({t.diagnose_fe_runs} runs), add {t.add_s:.0f} s ({t.add_fe_runs} new runs; "
        f"{t.add_reused_from_diagnose_fe_runs} runs of fits made while diagnosing reused), "
        f"next round {t.next_round_s:.0f} s ({t.next_round_fe_runs} runs); "
        f"{result.fe_seconds_per_run:.2f} s per FE run; {t.fe_runs_continued} runs started from the "
        f"states of a nearby point instead of a load ramp; {t.fe_runs_read_from_cache} runs read from "
        f"the cache of an earlier run (`fe_runs/`).",
        "",
    ]


def finite_or_null(value):
    """``value`` (nested dicts, lists and numbers) with every non-finite float replaced by None:
    report.json is strict JSON, with null where a number is not finite (e.g. the residual of a
    pseudo-time step that diverged)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v) for v in value]
    return value


def diagnosis_dict(d: Diagnosis) -> dict:
    """A diagnosis's regions, hotspot, candidates and competing larger model error, as report.json
    states them (for the baseline and for the next round alike)."""
    return {
        "regions": [dataclasses.asdict(g) for g in d.regions],
        "hotspot": dataclasses.asdict(d.hotspot),
        "candidates": [dict(vars(s)) for s in d.scores],
        "larger_model_error": None if d.larger_model_error is None else dataclasses.asdict(d.larger_model_error),
    }


def report_dict(result: CheckResult) -> dict:
    """Everything the report states, machine-readable.

    One literal naming every field of report.json: longer than a screen on purpose.
    """
    d = result.diagnosis
    return {
        "verdict": d.text,
        "noise": {
            "sd": result.data.noise.sd.tolist(),
            "length_mm": result.data.noise.length,
            "nugget": result.data.noise.nugget,
        },
        "observations": [{"alpha": o.alpha.tolist(), "t": o.t, "source": str(o.path)} for o in result.observations],
        "start": {"from": result.start_from, **dict(zip(result.names[:5], map(float, result.start)))},
        "discretisation": None
        if result.discretisation is None
        else {
            "mesh": result.discretisation.mesh,
            "refined": result.discretisation.refined,
            "relative": result.discretisation.relative,
            "sigma": result.discretisation.sigma,
            "order": result.discretisation.order,
            "ratio": result.discretisation.ratio,
            "basis": result.discretisation.basis,
            "remaining_sigma": result.discretisation.remaining_sigma,
            "resolved": result.discretisation.resolved,
            "suggested_h_edge_mm": result.discretisation.suggested_h_edge(),
            "amplitude": result.discretisation.amplitude,
            "amplitude_sd": result.discretisation.amplitude_sd,
            "carried_correlation_length_mm": result.data.model_error.length,
            "carried_nugget": result.data.model_error.nugget,
        },
        "noise_statement": {
            "consistent": result.noise_statement.consistent,
            "factor": result.noise_statement.factor,
            "used_sd": result.data.noise.sd.tolist(),
        },
        "failed_runs": [{"x": dict(zip(result.names, map(float, f.x))), "message": f.message} for f in result.failures],
        **diagnosis_dict(d),
        "next_round": None
        if result.next_round is None
        else {
            "after": result.versions[-1].calibration.label,
            "verdict": result.next_round.text,
            **diagnosis_dict(result.next_round),
        },
        "versions": [
            {
                "label": v.calibration.label,
                "metrics": dataclasses.asdict(v.metrics),
                "regions": [dataclasses.asdict(g) for g in v.regions],
                "estimates": {n: dataclasses.asdict(e) for n, e in v.calibration.estimates().items()},
                "fe_runs": v.calibration.fe_runs,
                "chi2_path": v.calibration.chi2_path,
            }
            for v in result.versions
        ],
        "confirmation_fits": {
            effect: {"fe_runs": fit.fe_runs, "seconds": fit.seconds, "chi2_path": fit.chi2_path}
            for effect, fit in d.fits.items()
        },
        "timings": dataclasses.asdict(result.timings),
        "fe_seconds_per_run": result.fe_seconds_per_run,
    }


@dataclasses.dataclass(frozen=True)
class ReportDiagnosis:
    """A diagnosis as report.json states it.

    Attributes:
        verdict: the verdict's paragraph.
        regions: the regions ranked by their RMS standardised residual [sigma].
        hotspot: the disc where the residual peaks.
        candidates: the candidate effects' scores, best first.
        larger_model_error: the carried model error at the multiple that fits the residual best,
            which a candidate must beat (None when no model error is carried).
    """

    verdict: str
    regions: list[RegionResidual]
    hotspot: Hotspot
    candidates: list[CandidateScore]
    larger_model_error: LargerModelError | None

    @classmethod
    def from_json(cls, d: dict) -> ReportDiagnosis:
        larger = d["larger_model_error"]
        return cls(
            d["verdict"],
            [RegionResidual(**g) for g in d["regions"]],
            Hotspot(**d["hotspot"]),
            [CandidateScore(**c) for c in d["candidates"]],
            None if larger is None else LargerModelError(**larger),
        )


@dataclasses.dataclass(frozen=True)
class ReportVersion:
    """One model version of report.json.

    Attributes:
        label: "baseline", then "baseline + <effect>" per added effect.
        metrics: its residual metrics (RMSE [log strain], chi^2/dof, PPC p, ...).
        regions: the regions ranked by its RMS standardised residual [sigma].
        estimates: the calibrated parameters (value ± Laplace sd, the parameter's unit) by name
            ("mu", ..., "theta", "<effect>.<parameter>").
    """

    label: str
    metrics: ResidualMetrics
    regions: list[RegionResidual]
    estimates: dict[str, Estimate]

    @classmethod
    def from_json(cls, d: dict) -> ReportVersion:
        return cls(
            d["label"],
            ResidualMetrics(**d["metrics"]),
            [RegionResidual(**g) for g in d["regions"]],
            {name: Estimate(**e) for name, e in d["estimates"].items()},
        )


@dataclasses.dataclass(frozen=True)
class ReportDiscretisation:
    """The check mesh's own error as report.json states it (see :class:`DiscretisationError`).

    Attributes:
        mesh: the check's mesh.
        relative: RMS of its error / RMS of the measured field.
        sigma: RMS of its error [noise sd].
        order: the order of convergence the estimate assumes.
        remaining_sigma: RMS of the corrected model's error, carried next to the noise [noise sd].
        resolved: the corrected model's error is below half the noise.
        suggested_h_edge_mm: the membrane-edge cell size [mm] whose error would be half the noise.
        amplitude, amplitude_sd: the fitted multiple of the two meshes' shift and its Laplace sd.
    """

    mesh: str
    relative: float
    sigma: float
    order: float
    remaining_sigma: float
    resolved: bool
    suggested_h_edge_mm: float
    amplitude: float | None
    amplitude_sd: float | None

    @classmethod
    def from_json(cls, d: dict) -> ReportDiscretisation:
        return cls(**{f.name: d[f.name] for f in dataclasses.fields(cls)})  # its other fields are not read


@dataclasses.dataclass(frozen=True)
class ReportNoiseStatement:
    """Whether the stated noise held (see :class:`NoiseStatement`): ``factor`` is the estimated
    sd over the stated one (1 when consistent), ``used_sd`` the sd the check went on with
    (xx, yy, xy)."""

    consistent: bool
    factor: float
    used_sd: list[float]


@dataclasses.dataclass(frozen=True)
class ReportFailedRun:
    """An FE run that did not converge: its parameter point by name and the solver's message."""

    x: dict[str, float]
    message: str


@dataclasses.dataclass(frozen=True)
class ReportFile:
    """report.json read back (:func:`read_report`): the fields its readers use.

    Attributes:
        diagnosis: of the baseline (the file's top-level verdict, regions, hotspot, candidates).
        next_round: of the last version, what is still missing after the added effects (None
            without ``--add``).
        versions: the baseline, then one version per added effect.
        discretisation: None if not estimated (``--no-discretisation``).
        noise_statement: whether the stated noise held, and the sd the check went on with.
        failed_runs: the FE runs that did not converge.
        timings: wall seconds and FE runs of each phase.
    """

    diagnosis: ReportDiagnosis
    next_round: ReportDiagnosis | None
    versions: list[ReportVersion]
    discretisation: ReportDiscretisation | None
    noise_statement: ReportNoiseStatement
    failed_runs: list[ReportFailedRun]
    timings: CheckTimings


def read_report(path: Path | str) -> ReportFile:
    """The report.json that :func:`write_report` wrote (from :func:`report_dict`).

    Raises:
        ValueError: the file lacks a field this version writes (an older report): rerun the check.
    """
    d = json.loads(Path(path).read_text())
    try:
        return _report_file(d)
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path} is not a report.json of this version of skinid ({exc!r}): rerun the check") from None


def _report_file(d: dict) -> ReportFile:
    return ReportFile(
        diagnosis=ReportDiagnosis.from_json(d),
        next_round=None if d["next_round"] is None else ReportDiagnosis.from_json(d["next_round"]),
        versions=[ReportVersion.from_json(v) for v in d["versions"]],
        discretisation=None if d["discretisation"] is None else ReportDiscretisation.from_json(d["discretisation"]),
        noise_statement=ReportNoiseStatement(**d["noise_statement"]),
        failed_runs=[ReportFailedRun(**f) for f in d["failed_runs"]],
        timings=CheckTimings(**d["timings"]),
    )
