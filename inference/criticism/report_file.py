"""report.json: everything the model-criticism report states, machine-readable
(:func:`report_dict`), and read back into typed records (:func:`read_report`)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from inference.criticism.calibration import Estimate
from inference.criticism.check import CheckResult, CheckTimings
from inference.criticism.diagnosis import CandidateScore, Diagnosis, LargerModelError
from inference.criticism.metrics import Hotspot, RegionResidual, ResidualMetrics
from skinfem.config import N_SKIN


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
        "start": {"from": result.start_from, **dict(zip(result.names[:N_SKIN], map(float, result.start)))},
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
            "noise_factor": result.discretisation.noise_factor,
            "resolved": result.discretisation.resolved,
            "suggested_h_edge_mm": result.discretisation.suggested_h_edge(),
            "amplitude": result.discretisation.amplitude,
            "amplitude_sd": result.discretisation.amplitude_sd,
            "correction_follows_the_parameters": result.discretisation.drifts,
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
        sigma: RMS of its error [stated noise sd].
        order: the order of convergence the estimate assumes.
        remaining_sigma: RMS of the corrected model's error, carried next to the noise [stated noise sd].
        resolved: the corrected model's error is below half the noise used (the stated sd times
            the noise statement's factor).
        suggested_h_edge_mm: the membrane-edge cell size [mm] whose error would be half the noise used.
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
        timings: wall seconds, FE runs and linear-algebra work of each phase.
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
        timings=CheckTimings.from_json(d["timings"]),
    )
