"""Coverage of the posterior intervals, measured on held-out materials (simulation-based calibration).

A study runs one observation setup over many cases. A case is one test material observed
through the setup, started from one of the dataset's designs, with one noise seed:

- ``single``: the last frame of that design;
- ``frames``: its last ``n`` frames;
- ``membranes``: the last frame of that design and the ``n - 1`` designs farthest from it in
  alpha (:func:`inference.studies.spread_designs`).

With ``noise_sd`` > 0 independent Gaussian noise of that sd [strain] is added to every cell and
stated (``noise="known"``); without it the posterior's noise is unknown (HalfCauchy), so its
width comes from the emulator's error model alone. Per case and parameter the study records the
truth's rank among ``RANK_DRAWS`` thinned draws (uniform on 0..RANK_DRAWS when the posterior is
calibrated) and whether the central 50 % and 95 % intervals hold it. Calibrated: 95 % intervals
cover 90-99 % and 50 % intervals 40-60 %. The cases of one material share its truth, so they
are not independent draws: the sd of a coverage is cluster-robust over materials
(:func:`clustered_sd`; sqrt(p (1 - p) / n) with one case per material), and a study over a few
materials measures mostly where those materials lie in the prior box.

Resumable: each finished case is a JSON file in ``<out>/cases/``.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from inference.model import ObservedWeights, draw_from_model
from inference.observations import Observation, from_dataset
from inference.plots import LABELS, pyplot, save_figure
from inference.studies import SamplerSettings, emulator_error_of, sample_skin_posterior, skin_posterior, spread_designs
from skinfem.io import StrainDataset
from skinfem.outputs import write_text
from surrogate.emulator import Emulator

SETUPS = ("single", "frames", "membranes")
DATA_SOURCES = ("fe", "model")
RANK_DRAWS = 99
GOAL_95, GOAL_50 = (0.90, 0.99), (0.40, 0.60)


@dataclass(frozen=True)
class CoverageCase:
    """One posterior of a study: material, designs and frames observed, noise seed."""

    material: int
    designs: tuple[int, ...]
    frames: tuple[int, ...]
    seed: int

    @property
    def name(self) -> str:
        return f"m{self.material:03d}_d{'-'.join(map(str, self.designs))}_s{self.seed}"


@dataclass(frozen=True)
class CaseResult:
    """Per parameter (mu, k1, k2, kappa, theta): the truth's rank among RANK_DRAWS draws and
    whether the central 50 % / 95 % intervals hold it; the truth and those thinned draws (theta
    in degrees) are kept, so that where a posterior misses can be studied (empty in case files
    written before they were)."""

    rank: tuple[int, ...]
    covered_50: tuple[bool, ...]
    covered_95: tuple[bool, ...]
    interval_share_95: tuple[float, ...]  # 95 % interval width / prior range
    divergences: int
    divergences_before_resampling: int | None = None  # of the first run, when it was run again
    truth: tuple[float, ...] = ()
    thinned_draws: tuple[tuple[float, ...], ...] = ()  # (RANK_DRAWS, 5): the draws the truth is ranked among

    def z_scores(self) -> np.ndarray | None:
        """(5,) the truth's distance from the posterior mean in posterior sd (thinned draws), NaN
        where the draws do not vary; None for a case file without them."""
        if not self.thinned_draws:
            return None
        draws = np.asarray(self.thinned_draws)
        sd = draws.std(axis=0)
        return np.where(sd > 0, (np.asarray(self.truth) - draws.mean(axis=0)) / np.where(sd > 0, sd, 1.0), np.nan)


def cases_of(
    data: StrainDataset,
    setup: str,
    n: int = 3,
    materials: list[int] | None = None,
    noise_seeds: int = 1,
    starts: int | None = None,
) -> list[CoverageCase]:
    """Every (test material, starting design, noise seed) case of ``setup`` (see module doc).

    ``starts``: starting designs per material (default: all). Material i starts from designs
    i, i + 1, ... (mod the number of designs), so every design is used about equally, a subset
    of ``materials`` keeps its cases, and with ``starts=1`` every case has its own material:
    independent cases."""
    if setup not in SETUPS:
        raise ValueError(f"setup must be one of {SETUPS}, got '{setup}'")
    materials = list(np.flatnonzero(data.split == 1)) if materials is None else materials
    n_designs = len(data.designs)
    starts = n_designs if starts is None else starts
    if not 1 <= starts <= n_designs:
        raise ValueError(f"starting designs per material must be in [1, {n_designs}], got {starts}")
    out = []
    for i in materials:
        for j in sorted(int(j) for j in (np.arange(starts) + i) % n_designs):
            designs = tuple(spread_designs(data.designs, j, n)) if setup == "membranes" else (j,)
            frames = tuple(range(-n, 0)) if setup == "frames" else (-1,)
            out += [CoverageCase(int(i), designs, frames, s) for s in range(noise_seeds)]
    return out


def noisy(observations: list[Observation], sd: float, seed: int) -> list[Observation]:
    """The observations with independent Gaussian noise of ``sd`` [strain] added and stated."""
    rng = np.random.default_rng(seed)
    return [
        Observation(
            o.alpha, o.t, o.fields + rng.normal(0, sd, o.fields.shape), o.mask, np.full(3, sd), o.truth, o.source
        )
        for o in observations
    ]


def run_case(
    emulator: Emulator,
    data: StrainDataset,
    case: CoverageCase,
    settings: SamplerSettings,
    noise_sd: float = 0.0,
    data_from: str = "fe",
) -> CaseResult:
    """Sample the case's posterior and rank its truth.

    ``data_from`` "fe": the material's simulated strains, its parameters the truth; "model": the
    truth drawn from the prior and the PC weights from the likelihood at it
    (:func:`inference.model.draw_from_model`), observed through the case's designs and frames
    with its noise sd stated: the posterior's own model, on which it is calibrated by
    construction (what departs is the sampler's or the GP variance fixed at the mode's doing)."""
    observations = from_dataset(data, case.material, list(case.designs), list(case.frames))
    if noise_sd > 0:
        observations = noisy(observations, noise_sd, 1000 * case.material + case.seed)
    case_settings = replace(settings, seed=settings.seed + case.seed, progress=False)
    noise = "known" if noise_sd > 0 else "halfcauchy"
    posterior = skin_posterior(emulator, ObservedWeights.project(emulator, observations), case_settings, noise)
    truth = data.params[case.material]
    if data_from == "model":
        values, weights = draw_from_model(posterior, 1000 * case.material + case.seed)
        truth = values[:5]
        observed = replace(posterior.observed, weights=weights, truth=truth)
        posterior = skin_posterior(emulator, observed, case_settings, noise)
    samples = sample_skin_posterior(posterior, case_settings)
    draws = samples.draws[..., :5].reshape(-1, 5)
    divergences = int(samples.diverging.sum())
    return case_result(draws, truth, emulator.param_bounds, divergences, samples.divergences_before_resampling)


def case_result(
    draws: np.ndarray, truth: np.ndarray, bounds: np.ndarray, divergences: int, before_resampling: int | None = None
) -> CaseResult:
    """Rank and interval coverage of the truth (5,) among posterior ``draws`` (n, 5) of the skin
    parameters (theta in degrees), interval widths as shares of the prior ``bounds`` (5, 2);
    ``before_resampling``: the divergences of a first run that was run again."""
    thinned = draws[np.linspace(0, len(draws) - 1, RANK_DRAWS).astype(int)]
    lo50, hi50, lo95, hi95 = np.percentile(draws, [25, 75, 2.5, 97.5], axis=0)
    return CaseResult(
        rank=tuple(int(r) for r in np.sum(thinned < truth, axis=0)),
        covered_50=tuple(bool(v) for v in (lo50 <= truth) & (truth <= hi50)),
        covered_95=tuple(bool(v) for v in (lo95 <= truth) & (truth <= hi95)),
        interval_share_95=tuple(float(v) for v in (hi95 - lo95) / np.ptp(bounds, axis=1)),
        divergences=divergences,
        divergences_before_resampling=before_resampling,
        truth=tuple(float(v) for v in truth),
        thinned_draws=tuple(tuple(float(v) for v in row) for row in thinned),
    )


def coverage_study(
    emulator: Emulator,
    data: StrainDataset,
    setup: str,
    settings: SamplerSettings,
    out: Path | str,
    n: int = 3,
    noise_sd: float = 0.0,
    noise_seeds: int = 1,
    materials: list[int] | None = None,
    starts: int | None = None,
    data_from: str = "fe",
) -> CoverageSummary:
    """Run (or resume) every case of ``setup`` (:func:`cases_of`) on data from the FE model or
    from the posterior's own model (``data_from``, :func:`run_case`); write ``coverage.json`` and
    ``ranks.png``."""
    if data_from not in DATA_SOURCES:
        raise ValueError(f"data_from must be one of {DATA_SOURCES}, got '{data_from}'")
    if data_from == "model" and noise_sd <= 0:
        raise ValueError("data drawn from the model need a stated noise sd (> 0): its unknown sd's prior is too wide")
    out = Path(out)
    results, cases = [], cases_of(data, setup, n, materials, noise_seeds, starts)
    for case in cases:
        path = out / "cases" / f"{case.name}.json"
        if path.exists():
            results.append(CaseResult(**json.loads(path.read_text())))
            continue
        results.append(run_case(emulator, data, case, settings, noise_sd, data_from))
        write_text(path, json.dumps(asdict(results[-1])) + "\n")
    summary = summarise(results, setup, n, noise_sd, settings, [case.material for case in cases], data_from)
    write_text(out / "coverage.json", json.dumps(summary.to_json(), indent=2) + "\n")
    observed = setup if setup == "single" else f"{setup} (n = {n})"
    source = ", data from the model" if data_from == "model" else ""
    error = emulator_error_of(settings)
    rank_histograms(
        np.array([r.rank for r in results]),
        out / "ranks.png",
        f"{observed}, noise sd {noise_sd:g}, emulator error {error}{source}: {len(results)} cases",
    )
    return summary


@dataclass(frozen=True)
class ParameterCoverage:
    """Coverage of one parameter's intervals over a study's cases."""

    coverage_50: float  # share of cases whose central 50 % interval holds the truth
    coverage_95: float
    binomial_sd_50: float  # cluster-robust over materials (clustered_sd)
    binomial_sd_95: float
    median_interval_share_95: float  # median 95 % interval width / prior range
    meets_goal: bool  # coverage_95 in GOAL_95 and coverage_50 in GOAL_50
    # RMS over cases of the truth's z-score (CaseResult.z_scores): 1 when calibrated (also for a
    # posterior equal to the prior), < 1 intervals too wide, > 1 too narrow; None without kept
    # draws (cases whose draws of the parameter do not vary are left out)
    rms_z: float | None = None


@dataclass(frozen=True)
class CoverageSummary:
    """What ``coverage.json`` holds."""

    setup: str
    n: int
    noise_sd: float
    n_cases: int
    n_materials: int
    divergences: int
    sampler: SamplerSettings
    parameters: dict[str, ParameterCoverage]
    cases_resampled: int = 0  # posteriors run again with smaller steps (sampling.RESAMPLE_ACCEPT)
    divergences_before_resampling: int = 0  # their first runs' divergences
    data_from: str = "fe"  # DATA_SOURCES: the FE model's strains or the posterior's own model (run_case)

    def to_json(self) -> dict:
        return asdict(self)


def clustered_sd(hits: np.ndarray, materials: np.ndarray) -> float:
    """Cluster-robust sd of the share of ``hits`` (n,) bool, cases grouped by ``materials`` (n,):
    sqrt(sum over materials of (sum of its (hit - p))^2) / n. One case per material gives the
    binomial sqrt(p (1 - p) / n); k copies of each material's cases leave it unchanged."""
    residual = hits - hits.mean()
    per_material = np.bincount(np.unique(materials, return_inverse=True)[1], weights=residual)
    return float(np.sqrt(np.sum(per_material**2)) / len(hits))


