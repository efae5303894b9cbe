"""What limits a posterior: the measurement noise or the emulator, as the stated noise sd grows.

    skinid surrogate fit --data out/small.h5 --out out/emu --gp-fraction 0.5 --restarts 1
    skinid surrogate fit --data out/small.h5 --out out/emu999 --gp-fraction 0.5 --restarts 1 --variance 0.999
    python benchmarks/error_budget.py --emulator "99 % (2 PCs)=out/emu" --emulator "99.9 % (6 PCs)=out/emu999" \
        --data out/small.h5

For every case of each panel (the test materials of --data x starting designs, as in
``skinid study coverage``: the single and 3-membrane setups, on the full field and through a DIC
window of +-18 mm with 15 % of the cells missing) and every stated noise sd, the share of the observed PC weights'
variance held by each term of the likelihood (:meth:`inference.model.SkinPosterior.error_budget`:
noise, the GPs' own variance, the cross-validated held-out excess, PCA truncation) at the true
parameters, averaged over the cases. No sampling: the budget is a property of the likelihood.
Writes benchmarks/results/error_budget.json and error_budget.png (the README's figure).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
TERMS = ("noise", "gp", "held_out_excess", "truncation")
TERM_LABELS = ("measurement noise", "GP variance", "held-out excess", "PCA truncation")


PANELS = {
    "single, full field": ("single", None),
    "single, DIC window": ("single", 18.0),
    "3 membranes, DIC window": ("membranes", 18.0),
}


def dic_window(observation, xy: np.ndarray, half: float, holes: float, rng) -> None:
    """Keep the cells (centres ``xy`` (n_cells, 2) [mm]) within +-``half`` mm of the membrane
    centre, less a random share ``holes``."""
    inside = (np.abs(xy) <= half).all(1) & (rng.random(len(xy)) >= holes)
    observation.mask = observation.mask & inside
    observation.fields = np.where(observation.mask[:, None], observation.fields, np.nan)


def case_budgets(emulator, data, case, noise_sd: np.ndarray, half: float | None) -> np.ndarray:
    """(n_sd, 4) shares of the weights' variance (noise, GP, excess, truncation) at the truth,
    on the full field (``half`` None) or through a DIC window of +-``half`` mm with holes."""
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset

    observations = from_dataset(data, case.material, list(case.designs), list(case.frames))
    if half is not None:
        rng = np.random.default_rng(case.material)
        for o in observations:
            dic_window(o, data.xy, half, 0.15, rng)
    rows = []
    for sd in noise_sd:
        for o in observations:
            o.sd = np.full(3, sd)
        posterior = SkinPosterior(emulator, ObservedWeights.project(emulator, observations), noise="known")
        budget = posterior.error_budget(data.params[case.material])
        rows.append([asdict(budget)[t] for t in TERMS])
    return np.array(rows)


def plot(noise_sd: np.ndarray, shares: dict[str, dict[str, np.ndarray]], path: Path) -> Path:
    """A stacked-area panel per emulator (rows) and setup / field of view (columns): the share
    of each term against the stated noise sd."""
    from inference.plots import pyplot, save_figure

    plt = pyplot()
    n_rows, n_cols = len(shares), len(PANELS)
    fig, axes = plt.subplots(
        n_rows, n_cols, figsize=(4.2 * n_cols, 3.2 * n_rows), sharex=True, sharey=True, squeeze=False
    )
    colours = ("#4c72b0", "#dd8452", "#c44e52", "#8c8c8c")
    for row, (label, by_panel) in zip(axes, shares.items()):
        for ax, (panel, s) in zip(row, by_panel.items()):
            ax.stackplot(noise_sd, s.T, labels=TERM_LABELS, colors=colours, alpha=0.85)
            ax.set_xscale("log")
            ax.set_xlim(noise_sd[0], noise_sd[-1])
            ax.set_ylim(0, 1)
            ax.axhline(0.5, color="k", lw=0.6, ls=":")
            ax.set_title(f"{label}: {panel}", fontsize=9)
        row[0].set_ylabel("share of the weights' variance [-]")
    for ax in axes[-1]:
        ax.set_xlabel("stated noise sd [strain]")
    axes[0, -1].legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=8, frameon=False)
    fig.suptitle("What limits the posterior: the measurement noise (blue) or the emulator (the rest)", fontsize=10)
    return save_figure(fig, path)


def main() -> None:
    from inference.coverage import cases_of
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--emulator", action="append", required=True, help="LABEL=FOLDER (repeat: one row each)")
    parser.add_argument("--data", type=Path, required=True, help="dataset whose test materials are the cases")
    parser.add_argument("--noise-sd", type=float, nargs=2, default=[1e-5, 1e-2], help="sd range [strain]")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    data = StrainDataset.open(args.data)
    noise_sd = np.geomspace(*args.noise_sd, 25)
    shares: dict[str, dict[str, np.ndarray]] = {}
    crossings: dict[str, dict[str, float | None]] = {}
    for spec in args.emulator:
        label, _, folder = spec.rpartition("=")
        emulator = Emulator.load(folder)
        shares[label], crossings[label] = {}, {}
        for panel, (setup, half) in PANELS.items():
            s = np.mean([case_budgets(emulator, data, c, noise_sd, half) for c in cases_of(data, setup)], axis=0)
            noise_dominates = s[:, 0] > 0.5
            crossings[label][panel] = float(noise_sd[np.argmax(noise_dominates)]) if noise_dominates.any() else None
            shares[label][panel] = s
            print(f"{label}, {panel}: the noise holds half the variance from sd {crossings[label][panel]}")
    args.results.mkdir(parents=True, exist_ok=True)
    result = {
        "emulators": args.emulator,
        "data": str(args.data),
        "terms": list(TERMS),
        "noise_sd": noise_sd.tolist(),
        "shares": {k: {p: v.round(4).tolist() for p, v in by.items()} for k, by in shares.items()},
        "noise_holds_half_from_sd": crossings,
        "cases": {panel: len(cases_of(data, setup)) for panel, (setup, _) in PANELS.items()},
    }
    (args.results / "error_budget.json").write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {plot(noise_sd, shares, args.results / 'error_budget.png')}")


if __name__ == "__main__":
    main()
