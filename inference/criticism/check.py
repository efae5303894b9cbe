"""``skinid check``: model criticism of measurements against the FE model.

:func:`run_check` calibrates the baseline on the mesh the user chose (started at the
emulator's posterior mode, or at the best of a few spread points), estimates and carries the
mesh's own discretisation error (:mod:`.discretisation`), diagnoses the residual
(:mod:`.diagnosis`), adds the requested effects one after the other, diagnoses what is still
missing after them (the next round) and returns every model version with its metrics;
:func:`inference.criticism.report.write_report` writes the report.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mpi4py import MPI

from inference.criticism.calibration import Calibration, CalibrationError, calibrate
from inference.criticism.data import Data, NoiseModel
from inference.criticism.diagnosis import Diagnosis, NoiseStatement, check_noise_statement, diagnose, extend
from inference.criticism.discretisation import (
    REFINEMENTS,
    CorrectedForward,
    DiscretisationError,
    describe_mesh,
    error_ratio,
    estimate,
    mesh_error_drift,
    refined_config,
)
from inference.criticism.metrics import MembraneRegions, RegionResidual, ResidualMetrics, rank_regions, residual_metrics
from inference.forward import FailedRun, FEForward, ForwardModel, TransferredRun
from inference.observations import Measurement, map_to_cells
from skinfem.config import N_SKIN, Config
from skinfem.dic import StrainGauge
from skinfem.effects import EFFECTS, get_effect
from skinfem.parallel import collective, on_root
from skinfem.solver_work import SolverWork, WorkMeter
from surrogate.emulator import Emulator

log = logging.getLogger(__name__)
# The uncorrected baseline only places the mesh's error estimate (the corrected fit follows):
# it stops once a step lowers chi^2 by less than this share of it.
PRE_CORRECTION_TOLERANCE = 0.01
SPREAD_POINTS = 5  # the calibration start without an emulator: the best of the box centre and 4 others


@dataclass
class CheckSettings:
    """Options of a check.

    Attributes:
        candidates: effects to test (default: every registered effect).
        add: effects to add, in order (each version includes the previous ones).
        increments: load increments of the FE runs (default: the configuration's).
        confirm: how many top candidates are calibrated for real during the diagnosis (besides
            those whose linearised test the skin's re-tuning blinds, and a strong candidate the
            fits leave leading; :func:`~inference.criticism.diagnosis.diagnose`).
        band: half-width [mm] of the membrane edge strip of the regions (default: 2 cells).
        max_iterations: trial steps per calibration.
        gauge: the DIC strain window the measurement was made with.
        spacing: the side [mm] of the squares the measured points were thinned to, one point
            each (stated in the report; the thinning is the caller's, e.g. the command line's).
        discretisation: estimate, correct and carry the mesh's own error (refined mesh run).
        refinement: the better mesh of that estimate, ``"uniform"``, ``"edge"``, ``"quadratic"``
            or ``"converged"`` (see :func:`inference.criticism.discretisation.refined_config`).
        mesh_drift: the correction follows the parameters to first order (exact sensitivities
            on both meshes at the baseline, :func:`~inference.criticism.discretisation.mesh_error_drift`).
        start: (5,) skin parameters to start the calibration from (None: the emulator's
            posterior mode if an emulator is given, else the best of a few spread points).
    """

    candidates: list[str] = field(default_factory=lambda: list(EFFECTS))
    add: list[str] = field(default_factory=list)
    increments: int | None = None
    confirm: int = 2
    band: float | None = None
    max_iterations: int = 12
    gauge: StrainGauge = field(default_factory=StrainGauge)
    spacing: float = 1.0
    discretisation: bool = True
    refinement: str = "uniform"
    mesh_drift: bool = False
    start: np.ndarray | None = None

    def __post_init__(self):
        for name in [*self.candidates, *self.add]:
            get_effect(name)
        if len(set(self.add)) != len(self.add):
            raise ValueError("--add lists an effect twice")
        if self.refinement not in REFINEMENTS:
            raise ValueError(f"unknown refinement {self.refinement!r}; choose one of {', '.join(REFINEMENTS)}")
        if self.mesh_drift and not self.discretisation:
            raise ValueError("--mesh-drift needs the discretisation estimate: drop --no-discretisation")
        if not self.spacing > 0:
            raise ValueError(f"the point spacing must be > 0 mm, got {self.spacing}")

    def membrane(self, config: Config) -> MembraneRegions:
        """The regions around ``config``'s membrane: its half size and the half-width ``band`` of
        its edge strip [mm] (None: 2 membrane cells)."""
        return MembraneRegions(config.mesh.membrane_size / 2, self.band or 2 * config.mesh.h_membrane)


@dataclass
class Version:
    """One model version: its calibration, residual metrics and region ranking."""

    calibration: Calibration
    metrics: ResidualMetrics
    regions: list[RegionResidual]


@dataclass
class PhaseWork:
    """Newton steps, LU factorisations and triangular solves of each phase of a check (all ranks)."""

    setup: SolverWork = SolverWork()
    compare: SolverWork = SolverWork()  # includes the mesh-error estimate's
    refined: SolverWork = SolverWork()  # the mesh-error estimate: the refined run and its starting states
    diagnose: SolverWork = SolverWork()
    add: SolverWork = SolverWork()
    next_round: SolverWork = SolverWork()


@dataclass
class CheckTimings:
    """Wall seconds, FE simulations and linear-algebra work of each phase of a check."""

    setup_s: float = 0.0  # the FE model's set-up and the starting point
    setup_fe_runs: int = 0  # the spread start's runs (none from the emulator or a given start)
    compare_s: float = 0.0  # baseline calibration(s), discretisation estimate, noise statement
    compare_fe_runs: int = 0
    refined_s: float = 0.0  # the refined mesh's simulations (part of compare)
    refined_fe_runs: int = 0
    diagnose_s: float = 0.0
    diagnose_fe_runs: int = 0
    add_s: float = 0.0
    add_fe_runs: int = 0
    next_round_s: float = 0.0  # the diagnosis of the last version (with --add)
    next_round_fe_runs: int = 0
    add_reused_from_diagnose_s: float = 0.0  # fits made while diagnosing, reused as versions
    add_reused_from_diagnose_fe_runs: int = 0
    fe_runs_read_from_cache: int = 0
    fe_runs_continued: int = 0  # started from a nearby point's states instead of a load ramp
    refined_fe_runs_continued: int = 0  # started from the check mesh's interpolated fields
    refined_runs: list[TransferredRun] = field(default_factory=list)  # every rank's, rank by rank
    work: PhaseWork | None = None  # None in reports written before it was counted

    @classmethod
    def from_json(cls, d: dict) -> CheckTimings:
        """From :func:`dataclasses.asdict` of one, as report.json holds it."""
        work = d.get("work")
        if work is not None:
            work = PhaseWork(**{phase: SolverWork(**counts) for phase, counts in work.items()})
        refined_runs = [TransferredRun.from_json(r) for r in d["refined_runs"]]
        return cls(**{**d, "work": work, "refined_runs": refined_runs})


@dataclass
class CheckResult:
    """Everything a check found, as :func:`run_check` returns it and the report writes it.

    Attributes:
        data: the measurements at their points (n_obs, n_pts), with the noise and carried
            model-error terms the check used.
        observations: the measurements as read (thinned to the check's spacing).
        names, bounds: the parameter vector's names and prior box (p, 2) [units of each].
        membrane: the membrane's half size and the half-width of its edge strip [mm], the
            regions the residual is ranked over.
        versions: the baseline, then each added effect's version.
        start: (p,) the calibration's start; ``start_from`` says where it came from.
        gauge_text: how model strains became measurements (the DIC operator), for the report.
        fe_seconds_per_run: wall seconds per FE simulation on one rank.
    """

    data: Data
    observations: list[Measurement]
    names: list[str]
    bounds: np.ndarray
    membrane: MembraneRegions
    versions: list[Version]
    diagnosis: Diagnosis  # of the baseline
    next_round: Diagnosis | None  # of the last version, when effects were added: what is still missing
    discretisation: DiscretisationError | None
    noise_statement: NoiseStatement
    failures: list[FailedRun]
    start: np.ndarray
    start_from: str
    gauge_text: str
    fe_seconds_per_run: float
    timings: CheckTimings


def emulator_start(emulator: Emulator, measurements: list[Measurement], seed: int = 0) -> np.ndarray:
    """(5,) posterior mode of the skin parameters under the emulator (known noise).

    The emulator works on its own mesh's cells: the measurements are mapped onto them."""
    import torch

    from inference.model import ObservedWeights, SkinPosterior
    from inference.sampling import find_mode

    observations = [map_to_cells(m, emulator.xy) for m in measurements]
    posterior = SkinPosterior(
        emulator, ObservedWeights.project(emulator, observations), noise="known", gp_variance="exact"
    )
    with torch.no_grad():
        return posterior.constrain(torch.as_tensor(find_mode(posterior, seed=seed)))[:N_SKIN].numpy()


def starting_point(
    forward: FEForward, data: Data, settings: CheckSettings, emulator: Emulator | None, measurements: list[Measurement]
) -> tuple[np.ndarray, str]:
    """(p,) calibration start (effects at their null values) and where it comes from: the given
    skin parameters, else the emulator's posterior mode, else the best of a few spread points."""
    start = forward.null.copy()
    if settings.start is not None:
        start[:N_SKIN] = settings.start
        return start, "given start"
    if emulator is not None:
        start[:N_SKIN] = on_root(forward.comm, lambda: emulator_start(emulator, measurements))
        return start, "emulator's posterior mode"
    return spread_start(forward, data), f"best of {SPREAD_POINTS} spread points"


def spread_start(forward: ForwardModel, data: Data, n: int = SPREAD_POINTS, seed: int = 0) -> np.ndarray:
    """(p,) the best of the box centre and n - 1 Latin-hypercube points of the skin box
    (effects at their null values), by whitened chi^2; points whose FE run fails are skipped."""
    from scipy.stats import qmc

    log.info("choosing the start: the best of %d spread points", n)
    skin = forward.bounds[:N_SKIN]
    unit = np.vstack([np.full(N_SKIN, 0.5), qmc.LatinHypercube(d=N_SKIN, seed=seed).random(n - 1)])
    points = [np.concatenate([skin[:, 0] + u * np.ptp(skin, axis=1), forward.null[N_SKIN:]]) for u in unit]
    chi2 = [
        np.inf if f is None else float(np.nansum(data.whitened_residual(f) ** 2)) for f in forward.evaluate_many(points)
    ]
    if not np.isfinite(min(chi2)):
        raise CalibrationError("the FE model converged at none of the starting points")
    return points[int(np.argmin(chi2))]


def run_check(
    measurements: list[Measurement],
    noise: NoiseModel,
    settings: CheckSettings,
    config: Config,
    skin_bounds: np.ndarray,
    emulator: Emulator | None = None,
    mesh_dir: Path | str = "meshes",
    comm: MPI.Comm = MPI.COMM_WORLD,
    cache_dir: Path | str | None = None,
) -> CheckResult:
    """Calibrate the baseline on ``config``'s mesh, estimate its discretisation error, diagnose
    the residual, add ``settings.add`` effects (see :mod:`inference.criticism`).

    The emulator, when given, only provides the starting point (its posterior mode); without
    it the start is the best of a few spread points. ``cache_dir`` keeps every finished FE
    simulation on disk; a rerun of the same check (e.g. after a kill) reads them.
    (Longer than a screen on purpose: the check's phases in order, each timed where it runs,
    then the result's fields by name.)
    """
    if settings.discretisation:  # a refinement that does not apply: before any FE run, said once
        collective(comm, lambda: error_ratio(config, settings.refinement), (ValueError,))
    timings, meter = CheckTimings(work=PhaseWork()), WorkMeter(comm)
    work = timings.work
    t0 = time.perf_counter()
    forward = FEForward(
        config, measurements, skin_bounds, mesh_dir, settings.increments, comm, cache_dir, settings.gauge
    )
    data = Data.from_points(measurements, noise)
    start, start_from = starting_point(forward, data, settings, emulator, measurements)
    timings.setup_s, timings.setup_fe_runs, work.setup = time.perf_counter() - t0, forward.runs, meter.lap()
    log.info("calibrating the baseline on %s (start: %s)", describe_mesh(config), start_from)
    membrane = settings.membrane(config)

    t0, runs0 = time.perf_counter(), forward.runs
    refined = refined_forward(forward, measurements, skin_bounds, (mesh_dir, comm, cache_dir), settings)
    model, data, baseline, disc = compare(forward, refined, data, start, settings, timings, work)
    baseline, data, noise_statement = check_noise_statement(
        model, baseline, data, membrane, settings.max_iterations // 2
    )
    timings.compare_s, timings.compare_fe_runs = time.perf_counter() - t0, forward.runs - runs0
    work.compare = meter.lap()
    if disc is not None and not noise_statement.consistent:  # the baseline was refitted with the estimated noise
        disc.amplitude, disc.amplitude_sd = float(baseline.x[-1]), float(baseline.sd[-1])
    if disc is not None:
        disc.noise_factor = noise_statement.factor
    carried = 0.0 if disc is None else disc.carried_sigma
    shift = None if disc is None else disc.shift
    log.info("diagnosing the residual: %d candidate effects", len(settings.candidates))
    diagnosis = _diagnose(model, baseline, data, settings, membrane, (carried, shift))  # also its metrics
    timings.diagnose_s, timings.diagnose_fe_runs = diagnosis.seconds, diagnosis.fe_runs
    work.diagnose = meter.lap()

    t0, runs0 = time.perf_counter(), forward.runs
    versions = add_versions(model, data, baseline, diagnosis, settings, membrane, timings)
    timings.add_s, timings.add_fe_runs = time.perf_counter() - t0, forward.runs - runs0
    work.add = meter.lap()
    next_round = _next_round(model, versions[-1].calibration, data, settings, membrane, (carried, shift), timings)
    work.next_round = meter.lap()
    timings.fe_runs_read_from_cache, timings.fe_runs_continued = forward.reused, forward.continued
    diagnosis.text = _verdict(disc, noise_statement.summary(noise.sd), diagnosis, settings.add, next_round)
    return CheckResult(
        data=data,
        observations=measurements,
        names=forward.names,
        bounds=forward.bounds,
        membrane=membrane,
        versions=versions,
        diagnosis=diagnosis,
        next_round=next_round,
        discretisation=disc,
        noise_statement=noise_statement,
        failures=forward.failures,
        start=start,
        start_from=start_from,
        gauge_text=(
            f"surface strain of a {settings.gauge.window:g} mm strain window at {data.n // 3} points "
            f"(one per {settings.spacing:g} mm square)"
        ),
        fe_seconds_per_run=forward.seconds / max(forward.runs, 1) * comm.size,
        timings=timings,
    )


def refined_forward(
    forward: FEForward,
    measurements: list[Measurement],
    skin_bounds: np.ndarray,
    where: tuple,
    settings: CheckSettings,
) -> Callable[[], FEForward]:
    """The forward model on the refined mesh of the discretisation estimate, built only when the
    estimate asks for it. ``where``: (mesh_dir, comm, cache_dir) as for the check's own model."""
    mesh_dir, comm, cache_dir = where
    return lambda: FEForward(
        refined_config(forward.config, settings.refinement),
        measurements,
        skin_bounds,
        mesh_dir,
        None,
        comm,
        cache_dir,
        settings.gauge,
    )


def _next_round(
    model: ForwardModel,
    last: Calibration,
    data: Data,
    settings: CheckSettings,
    membrane: MembraneRegions,
    mesh_error: tuple[float, np.ndarray | None],
    timings: CheckTimings,
) -> Diagnosis | None:
    """With ``settings.add``: the diagnosis repeated on the last version, over the candidates not
    added (what is still missing); None otherwise. ``membrane``: the regions the residual is
    ranked over; ``mesh_error``: RMS of the carried mesh error [sd of the noise used] and the
    two-mesh shift it was estimated from (None without one)."""
    if not settings.add:
        return None
    log.info("diagnosing what is still missing with %s added", " and ".join(settings.add))
    next_round = _diagnose(model, last, data, settings, membrane, mesh_error, settings.add)
    timings.next_round_s, timings.next_round_fe_runs = next_round.seconds, next_round.fe_runs
    return next_round


def _diagnose(
    model: ForwardModel,
    cal: Calibration,
    data: Data,
    settings: CheckSettings,
    membrane: MembraneRegions,
    mesh_error: tuple[float, np.ndarray | None],
    added: Sequence[str] = (),
) -> Diagnosis:
    """:func:`diagnose` of ``cal`` over the candidates not ``added``, as ``settings`` set it up;
    ``membrane`` and ``mesh_error`` as for :func:`_next_round`."""
    return diagnose(
        model,
        cal,
        data,
        [c for c in settings.candidates if c not in added],
        membrane,
        settings.confirm,
        carried_sigma=mesh_error[0],
        added=added,
        mesh_shift=mesh_error[1],
        max_iterations=settings.max_iterations,
    )


def _verdict(
    disc: DiscretisationError | None,
    noise_text: str,
    diagnosis: Diagnosis,
    added: list[str],
    next_round: Diagnosis | None,
) -> str:
    """The check's paragraph: the mesh's own error, the noise statement, the diagnosis, the next round."""
    again = f"With {' and '.join(added)} added, the diagnosis repeated: {next_round.text}" if next_round else ""
    return " ".join(part for part in (disc.summary() if disc else "", noise_text, diagnosis.text, again) if part)


def compare(
    forward: FEForward,
    refined: Callable[[], FEForward],
    data: Data,
    start: np.ndarray,
    settings: CheckSettings,
    timings: CheckTimings,
    work: PhaseWork,
) -> tuple[ForwardModel, Data, Calibration, DiscretisationError | None]:
    """The baseline calibration; with ``settings.discretisation`` the mesh's own error is
    estimated at it (``refined()``: the model on the refined mesh; one run per design), the
    model corrected by a fitted multiple of it (:class:`CorrectedForward`), the data given the
    carried model error, and the baseline recalibrated with that multiple. The refined mesh's
    time, runs and work go to ``timings`` and ``work``.
    Returns (model, data, baseline, error)."""
    near = PRE_CORRECTION_TOLERANCE if settings.discretisation else 0.0
    baseline = calibrate(
        forward, data, start, list(range(N_SKIN)), max_iterations=settings.max_iterations, relative_tolerance=near
    )
    if not settings.discretisation:
        return forward, data, baseline, None
    refined_started = time.perf_counter()  # the refined phase: the better mesh's runs (and the drift's check-mesh run)
    fine = refined()
    log.info("estimating the mesh's own error: %s at the calibrated parameters", describe_mesh(fine.config))
    meter = WorkMeter(forward.comm)
    fine.continue_from(forward, baseline.x)  # Newton from the check mesh's fields, not a load ramp
    drift = mesh_error_drift(forward, fine, baseline.x, data.masks) if settings.mesh_drift else None
    disc = estimate(forward, fine, baseline.x, data, settings.refinement)
    fine.release_factorisation()  # its runs are done: its factors need not wait for the collector
    disc.drifts = drift is not None
    work.refined, refined_s = meter.lap(), time.perf_counter() - refined_started
    model = CorrectedForward(forward, disc.shift, drift, None if drift is None else baseline.x)
    data = data.with_model_error(disc.model_error(data.xy, data.masks))
    x0, free = np.append(baseline.x, model.null[-1]), [*range(N_SKIN), len(model.names) - 1]
    # the amplitude starts at 1, away from its optimum: the full number of trial steps
    log.info("calibrating the baseline again, corrected by a fitted multiple of the mesh's error")
    baseline = calibrate(model, data, x0, free, max_iterations=settings.max_iterations)
    disc.amplitude, disc.amplitude_sd = float(baseline.x[-1]), float(baseline.sd[-1])
    timings.refined_fe_runs, timings.refined_s = fine.runs, refined_s
    timings.refined_fe_runs_continued = fine.continued
    timings.refined_runs = [r for part in fine.comm.allgather(fine.transferred_runs) for r in part]
    return model, data, baseline, disc


def add_versions(
    model: ForwardModel,
    data: Data,
    baseline: Calibration,
    diagnosis: Diagnosis,
    settings: CheckSettings,
    membrane: MembraneRegions,
    timings: CheckTimings,
) -> list[Version]:
    """The baseline, then ``settings.add`` effects one after the other, each version including
    the previous ones (a fit made while diagnosing is reused as the first added version), each
    ranked over ``membrane``'s regions."""
    versions = [Version(baseline, diagnosis.metrics, diagnosis.regions)]
    for effect in settings.add:
        previous = versions[-1].calibration
        if len(versions) == 1 and effect in diagnosis.fits:  # already calibrated while diagnosing
            cal = diagnosis.fits[effect]
            timings.add_reused_from_diagnose_s += cal.seconds
            timings.add_reused_from_diagnose_fe_runs += cal.fe_runs
        else:
            log.info("adding %s", effect)
            cal = extend(model, previous, data, effect, max_iterations=settings.max_iterations)
        versions.append(Version(cal, residual_metrics(cal, data), rank_regions(cal, data, membrane)))
    return versions
