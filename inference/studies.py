"""Studies over many posteriors: every test-split material for one observation setup.

An observation setup is a list of design indices and frame indices of the dataset (e.g. the
"mixed" design, last frame; the last 3 frames of one design; the last frame of 3 designs).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inference.model import ObservedWeights, SkinPosterior
from inference.observations import Observation, from_dataset
from inference.plots import LABELS, accuracy_plot, pyplot, save_figure
from inference.posterior_file import PosteriorSamples, PosteriorSummary, write_outputs
from inference.sampling import sample_posterior
from skinfem.io import StrainDataset
from skinfem.outputs import write_text
from surrogate.emulator import Emulator


@dataclass(frozen=True)
class SamplerSettings:
    chains: int = 4
    warmup: int = 500
    draws: int = 1000
    seed: int = 0
    n_jobs: int = 2
    gp_variance: str = "mode"
    progress: bool = True
    emulator_error: bool = True
    emulator_scale: bool = False
    emulator_shift: bool = False


EMULATOR_ERRORS = ("on", "scaled", "shift", "off")


def resolve_emulator_error(choice: str, emulator: Emulator | None) -> str:
    """An ``--emulator-error`` choice with ``auto`` (the command line's default) resolved:
    ``shift`` when ``emulator`` fitted a parameter shift (every emulator fitted with its error
    model does; None: emulators a study fits itself), else ``on`` (calibrated on 1–5
    observations with and without noise: docs/inference.md, "Coverage"). Other choices pass."""
    if choice != "auto":
        return choice
    excess = None if emulator is None else emulator.held_out_excess
    return "shift" if emulator is None or (excess is not None and excess.parameter_shift is not None) else "on"


def emulator_error_flags(choice: str) -> dict[str, bool]:
    """The :class:`SamplerSettings` flags of an ``--emulator-error`` choice (EMULATOR_ERRORS)."""
    if choice not in EMULATOR_ERRORS:
        raise ValueError(f"the emulator error must be one of {EMULATOR_ERRORS}, got '{choice}'")
    return {
        "emulator_error": choice != "off",
        "emulator_scale": choice == "scaled",
        "emulator_shift": choice == "shift",
    }


def emulator_error_of(settings: SamplerSettings) -> str:
    """The EMULATOR_ERRORS choice that ``settings`` hold (the inverse of :func:`emulator_error_flags`)."""
    if not settings.emulator_error:
        return "off"
    if settings.emulator_scale and settings.emulator_shift:
        return "shift-scaled"  # benchmarks/coverage.py's diagnostic
    return "scaled" if settings.emulator_scale else "shift" if settings.emulator_shift else "on"


def skin_posterior(
    emulator: Emulator, observed: ObservedWeights, settings: SamplerSettings, noise: str = "halfcauchy"
) -> SkinPosterior:
    """The posterior of ``observed`` weights (noise "halfcauchy" or "known") with the error model of ``settings``."""
    return SkinPosterior(
        emulator,
        observed,
        noise=noise,
        gp_variance=settings.gp_variance,
        emulator_error=settings.emulator_error,
        emulator_scale=settings.emulator_scale,
        emulator_shift=settings.emulator_shift,
    )


def sample_of(
    emulator: Emulator, observations: list[Observation], settings: SamplerSettings, noise: str = "halfcauchy"
) -> PosteriorSamples:
    """The posterior of ``observations`` (noise "halfcauchy" or "known"), sampled with ``settings``."""
    return sample_skin_posterior(
        skin_posterior(emulator, ObservedWeights.project(emulator, observations), settings, noise), settings
    )


def sample_skin_posterior(posterior: SkinPosterior, settings: SamplerSettings) -> PosteriorSamples:
    """``posterior`` sampled with ``settings``."""
    return sample_posterior(
        posterior,
        chains=settings.chains,
        warmup=settings.warmup,
        draws=settings.draws,
        seed=settings.seed,
        n_jobs=settings.n_jobs,
        progress=settings.progress,
    )


def posterior_of(
    emulator: Emulator,
    observations: list[Observation],
    settings: SamplerSettings,
    out: Path | None,
    noise: str = "halfcauchy",
) -> PosteriorSummary:
    """Sample one posterior; write its outputs to ``out`` if given. Returns the summary."""
    samples = sample_of(emulator, observations, settings, noise)
    sources = [o.source for o in observations]
    if out is None:
        return samples.summary(sources)
    return write_outputs(samples, out, sources)


def test_set_study(
    emulator: Emulator,
    data: StrainDataset,
    designs: list[int],
    frames: list[int],
    settings: SamplerSettings,
    out: Path | str,
    materials: list[int] | None = None,
    label: str | None = None,
) -> StudyResult:
    """Posteriors of every test material (or ``materials``) for one setup, accuracy + coverage.

    Writes ``<out>/material_<i>/`` per material (resumable: finished materials are reused),
    ``accuracy.png`` and ``study.json``.
    """
    out = Path(out)
    materials = list(np.flatnonzero(data.split == 1)) if materials is None else materials
    summaries = []
    for i in materials:
        directory = out / f"material_{i:03d}"
        if (directory / "summary.json").exists():
            summaries.append(PosteriorSummary.load(directory / "summary.json"))
            continue
        obs = from_dataset(data, int(i), designs, frames)
        summaries.append(posterior_of(emulator, obs, settings, directory))
    names = list(LABELS)
    coverage = {n: float(np.mean([s.parameters[n].covered for s in summaries])) for n in names}
    width = {n: float(np.median([s.parameters[n].interval_share_of_prior for s in summaries])) for n in names}
    identified = {n: bool(coverage[n] >= 0.8 and width[n] < 0.5) for n in names}
    label = label or f"designs {designs}, frames {frames}"
    accuracy_plot(
        summaries,
        emulator.param_bounds,
        out / "accuracy.png",
        f"{label}: posterior median and 95 % interval vs truth ({len(summaries)} test materials)",
    )
    result = StudyResult(
        designs=designs,
        frames=frames,
        label=label,
        materials=[int(i) for i in materials],
        coverage_95=coverage,
        median_interval_share_of_prior=width,
        identified=identified,
        max_r_hat=float(max(s.parameters[n].r_hat for s in summaries for n in names)),
    )
    write_text(out / "study.json", json.dumps(result.to_json(), indent=2) + "\n")
    return result


@dataclass(frozen=True)
class StudyResult:
    """A test-set study (:func:`test_set_study`), as its study.json holds it; per-parameter values by name
    ("mu", "k1", "k2", "kappa", "theta").

    Attributes:
        designs, frames, label: the observation setup (its "setup"): design and frame indices
            (None: every design, the last frame) and its name.
        materials: the test materials' indices.
        coverage_95: share of the materials whose 95 % interval covers the truth.
        median_interval_share_of_prior: median width of the 95 % interval / prior range.
        identified: coverage_95 >= 0.8 and median_interval_share_of_prior < 0.5.
        max_r_hat: the largest R-hat over the materials and parameters.
    """

    designs: list[int] | None
    frames: list[int] | None
    label: str
    materials: list[int]
    coverage_95: dict[str, float]
    median_interval_share_of_prior: dict[str, float]
    identified: dict[str, bool]
    max_r_hat: float

    @classmethod
    def from_json(cls, d: dict) -> StudyResult:
        setup = d["setup"]
        return cls(
            designs=setup["designs"],
            frames=setup["frames"],
            label=setup["label"],
            materials=d["materials"],
            coverage_95=d["coverage_95"],
            median_interval_share_of_prior=d["median_interval_share_of_prior"],
            identified=d["identified"],
            max_r_hat=d["max_r_hat"],
        )

    def to_json(self) -> dict:
        """The content of study.json (:meth:`from_json` reads it back)."""
        return {
            "setup": {"designs": self.designs, "frames": self.frames, "label": self.label},
            "materials": self.materials,
            "coverage_95": self.coverage_95,
            "median_interval_share_of_prior": self.median_interval_share_of_prior,
            "identified": self.identified,
            "max_r_hat": self.max_r_hat,
        }


def read_study(path: Path | str) -> StudyResult:
    """A study.json that :func:`test_set_study` wrote."""
    return StudyResult.from_json(json.loads(Path(path).read_text()))


def spread_designs(designs: np.ndarray, first: int, n: int) -> list[int]:
    """``first`` and n - 1 more design indices, each the farthest (in alpha) from those chosen.

    Greedy max-min selection over the (n_des, 2) eigen-strains: the extra membranes of a
    multi-membrane setup load the skin as differently as the dataset allows. Ties go to the
    design with the larger alpha11 + alpha22: stretching engages the fibers, which carry no
    load in compression.
    """
    designs = np.asarray(designs, dtype=float)
    if not 0 <= first < len(designs):
        raise ValueError(f"design {first} is not in [0, {len(designs)})")
    if not 1 <= n <= len(designs):
        raise ValueError(f"need 1 <= n <= {len(designs)} designs, got n = {n}")
    chosen = [first]
    while len(chosen) < n:
        gap = np.min(np.linalg.norm(designs[:, None, :] - designs[None, chosen, :], axis=-1), axis=1)
        ties = np.flatnonzero(gap >= gap.max() - 1e-12)
        chosen.append(int(ties[np.argmax(designs[ties].sum(axis=1))]))
    return chosen


def setups_plot(results: dict[str, StudyResult], path: Path | str) -> Path:
    """Median 95 %-interval width (share of the prior range) per parameter and setup (Fig. 8)."""
    plt = pyplot()

    names = list(LABELS)
    fig, ax = plt.subplots(figsize=(8, 3.8))
    width = 0.8 / len(results)
    for k, (label, res) in enumerate(results.items()):
        values = [res.median_interval_share_of_prior[n] for n in names]
        ax.bar(np.arange(5) + k * width, values, width, label=label)
    ax.set_xticks(np.arange(5) + 0.4 - width / 2, [LABELS[n] for n in names])
    ax.set_ylabel("95 % interval / prior range [-]")
    ax.axhline(0.5, color="k", lw=0.8, ls="--")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    ax.set_title("posterior width over the test materials (lower is better identified)")
    return save_figure(fig, path, dpi=120)


test_set_study.__test__ = False  # not a pytest test


PAPER_FINDINGS = {
    "noiseless": "θ best identified, then μ, then k1; κ wider; k2 not identifiable",
    "noise": "κ is lost first, then k1; μ and θ survive 10 % noise at 0.1 mm; at 5 mm only θ survives",
}
LENGTH_NAMES = {0.1: "s", 1.0: "m", 5.0: "l"}


def case_name(length: float, level: float) -> str:
    """The paper's names: s1 ... l10 (length class + level in %)."""
    return f"{LENGTH_NAMES.get(length, f'L{length:g}-')}{level * 100:g}"


def noise_study(
    data: StrainDataset,
    out: Path | str,
    design: int,
    settings: SamplerSettings,
    lengths: tuple[float, ...] = (0.1, 1.0, 5.0),
    levels: tuple[float, ...] = (0.01, 0.05, 0.10),
    materials: list[int] | None = None,
    fit_options: dict | None = None,
) -> dict[str, NoiseCase]:
    """The paper's noise study on ``data`` (clean): per case a noisy copy, an emulator fitted on
    its training materials only (with the clean case's number of PCs, or ``fit_options``'
    ``n_components`` in every case), validation on its test
    materials, and test-set posteriors for one design (last frame). Resumable: finished files
    are reused. Writes ``<out>/README.md``.

    Longer than a screen: the study's steps per case, in order, and its result record.
    """
    from inference.noise import add_noise
    from surrogate.validation import validate

    out = Path(out)
    fit_options = fit_options or {}
    cases = {"clean": None} | {case_name(length, v): (length, v) for length in lengths for v in levels}
    results = {}
    for k, (name, noise) in enumerate(cases.items()):
        folder = out / "cases" / name
        folder.mkdir(parents=True, exist_ok=True)
        path = data.path
        if noise is not None:
            path = folder / "data.h5"
            if not path.exists():
                add_noise(data, path, noise[0], noise[1], seed=k)
        case_data = StrainDataset.open(path)
        emulator = _case_emulator(case_data, folder / "emulator", fit_options)
        if noise is None and "n_components" not in fit_options:
            # noisy cases keep the clean number of PCs (as the paper does): a variance threshold
            # on noisy fields would retain hundreds of noise components
            fit_options = {**fit_options, "n_components": max(emulator.n_weights.values())}
        report, _ = validate(emulator, case_data)
        study = test_set_study(
            emulator,
            case_data,
            [design],
            [-1],
            settings,
            folder / "posteriors",
            materials,
            label=f"{name}: design {design}",
        )
        results[name] = NoiseCase(
            data=str(path),
            length_mm=None if noise is None else noise[0],
            level=None if noise is None else noise[1],
            study=study,
            explained_variance={
                c: np.cumsum(p.explained_variance_ratio_)[:12].tolist() for c, p in emulator.pcas.items()
            },
            n_components=dict(emulator.n_weights),
            r2_per_pc={c: [float(v) for v in r.r2_per_pc] for c, r in report.components.items()},
            pca_scaling=emulator.pca_scaling,
        )
    write_text(out / "noise_study.json", json.dumps({n: c.to_json() for n, c in results.items()}, indent=2) + "\n")
    explained_variance_plot(results, out / "explained_variance.png")
    sensitivity_maps(
        out,
        ["clean", case_name(lengths[min(1, len(lengths) - 1)], levels[0])],
        design,
        data.designs[design],
        out / "sensitivity.png",
    )
    write_noise_report(results, out)
    return results


@dataclass(frozen=True)
class NoiseCase:
    """One case of noise_study.json (written by :func:`noise_study`).

    Attributes:
        data: the case's dataset (the clean one, or its noisy copy); None in files written
            before it was recorded.
        length_mm, level: the added noise's length scale [mm] and level (share of the training
            data's max |strain|); None for the clean case.
        study: the test-set study of the case.
        explained_variance: per component, the cumulative explained variance of the first 12 PCs [-].
        n_components: per component, the PCs the case's emulator keeps.
        r2_per_pc: per component, the GPs' R² per PC on the held-out materials [-].
        pca_scaling: the PCA's per-cell scaling, "cell" or "none" (:mod:`surrogate.pca`);
            "cell" in files written before it was recorded.
    """

    data: str | None
    length_mm: float | None
    level: float | None
    study: StudyResult
    explained_variance: dict[str, list[float]]
    n_components: dict[str, int]
    r2_per_pc: dict[str, list[float]]
    pca_scaling: str = "cell"

    @classmethod
    def from_json(cls, d: dict) -> NoiseCase:
        noise = d["noise"] or {"length_mm": None, "level": None}
        return cls(
            data=d.get("data"),
            length_mm=noise["length_mm"],
            level=noise["level"],
            study=StudyResult.from_json(d["study"]),
            explained_variance=d["explained_variance"],
            n_components=d["n_components"],
            r2_per_pc=d["r2_per_pc"],
            pca_scaling=d.get("pca_scaling", "cell"),
        )

    def to_json(self) -> dict:
        """The case's entry in noise_study.json (:meth:`from_json` reads it back)."""
        noise = None if self.length_mm is None else {"length_mm": self.length_mm, "level": self.level}
        return {
            "data": self.data,
            "noise": noise,
            "explained_variance": self.explained_variance,
            "n_components": self.n_components,
            "r2_per_pc": self.r2_per_pc,
            "pca_scaling": self.pca_scaling,
            "study": self.study.to_json(),
        }


def read_noise_study(path: Path | str) -> dict[str, NoiseCase]:
    """A noise_study.json that :func:`noise_study` wrote: its cases by name ("clean", "s1", ..., "l10")."""
    return {name: NoiseCase.from_json(case) for name, case in json.loads(Path(path).read_text()).items()}


def _case_emulator(data: StrainDataset, folder: Path, fit_options: dict) -> Emulator:
    """The emulator of a noise-study case: read from ``folder`` if fitted, else fitted and saved there."""
    from surrogate.emulator import fit_emulator

    if (folder / "meta.json").exists():
        emulator = Emulator.load(folder)
        wanted = fit_options.get("pca_scaling", "cell")
        if emulator.pca_scaling != wanted:
            raise ValueError(
                f"{folder} holds an emulator with PCA scaling '{emulator.pca_scaling}', not '{wanted}': "
                "write this study to another folder"
            )
        return emulator
    emulator = fit_emulator(data, **fit_options)
    emulator.save(folder)
    return emulator


def explained_variance_plot(results: dict[str, NoiseCase], path: Path) -> Path:
    """Cumulative explained variance per case and component (the paper's Fig. 4).

    Cases that coincide stay visible: line style and marker by noise length scale ℓ, colour by
    noise level (the clean case black), each case shifted a little along M; the legend sits
    outside the panels.
    """
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    comps = list(next(iter(results.values())).explained_variance)
    noisy = [res for res in results.values() if res.length_mm is not None]
    lengths = sorted({res.length_mm for res in noisy})
    levels = sorted({res.level for res in noisy})
    styles = [("-", "o"), ("--", "s"), (":", "^"), ("-.", "D"), ((0, (5, 1, 1, 1, 1, 1)), "v")]
    colours = plt.get_cmap("plasma")(np.linspace(0.05, 0.75, max(len(levels), 1)))
    offsets = np.linspace(-0.3, 0.3, len(results)) if len(results) > 1 else np.zeros(1)
    lowest = min(min(ev) for res in results.values() for ev in res.explained_variance.values())
    fig, axes = plt.subplots(1, len(comps), figsize=(4.6 * len(comps) + 2.4, 4.2), squeeze=False)
    for ax, c in zip(axes[0], comps):
        for (name, res), dx in zip(results.items(), offsets):
            ev = np.asarray(res.explained_variance[c])
            if res.length_mm is None:
                style = {"color": "k", "ls": "-", "marker": "o", "lw": 2.0, "label": name}
            else:
                ls, marker = styles[lengths.index(res.length_mm) % len(styles)]
                style = {
                    "color": colours[levels.index(res.level)],
                    "ls": ls,
                    "marker": marker,
                    "lw": 1.4,
                    "label": f"{name}: ℓ = {res.length_mm:g} mm, level {res.level * 100:g} %",
                }
            ax.plot(np.arange(1, len(ev) + 1) + dx, ev, ms=4, **style)
        ax.axhline(0.99, color="0.5", ls="--", lw=0.8, label="99 %")
        ax.set_xlabel("number of principal components M")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(f"cumulative explained variance of E_{c} [-]")
        ax.set_ylim(max(0.0, lowest - 0.03), 1.005)
        ax.set_title(f"E_{c}", fontsize=10)
        ax.grid(alpha=0.3)
    axes[0, -1].legend(
        fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.02, 1.0),
        borderaxespad=0,
        title="case (noise length ℓ, level)",
        title_fontsize=8,
    )
    return save_figure(fig, path, dpi=120)


