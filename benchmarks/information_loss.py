"""Where a noise study loses the field's information: a ladder of linearised widths per step.

    python benchmarks/information_loss.py --study out/paper_uniaxial_noise --design uniaxial
        [--jacobians out/design_information] [--observable surface] [--cases clean s1 s10]
        [--results benchmarks/results/information_loss.json]

The paper-mesh noise studies' 95 % intervals are 6× and more wider than what the fields carry
(``benchmarks/design_information.py``). This follows one observation (one design, last frame)
from the field to the posterior and measures, at each test material's true parameters, the
linearised (Cramér–Rao) 95 % width as a share of the prior range after each step, using the
field's exact derivative (forward differences of whole FE simulations, kept by
design_information.py) wherever the step allows:

1. ``field``: every cell of the components the emulator models (E_xx, E_yy), with the noise
   the study added (amplitude and length scale from the case's dataset).
2. ``retained PCs``: the same field seen only through the PC weights the emulator keeps (the
   case's PCA, standardised per cell or not as it was fitted), with that noise carried exactly
   into the weights.
3. ``noise as modelled``: the likelihood's noise model instead — one sd per component shared by
   all its weights, at the posterior median of that sd.
4. ``+ emulator error``: the likelihood's emulator covariance at the truth added (GP variance,
   held-out excess, PCA truncation), as the studies' posteriors carry it (``--emulator-error
   on``); the GPs' white-noise level is in it unless the emulator recorded its training data's
   noise (then that level is the measurement's noise; the key says "latent GP"). Each noisy
   case also records its GPs' white-noise sd over the added noise's sd per weight.
5. ``emulator Jacobian``: the emulator's derivative (autograd of its GP means) instead of the
   field's: the study's likelihood, linearised.
6. ``posterior``: the NUTS width the study recorded.

A step that widens a parameter's interval is where its information goes; what is left between
5 and 6 is the likelihood's nonlinearity, the prior box and the uncertain noise sd. Recorded,
not asserted: ``tests/test_information_loss.py`` checks the ladder's algebra.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from inference.studies import NoiseCase
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

PARAMS = ("mu", "k1", "k2", "kappa", "theta")
STEPS = ("field", "retained PCs", "noise as modelled", "+ emulator error", "emulator Jacobian", "posterior")
Z95 = 1.959963984540054


def width_95(fisher: np.ndarray) -> np.ndarray:
    """(5,) 95 % Cramér–Rao width 2 × 1.96 × sd from a Fisher matrix (5, 5) in prior-range units
    (a singular direction gets an infinite width)."""
    values, vectors = np.linalg.eigh((fisher + fisher.T) / 2)
    floor = 1e-12 * max(values.max(), 1e-300)
    inverse = (vectors / np.where(values > floor, values, np.nan)) @ vectors.T
    variance = np.diag(inverse)
    return np.where(np.isfinite(variance), 2 * Z95 * np.sqrt(np.abs(variance)), np.inf)


def gaussian_fisher(jacobian: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """J^T C^-1 J (5, 5) of a Gaussian mean J (n, 5) with covariance C (n, n)."""
    factor = np.linalg.cholesky(covariance)
    white = np.linalg.solve(factor, jacobian)
    return white.T @ white


def weight_map(components: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(M, n_cells) linear map from a strain field to its PC weights: components (M, n_cells)
    of the per-cell standardised field, scale (n_cells,) the standardisation's sd [strain]."""
    return components / scale


@dataclass(frozen=True)
class Ladder:
    """The widths (95 % / prior range) of one material and case after each step (STEPS), per parameter."""

    material: int
    widths: dict[str, dict[str, float]]


