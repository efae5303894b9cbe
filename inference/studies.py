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
from inference.plots import LABELS, accuracy_plot
from inference.sampling import sample_posterior, write_outputs
from skinfem.io import StrainDataset
from surrogate.emulator import Emulator


@dataclass(frozen=True)
class SamplerSettings:
    chains: int = 4
    warmup: int = 500
    draws: int = 1000
    seed: int = 0
    n_jobs: int = 2
    gp_variance: str = "exact"
    progress: bool = True


def posterior_of(
    emulator: Emulator, observations: list[Observation], settings: SamplerSettings, out: Path | None,
    noise: str = "halfcauchy",
) -> dict:
    """Sample one posterior; write its outputs to ``out`` if given. Returns the summary."""
    posterior = SkinPosterior(emulator, ObservedWeights.project(emulator, observations), noise=noise,
                              gp_variance=settings.gp_variance)
    samples = sample_posterior(posterior, chains=settings.chains, warmup=settings.warmup,
                               draws=settings.draws, seed=settings.seed, n_jobs=settings.n_jobs,
                               progress=settings.progress)
    extra = {"observations": [o.source for o in observations]}
    if out is None:
        return {**samples.summary(), **extra}
    return write_outputs(samples, out, extra)


def test_set_study(
    emulator: Emulator,
    data: StrainDataset,
    designs: list[int],
    frames: list[int],
    settings: SamplerSettings,
    out: Path | str,
    materials: list[int] | None = None,
    label: str | None = None,
) -> dict:
    """Posteriors of every test material (or ``materials``) for one setup, accuracy + coverage.

    Writes ``<out>/material_<i>/`` per material (resumable: finished materials are reused),
    ``accuracy.png`` and ``study.json``.
    """
    out = Path(out)
    materials = list(np.flatnonzero(data.split == 1)) if materials is None else materials
    rows = []
    for i in materials:
        directory = out / f"material_{i:03d}"
        summary_path = directory / "summary.json"
        if summary_path.exists():
            rows.append(json.loads(summary_path.read_text())["parameters"])
            continue
        obs = from_dataset(data, int(i), designs, frames)
        rows.append(posterior_of(emulator, obs, settings, directory)["parameters"])
    names = list(LABELS)
    coverage = {n: float(np.mean([r[n]["covered"] for r in rows])) for n in names}
    width = {n: float(np.median([r[n]["interval_share_of_prior"] for r in rows])) for n in names}
    identified = {n: bool(coverage[n] >= 0.8 and width[n] < 0.5) for n in names}
    label = label or f"designs {designs}, frames {frames}"
    accuracy_plot(rows, emulator.param_bounds, out / "accuracy.png",
                  f"{label}: posterior median and 95 % interval vs truth ({len(rows)} test materials)")
    result = {
        "setup": {"designs": designs, "frames": frames, "label": label},
        "materials": [int(i) for i in materials],
        "coverage_95": coverage,
        "median_interval_share_of_prior": width,
        "identified": identified,
        "max_r_hat": float(max(r[n]["r_hat"] for r in rows for n in names)),
    }
    (out / "study.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def setups_plot(results: dict[str, dict], path: Path | str) -> Path:
    """Median 95 %-interval width (share of the prior range) per parameter and setup (Fig. 8)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(LABELS)
    fig, ax = plt.subplots(figsize=(8, 3.8))
    width = 0.8 / len(results)
    for k, (label, res) in enumerate(results.items()):
        values = [res["median_interval_share_of_prior"][n] for n in names]
        ax.bar(np.arange(5) + k * width, values, width, label=label)
    ax.set_xticks(np.arange(5) + 0.4 - width / 2, [LABELS[n] for n in names])
    ax.set_ylabel("95 % interval / prior range [-]")
    ax.axhline(0.5, color="k", lw=0.8, ls="--")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    ax.set_title("posterior width over the test materials (lower is better identified)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)
test_set_study.__test__ = False  # not a pytest test