def sensitivity_maps(out: Path, cases: list[str], design: int, alpha: np.ndarray, path: Path, n: int = 41) -> Path:
    """First two PC weights of E_xx over (mu, k1), other parameters at the box centre, for two
    cases (the paper's Fig. 10: noise flattens the map, hence less identifiability)."""
    plt = pyplot()
    import torch

    from surrogate.emulator import model_inputs

    fig, axes = plt.subplots(len(cases), 2, figsize=(9, 3.8 * len(cases)), squeeze=False)
    for r, name in enumerate(cases):
        emulator = Emulator.load(out / "cases" / name / "emulator")
        b = emulator.param_bounds
        mu, k1 = np.meshgrid(np.linspace(*b[0], n), np.linspace(*b[1], n))
        params = np.tile(b.mean(1), (n * n, 1))
        params[:, 0], params[:, 1] = mu.ravel(), k1.ravel()
        with torch.no_grad():
            w = emulator.predict_weights(torch.as_tensor(model_inputs(params, alpha, 1.0)), return_var=False).numpy()
        for j in range(2):
            ax = axes[r, j]
            im = ax.contourf(mu, k1, w[:, j].reshape(n, n), levels=20, cmap="viridis")
            fig.colorbar(im, ax=ax, label=f"E_xx PC{j + 1} weight [-]")
            ax.set_xlabel(LABELS["mu"])
            ax.set_ylabel(LABELS["k1"])
            ax.set_title(f"{name}: E_xx PC{j + 1}", fontsize=10)
    return save_figure(fig, path)