def ladder(
    field_jacobian: dict[str, np.ndarray],
    maps: dict[str, np.ndarray],
    noise_sd: dict[str, float],
    correlation: np.ndarray,
    model_noise_sd: dict[str, float],
    emulator_variance: np.ndarray,
    emulator_jacobian: np.ndarray,
) -> list[np.ndarray]:
    """Widths (5,) after steps 1-5 (STEPS) for one observation.

    Args:
        field_jacobian: per component (n_cells, 5) d strain / d parameter per prior range.
        maps: per component the weight map (M_c, n_cells) (:func:`weight_map`).
        noise_sd: per component the added noise's amplitude [strain] (0: no noise).
        correlation: (n_cells, n_cells) the noise's correlation between cells.
        model_noise_sd: per component the likelihood's noise sd [PC-weight units].
        emulator_variance: (G,) the likelihood's emulator variance of each weight (in component order).
        emulator_jacobian: (G, 5) d weight / d parameter per prior range from the emulator.
    """
    comps = list(maps)
    noise_cov = {c: noise_sd[c] ** 2 * maps[c] @ correlation @ maps[c].T for c in comps}
    j_w = np.concatenate([maps[c] @ field_jacobian[c] for c in comps])
    model_noise = np.concatenate([np.full(len(maps[c]), model_noise_sd[c] ** 2) for c in comps])
    fisher_field = sum(
        (gaussian_fisher(field_jacobian[c], noise_sd[c] ** 2 * correlation) for c in comps if noise_sd[c] > 0),
        np.zeros((5, 5)),
    )
    fisher_pcs = sum(
        (gaussian_fisher(maps[c] @ field_jacobian[c], noise_cov[c]) for c in comps if noise_sd[c] > 0),
        np.zeros((5, 5)),
    )
    total = np.diag(model_noise + emulator_variance)
    return [
        width_95(fisher_field),
        width_95(fisher_pcs),
        width_95(gaussian_fisher(j_w, np.diag(model_noise))),
        width_95(gaussian_fisher(j_w, total)),
        width_95(gaussian_fisher(emulator_jacobian, total)),
    ]


def case_noise(data: StrainDataset) -> tuple[dict[str, float], float]:
    """The noise a study case added (amplitude per component [strain], length scale [mm]); none for the clean data."""
    from skinfem.io import COMPONENTS

    noise = data.added_noise
    if noise is None:
        return dict.fromkeys(COMPONENTS, 0.0), 0.0
    return dict(zip(COMPONENTS, noise.amplitude)), noise.length_mm


def white_noise_over_added(case: StudyCase) -> dict[str, list[float]] | None:
    """Per component, each GP's white-noise sd over the added noise's sd [-] (None: clean case)."""
    if case.data.added_noise is None:
        return None
    gps, slices = case.emulator.gps, case.emulator.weight_slices()
    sd = (gps.noise * gps.y_std**2).sqrt().numpy()
    return {c: (sd[s] / case.noise_sd[c]).tolist() for c, s in slices.items()}


@dataclass(frozen=True)
class StudyCase:
    """What every material of one noise-study case shares, read once.

    Attributes:
        folder: the case's folder (``<study>/cases/<name>``).
        data: its dataset (the clean one or its noisy copy); emulator: its emulator.
        design: the study's one design (index into the dataset's designs).
        noise_sd: per component the added noise's amplitude [strain] (0: the clean case).
        correlation: (n_cells, n_cells) the added noise's correlation between cells.
    """

    folder: Path
    data: StrainDataset
    emulator: Emulator
    design: list[int]
    noise_sd: dict[str, float]
    correlation: np.ndarray


def read_case(folder: Path, record: NoiseCase) -> StudyCase:
    """The shared inputs of one noise-study case folder, ``record`` its entry in noise_study.json."""
    from inference.noise import correlation_matrix
    from inference.studies import read_study
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    data = StrainDataset.open(record.data)
    noise_sd, length = case_noise(data)
    return StudyCase(
        folder,
        data,
        Emulator.load(folder / "emulator"),
        read_study(folder / "posteriors" / "study.json").designs,
        noise_sd,
        correlation_matrix(data.xy, length),
    )


