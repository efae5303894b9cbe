"""``skinid check``: model criticism of measurements against the FE model (see criticism.py).

:func:`run_check` calibrates the baseline (started at the emulator's posterior mode),
diagnoses its residual, adds the requested effects one after the other and returns every
model version with its metrics; :func:`inference.check_report.write_report` writes the report.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from mpi4py import MPI

from inference.criticism import (
    Calibration,
    Data,
    Diagnosis,
    NoiseModel,
    calibrate,
    diagnose,
    extend,
    rank_regions,
    residual_metrics,
)
from inference.forward import FEForward
from inference.observations import Observation
from skinfem.config import config_from_toml
from skinfem.effects import EFFECTS, get_effect
from surrogate.emulator import COMPONENTS, Emulator


@dataclass
class CheckSettings:
    """Options of a check.

    Attributes:
        candidates: effects to test (default: every registered effect).
        add: effects to add, in order (each version includes the previous ones).
        increments: load increments of the FE runs (default: the configuration's).
        confirm: how many top candidates are calibrated for real during the diagnosis.
        band: half-width [mm] of the membrane edge strip of the regions (default: 2 cells).
        max_iterations: residual evaluations per calibration.
    """

    candidates: list[str] = field(default_factory=lambda: list(EFFECTS))
    add: list[str] = field(default_factory=list)
    increments: int | None = None
    confirm: int = 2
    band: float | None = None
    max_iterations: int = 12

    def __post_init__(self):
        for name in [*self.candidates, *self.add]:
            get_effect(name)
        if len(set(self.add)) != len(self.add):
            raise ValueError("--add lists an effect twice")


@dataclass
class Version:
    """One model version: its calibration, residual metrics and region ranking."""

    calibration: Calibration
    metrics: dict
    regions: list[dict]


@dataclass
class CheckResult:
    data: Data
    observations: list[Observation]
    names: list[str]
    bounds: np.ndarray
    half: float
    band: float
    versions: list[Version]
    diagnosis: Diagnosis
    subspace: dict
    emulator_rmse: float
    start: np.ndarray
    fe_seconds_per_run: float
    timings: dict


def emulator_start(emulator: Emulator, observations: list[Observation], seed: int = 0) -> np.ndarray:
    """(5,) posterior mode of the skin parameters under the emulator (known noise)."""
    from inference.model import ObservedWeights, SkinPosterior
    from inference.sampling import find_mode

    posterior = SkinPosterior(emulator, ObservedWeights.project(emulator, observations), noise="known",
                              gp_variance="exact")
    with torch.no_grad():
        return posterior.constrain(torch.as_tensor(find_mode(posterior, seed=seed)))[:5].numpy()


def subspace_share(emulator: Emulator, data: Data) -> dict:
    """Share of the measured (standardised, centred) field outside the emulator's PC subspace.

    Also the share that noise alone would put there, so a reader can tell a field the
    emulator cannot represent from a noisy one.
    """
    out = {}
    for c, pca in emulator.pcas.items():
        k = COMPONENTS.index(c)
        outside = total = noise = 0.0
        for o, mask in enumerate(data.masks):
            weights, _ = pca.transform_masked(data.fields[o, :, k], mask)
            z = (data.fields[o, mask, k] - pca.mean_[mask]) / pca.scale_[mask]
            recon = weights @ pca.components_[:, mask]
            outside += float(np.sum((z - recon) ** 2))
            total += float(np.sum(z**2))
            noise += (mask.sum() - pca.n_components_) * float(np.mean((data.noise.sd[k] / pca.scale_[mask]) ** 2))
        out[c] = {"outside": outside / total, "noise_expected": min(noise / total, 1.0)}
    return out


def run_check(emulator: Emulator, observations: list[Observation], noise: NoiseModel, settings: CheckSettings,
              mesh_dir: Path | str = "meshes", comm: MPI.Comm = MPI.COMM_WORLD,
              cache_dir: Path | str | None = None) -> CheckResult:
    """Calibrate the baseline, diagnose it, add ``settings.add`` effects; see module doc.

    ``cache_dir`` keeps every finished FE simulation on disk; a rerun of the same check
    (e.g. after a kill) reads them instead of simulating again."""
    timings = {}
    t0 = time.perf_counter()
    config = config_from_toml(emulator.meta["dataset_config"])
    forward = FEForward(config, observations, emulator.param_bounds, mesh_dir, settings.increments, comm, cache_dir)
    if forward.xy.shape != emulator.xy.shape or not np.allclose(forward.xy, emulator.xy, atol=1e-6):
        raise ValueError("the FE model's skin cells differ from the emulator's (mesh changed since the fit?)")
    data = Data.from_observations(observations, emulator.xy, noise)
    start = comm.bcast(emulator_start(emulator, observations) if comm.rank == 0 else None)
    x0 = forward.null.copy()
    x0[:5] = start
    timings["setup_s"] = time.perf_counter() - t0
    half = config.mesh.membrane_size / 2
    band = settings.band or 2 * config.mesh.h_membrane

    t0, runs0 = time.perf_counter(), forward.runs
    baseline = calibrate(forward, data, x0, list(range(5)), max_iterations=settings.max_iterations)
    timings["compare_s"], timings["compare_fe_runs"] = time.perf_counter() - t0, forward.runs - runs0
    diagnosis = diagnose(forward, baseline, data, settings.candidates, half, band, settings.confirm,
                         max_iterations=settings.max_iterations)  # also the baseline's metrics
    timings["diagnose_s"], timings["diagnose_fe_runs"] = diagnosis.seconds, diagnosis.fe_runs

    t0, runs0 = time.perf_counter(), forward.runs
    versions = [Version(baseline, diagnosis.metrics, diagnosis.regions)]
    reused_s = reused_runs = 0
    for effect in settings.add:
        previous = versions[-1].calibration
        if len(versions) == 1 and effect in diagnosis.fits:  # already calibrated while diagnosing
            cal = diagnosis.fits[effect]
            reused_s, reused_runs = reused_s + cal.seconds, reused_runs + cal.fe_runs
        else:
            cal = extend(forward, previous, data, effect, max_iterations=settings.max_iterations)
        versions.append(Version(cal, residual_metrics(cal, data), rank_regions(cal, data, half, band)))
    timings["add_s"], timings["add_fe_runs"] = time.perf_counter() - t0, forward.runs - runs0
    timings["add_reused_from_diagnose_s"], timings["add_reused_from_diagnose_fe_runs"] = reused_s, reused_runs
    timings["fe_runs_read_from_cache"] = forward.reused

    predicted = np.stack([emulator.predict_fields(baseline.x[None, :5], o.alpha, o.t)[0] for o in observations])
    modelled = [COMPONENTS.index(c) for c in emulator.components]
    err = (predicted - baseline.model_fields[..., modelled])[data.masks]
    return CheckResult(
        data=data, observations=observations, names=forward.names, bounds=forward.bounds, half=half, band=band,
        versions=versions, diagnosis=diagnosis, subspace=subspace_share(emulator, data),
        emulator_rmse=float(np.sqrt(np.mean(err**2))), start=start,
        fe_seconds_per_run=forward.seconds / max(forward.runs, 1) * comm.size, timings=timings,
    )