def write_noise_report(results: dict[str, NoiseCase], out: Path) -> Path:
    """``<out>/README.md``: figures, R² tables, identification table next to the paper's findings."""
    names = list(LABELS)
    lines = [
        "# Noise study",
        "",
        "Each case adds zero-mean GP noise (RBF kernel, length scale ℓ, amplitude = level × max |strain| "
        "of the training data) to every frame, refits PCA and GPs on the training materials only and "
        "samples the posterior of every test material from the last frame of one design. Noisy cases "
        "keep the clean case's number of PCs M, so the explained variance at M shows what noise takes. "
        f"PCA scaling: {next(iter(results.values())).pca_scaling} (cell: per-cell standardisation, the paper's; "
        "none: strain units).",
        "",
        "![explained variance](explained_variance.png)",
        "",
        "## GP R² per PC on held-out materials",
        "",
    ]
    for c in next(iter(results.values())).r2_per_pc:
        width = max(len(r.r2_per_pc[c]) for r in results.values())
        lines += [
            f"**E_{c}**",
            "",
            "| case | M | " + " | ".join(f"PC{k + 1}" for k in range(width)) + " |",
            "|---|---|" + "---|" * width,
        ]
        for name, r in results.items():
            vals = r.r2_per_pc[c]
            lines.append(
                f"| {name} | {len(vals)} | " + " | ".join(f"{v:.3f}" for v in vals) + " |" + " |" * (width - len(vals))
            )
        lines.append("")
    lines += [
        "## Which parameters are identified",
        "",
        "Identified = the 95 % interval covers the truth for ≥ 80 % of the test materials and its median "
        "width is < 50 % of the prior range. Cells: coverage / median width share.",
        "",
        "| case | " + " | ".join(LABELS[n] for n in names) + " | identified |",
        "|---|" + "---|" * 6,
    ]
    for name, r in results.items():
        s = r.study
        cells = [f"{s.coverage_95[n]:.0%} / {s.median_interval_share_of_prior[n]:.2f}" for n in names]
        ident = ", ".join(LABELS[n].split(" ")[0] for n in names if s.identified[n]) or "none"
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {ident} |")
    lines += [
        "",
        "Paper (noiseless): " + PAPER_FINDINGS["noiseless"] + ".",
        "Paper (noise): " + PAPER_FINDINGS["noise"] + ".",
        "",
        "Accuracy plots: `cases/<case>/posteriors/accuracy.png`. Sensitivity of the PC weights over (μ, k₁):",
        "",
        "![sensitivity](sensitivity.png)",
        "",
    ]
    return write_text(out / "README.md", "\n".join(lines))
