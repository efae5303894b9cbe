"""The model-criticism report: report.md, with its figures (:mod:`.report_figures`) and report.json
(:mod:`.report_file`) beside it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from inference.criticism.calibration import Calibration
from inference.criticism.check import CheckResult, PhaseWork
from inference.criticism.diagnosis import MESH_LIKE, STRONG_EVIDENCE, CandidateScore
from inference.criticism.metrics import RegionResidual
from inference.criticism.report_figures import candidates_plot, error_falls_plot, regions_map, residual_maps
from inference.criticism.report_file import finite_or_null, report_dict
from skinfem.config import N_SKIN
from skinfem.effects import EFFECTS, get_effect
from skinfem.outputs import write_text


def discretisation_lines(result: CheckResult) -> list[str]:
    """Section 1's part on the check mesh's own error: the summary and its table."""
    disc = result.discretisation
    if disc is None:
        return ["Discretisation error: not estimated (--no-discretisation).", ""]
    return [
        "### The check's own discretisation error",
        "",
        disc.summary(),
        "",
        "| | RMS, share of the field | RMS [stated noise sd] |",
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
    """The FE runs that did not converge, each a rejected step."""
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
        *region_table(result.diagnosis.regions),
    ]
    spot = result.diagnosis.hotspot
    return lines + ["", f"The residual peaks {spot.summary()}.", "", "![regions](regions.png)"]


def candidate_lines(result: CheckResult) -> list[str]:
    """Section 3: the candidate effects' scores."""
    lines = [
        "",
        "## 3. Which effect is missing",
        "",
        "Each candidate's field signature at the calibrated parameters, with what re-tuning the skin "
        f"parameters absorbs projected out; ΔBIC > {STRONG_EVIDENCE:g} is strong evidence; '(fit)' rows were "
        "calibrated with the effect added; 'mesh error reproduced': the share of the check mesh's own error (its "
        f"two-mesh shift) the signature reproduces (from {MESH_LIKE:.0%} on, such a candidate is not named while "
        "that error exceeds half the noise).",
        "",
    ]
    return (
        lines
        + candidate_table(result.diagnosis.scores)
        + uncalibrated_note(result)
        + ["", "![candidates](candidates.png)"]
    )


def uncalibrated_note(result: CheckResult) -> list[str]:
    """Why a strong linearised score names nothing when the residual is consistent and a mesh error
    is carried: the carried error is a Gaussian summary of a deterministic field, and along some
    candidate's signature its remainder alone scores high (docs/criticism.md §16, §25)."""
    d = result.diagnosis
    if (
        d.metrics.structured
        or result.discretisation is None
        or not any(s.delta_bic > STRONG_EVIDENCE for s in d.scores)
    ):
        return []
    return [
        "",
        "The residual is consistent with the noise and the carried discretisation error, so no candidate is "
        f"named: a ΔBIC above {STRONG_EVIDENCE:g} here does not say that an effect is missing. The mesh's "
        "remaining error is carried as a correlated Gaussian field that spreads it over many directions; the real "
        "remainder lies along a few smooth ones, and a candidate's linearised test along them scores high with "
        "no effect hidden (measured on independent data: docs/criticism.md §25).",
    ]


def region_table(regions: list[RegionResidual]) -> list[str]:
    """The regions ranked by their RMS standardised residual, as a Markdown table."""
    rows = [f"| {i + 1} | {g.region} | {g.points} | {g.rms_sigma:.2f} |" for i, g in enumerate(regions)]
    return ["| rank | region | points | RMS [σ] |", "|---|---|---|---|", *rows]