def material_ladder(case: StudyCase, material: int, jacobian_file: Path, observable: str) -> Ladder:
    """Steps 1-6 (STEPS) for one material of one noise-study case."""
    import torch

    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset
    from skinfem.io import COMPONENTS

    data, emulator = case.data, case.emulator
    summary = json.loads((case.folder / "posteriors" / f"material_{material:03d}" / "summary.json").read_text())
    prior_range = np.diff(emulator.param_bounds, axis=1)[:, 0]
    saved = np.load(jacobian_file)
    if not np.allclose(saved["xy"], data.xy):
        raise ValueError(f"{jacobian_file} was computed on other cells than {data.path}")
    jacobian = saved[f"jacobian_{observable}"] * prior_range  # (n_cells, 3, 5) per prior range
    field_jacobian = {c: jacobian[:, COMPONENTS.index(c)] for c in emulator.components}
    maps = {c: weight_map(p.components_, p.scale_) for c, p in emulator.pcas.items()}
    model_sd = {c: summary["parameters"][f"sigma_{c}"]["median"] for c in emulator.components}
    observed = ObservedWeights.project(emulator, from_dataset(data, material, case.design, [-1]))
    posterior = SkinPosterior(emulator, observed, gp_variance="exact")
    truth = torch.as_tensor(data.params[material], dtype=torch.float64)
    _, gp_cov = posterior.gp_moments(truth)
    emulator_variance = posterior.model_covariance(gp_cov).detach().numpy()[:, 0, 0]
    jac = torch.autograd.functional.jacobian(
        lambda p: emulator.predict_weights(posterior.inputs(p), return_var=False)[0], truth
    ).numpy()
    widths = ladder(
        field_jacobian, maps, case.noise_sd, case.correlation, model_sd, emulator_variance, jac * prior_range
    )
    widths.append(np.array([summary["parameters"][n]["interval_share_of_prior"] for n in PARAMS]))
    return Ladder(material, {step: dict(zip(PARAMS, map(float, w))) for step, w in zip(STEPS, widths)})


def medians(ladders: list[Ladder]) -> dict[str, dict[str, float | None]]:
    """Median width over materials per step and parameter (None: infinite, no noise to bound it)."""
    out = {}
    for step in STEPS:
        out[step] = {}
        for n in PARAMS:
            value = float(np.median([lad.widths[step][n] for lad in ladders]))
            out[step][n] = value if np.isfinite(value) else None
    return out


def table(results: dict[str, dict]) -> str:
    """Markdown: per case the median width after each step."""
    lines = ["| case | step | " + " | ".join(PARAMS) + " |", "|---" * (len(PARAMS) + 2) + "|"]
    for name, entry in results.items():
        for step, widths in entry["median"].items():
            cells = ["—" if widths[n] is None else f"{widths[n]:.3g}" for n in PARAMS]
            lines.append(f"| {name} | {step} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def finite(value):
    """JSON-safe: an infinite width becomes None."""
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    return value if np.isfinite(value) else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--study", type=Path, required=True, help="a noise study's folder (skinid study noise --out)")
    parser.add_argument("--design", required=True, help="the design's name in design_information.py (e.g. uniaxial)")
    parser.add_argument("--jacobians", type=Path, default=Path("out/design_information"))
    parser.add_argument("--observable", default="surface", choices=["surface", "top_cell_average"])
    parser.add_argument("--config", default="paper", help="the configuration design_information.py ran")
    parser.add_argument("--cases", nargs="+", default=["clean", "s1", "s10"])
    parser.add_argument("--results", type=Path, default=Path("benchmarks/results/information_loss.json"))
    args = parser.parse_args()
    results = json.loads(args.results.read_text()) if args.results.exists() else {}
    from inference.studies import read_noise_study

    cases = read_noise_study(args.study / "noise_study.json")
    entry, latent = {}, False
    for name in args.cases:
        case = args.study / "cases" / name
        shared = read_case(case, cases[name])
        latent |= shared.emulator.white_noise_is_measurement
        ladders = [
            material_ladder(shared, int(m), path, args.observable)
            for m, path in sorted(
                (p.stem.split("_")[1], p) for p in args.jacobians.glob(f"{args.config}_*_{args.design}.npz")
            )
            if m.isdigit() and (case / "posteriors" / f"material_{int(m):03d}" / "summary.json").exists()
        ]
        if not ladders:
            raise SystemExit(f"error: no material of {case} has a Jacobian in {args.jacobians}")
        entry[name] = {
            "materials": [lad.material for lad in ladders],
            "gp_white_noise_sd_over_added_sd": white_noise_over_added(shared),
            "median": medians(ladders),
            "per_material": [finite(asdict(lad)) for lad in ladders],
        }
    key = f"{args.design}, {args.observable}, PCA scaling {cases[args.cases[0]].pca_scaling}" + ", latent GP" * latent
    command = (
        f"python benchmarks/information_loss.py --study {args.study} --design {args.design} "
        f"--observable {args.observable}"
    )
    results[key] = {"command": command, "steps": list(STEPS), "cases": entry}
    args.results.write_text(json.dumps(results, indent=2) + "\n")
    print(table(entry))


if __name__ == "__main__":
    main()