def rms_z_scores(results: list[CaseResult]) -> list[float | None]:
    """Per parameter, the RMS of the truth's z-scores over the cases whose draws vary; None for
    all when a case has no kept draws, or for a parameter whose draws vary in none."""
    scores = [r.z_scores() for r in results]
    if not scores or any(z is None for z in scores):
        return [None] * len(LABELS)
    z = np.array(scores)
    return [
        float(np.sqrt(np.mean(column[np.isfinite(column)] ** 2))) if np.isfinite(column).any() else None
        for column in z.T
    ]


def summarise(
    results: list[CaseResult],
    setup: str,
    n: int,
    noise_sd: float,
    settings: SamplerSettings,
    materials: list[int],
    data_from: str = "fe",
) -> CoverageSummary:
    """Coverage per parameter with its sd over ``materials`` (one per result), and whether it meets the goal."""
    n_cases, groups = len(results), np.asarray(materials)
    rms_z = rms_z_scores(results)
    parameters = {}
    for k, name in enumerate(LABELS):
        hits_50 = np.array([r.covered_50[k] for r in results], float)
        hits_95 = np.array([r.covered_95[k] for r in results], float)
        c50, c95 = float(hits_50.mean()), float(hits_95.mean())
        parameters[name] = ParameterCoverage(
            c50,
            c95,
            clustered_sd(hits_50, groups),
            clustered_sd(hits_95, groups),
            float(np.median([r.interval_share_95[k] for r in results])),
            bool(GOAL_95[0] <= c95 <= GOAL_95[1] and GOAL_50[0] <= c50 <= GOAL_50[1]),
            rms_z[k],
        )
    divergences = int(sum(r.divergences for r in results))
    first = [r.divergences_before_resampling for r in results if r.divergences_before_resampling is not None]
    return CoverageSummary(
        setup,
        n,
        noise_sd,
        n_cases,
        len(set(materials)),
        divergences,
        settings,
        parameters,
        len(first),
        sum(first),
        data_from,
    )


def rank_histograms(ranks: np.ndarray, path: Path | str, title: str, bins: int = 10) -> Path:
    """One histogram per parameter of the truth's rank (n_cases, 5), with the band a calibrated
    posterior's counts fall in 95 % of the time (binomial)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 5, figsize=(13, 2.8), sharey=True)
    expected = len(ranks) / bins
    half = 1.96 * np.sqrt(expected * (1 - 1 / bins))
    for k, (name, ax) in enumerate(zip(LABELS, axes)):
        ax.hist(ranks[:, k], bins=np.linspace(0, RANK_DRAWS + 1, bins + 1), color="tab:blue", alpha=0.8)
        ax.axhspan(max(0, expected - half), expected + half, color="0.8", zorder=0)
        ax.axhline(expected, color="k", lw=0.8)
        ax.set_title(LABELS[name])
        ax.set_xlabel(f"rank of the truth (0-{RANK_DRAWS})")
    axes[0].set_ylabel("cases")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path, dpi=110)