def candidate_table(scores: list[CandidateScore]) -> list[str]:
    """The candidates' scores, best first; "mesh error reproduced": the share of the check mesh's
    own error the candidate's signature reproduces (diagnosis.mesh_shares)."""
    lines = [
        "| effect | ΔBIC | share of excess residual | confounding | mesh error reproduced | score T (dof) | p "
        "| estimate | explains |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        est = ", ".join(f"{k.split('.')[-1]} = {v:.3g}" for k, v in s.estimate.items())
        explains = "**yes**" if s.explains else "like the mesh's error" if s.mesh_like else "no"
        lines.append(
            f"| {s.effect} | {s.delta_bic:+.1f} ({'fit' if s.fitted else 'linearised'}) | "
            f"{s.share_explained:.0%} | {s.confounding:.0%} | "
            f"{'—' if s.mesh_share is None else f'{s.mesh_share:.1%}'} | {s.statistic:.1f} ({s.dof}) | "
            f"{s.p_value:.2g} | {est} | {explains} |"
        )
    return lines


def next_round_lines(result: CheckResult) -> list[str]:
    """Section 6: what is still missing after the added effects (only with --add)."""
    d = result.next_round
    if d is None:
        return []
    return [
        "",
        f"## 6. Next round: what is still missing with {result.versions[-1].calibration.label}",
        "",
        d.text,
        "",
        *region_table(d.regions),
        "",
    ] + (candidate_table(d.scores) if d.scores else ["No candidate is left to test."])


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
    lines += ["", "![error falls](error_falls.png)", "", *estimate_lines(result)]
    final = result.versions[-1].calibration
    added = [name for name in dict.fromkeys(n.split(".")[0] for n in final.free_names[N_SKIN:]) if name in EFFECTS]
    for name in added:
        values = {q.split(".", 1)[1]: float(final.x[final.names.index(q)]) for q in get_effect(name).qualified_names()}
        lines += ["", f"{name} in the final version: {get_effect(name).describe(values)}"]
    if final_maps:
        lines += ["", f"Final version ({final.label}), residual maps:", ""]
        lines += [f"![final residual, observation {i}]({p.name})" for i, p in enumerate(final_maps)]
    return lines


def estimate_lines(result: CheckResult) -> list[str]:
    """The versions' parameter estimates (± Laplace sd), then those the data do not determine."""
    lines = [
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
    loose = [
        f"{', '.join(names)} ({v.calibration.label})"
        for v in result.versions
        if (names := undetermined(v.calibration, result.names, result.bounds))
    ]
    if loose:
        lines += [
            "",
            "Not determined by these data (Laplace sd above the prior's, the box width / sqrt(12): the fit "
            "is flat along them, and the value shown is one point of a valley of equal fit): "
            + "; ".join(loose) + ".",
        ]  # fmt: skip
    return lines


def undetermined(cal: Calibration, names: list[str], bounds: np.ndarray) -> list[str]:
    """Free parameters of ``cal`` whose Laplace sd is not finite or exceeds that of a uniform prior
    on ``bounds`` (p, 2; rows as ``names``, the forward model's), width / sqrt(12). Parameters
    outside ``names`` (the discretisation amplitude) are not judged."""
    prior_sd = dict(zip(names, np.ptp(bounds, axis=1) / np.sqrt(12)))
    return [n for n, e in cal.estimates().items() if n in prior_sd and not e.sd <= prior_sd[n]]


def cost_lines(result: CheckResult) -> list[str]:
    """The wall time, FE runs and linear-algebra work of each phase."""
    t = result.timings
    return [
        "",
        "## Cost",
        "",
        f"setup {t.setup_s:.0f} s ({t.setup_fe_runs} FE runs for the starting point), "
        f"compare {t.compare_s:.0f} s ({t.compare_fe_runs} FE runs; with the refined mesh's "
        f"{t.refined_fe_runs} runs in {t.refined_s:.0f} s), diagnose {t.diagnose_s:.0f} s "
        f"({t.diagnose_fe_runs} runs), add {t.add_s:.0f} s ({t.add_fe_runs} new runs; "
        f"{t.add_reused_from_diagnose_fe_runs} runs of fits made while diagnosing reused), "
        f"next round {t.next_round_s:.0f} s ({t.next_round_fe_runs} runs); "
        f"{result.fe_seconds_per_run:.2f} s per FE run; {t.fe_runs_continued} runs started from the "
        f"states of a nearby point instead of a load ramp; {t.fe_runs_read_from_cache} runs read from "
        f"the cache of an earlier run (`fe_runs/`).",
        *work_lines(t.work),
        "",
    ]


def work_lines(work: PhaseWork | None) -> list[str]:
    """A table of each phase's Newton steps, factorisations and triangular solves (all ranks)."""
    if work is None:
        return []
    rows = [
        f"| {label} | {w.newton_steps} | {w.factorisations} | {w.triangular_solves} |"
        for label, w in (
            ("setup", work.setup),
            ("compare", work.compare),
            ("… of which the mesh-error estimate", work.refined),
            ("diagnose", work.diagnose),
            ("add", work.add),
            ("next round", work.next_round),
        )
    ]
    header = ["", "| phase | Newton steps | LU factorisations | triangular solves |", "|---|---|---|---|"]
    return [*header, *rows]
