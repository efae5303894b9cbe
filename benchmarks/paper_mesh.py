"""The paper's identifiability and noise studies on the paper mesh, side by side with the `study` mesh.

    # 1. paper-mesh data: 120 materials, the "mixed" design (0.05, -0.05), 10 frames (~35 min, 2 cores)
    mpirun -n 2 skinid sweep --config benchmarks/configs/paper_mixed.toml --out out/paper_mixed.h5
    # 2. the cells hypothesis: the same data on 256 of its 3,844 skin cells (every 4th row and column)
    python benchmarks/paper_mesh.py subset --data out/paper_mixed.h5 --every 4 --out out/paper_mixed_256.h5
    # 3. the noise studies (clean = identifiability), as the `study` run in benchmarks/results/noise_study
    skinid study noise --data out/paper_mixed.h5 --designs 0 --gp-fraction 0.7 --restarts 0 \
        --warmup 300 --draws 300 --out out/paper_noise
    skinid study noise --data out/paper_mixed_256.h5 --designs 0 --gp-fraction 0.7 --restarts 0 \
        --warmup 300 --draws 300 --lengths 0.1 --levels 0.01 0.1 --out out/paper_noise_256
    # 4. the side-by-side table and the coverage of the noise cases (benchmarks/results/paper_mesh/)
    python benchmarks/paper_mesh.py table --run "paper mesh=out/paper_noise" \
        --run "paper mesh, 256 cells=out/paper_noise_256" \
        --run "study mesh=benchmarks/results/noise_study"
    python benchmarks/paper_mesh.py coverage --study out/paper_noise
    # 5. the "max" design (0.05, 0.05), another of the paper's single observations (~48 min, 2 cores),
    #    the clean case and white noise 1 % and 10 %, side by side with the mixed design
    mpirun -n 2 skinid sweep --config benchmarks/configs/paper_max.toml --out out/paper_max.h5
    skinid study noise --data out/paper_max.h5 --designs 0 --gp-fraction 0.7 --restarts 0 --warmup 300 \
        --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --emulator-error on --lengths 0.1 \
        --levels 0.01 0.1 --out out/paper_max_noise
    python benchmarks/paper_mesh.py table --run "max design=out/paper_max_noise" \
        --run "mixed design=benchmarks/results/paper_mesh/noise_paper_mesh" --results benchmarks/results/paper_mesh_max
    python benchmarks/paper_mesh.py coverage --study out/paper_max_noise --results benchmarks/results/paper_mesh_max
    # 6. the "uniaxial" design (0.05, 0), the paper's third single observation, as step 5
    mpirun -n 2 skinid sweep --config benchmarks/configs/paper_uniaxial.toml --out out/paper_uniaxial.h5
    skinid study noise --data out/paper_uniaxial.h5 --designs 0 --gp-fraction 0.7 --restarts 0 --warmup 300 \
        --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --emulator-error on --lengths 0.1 \
        --levels 0.01 0.1 --out out/paper_uniaxial_noise
    python benchmarks/paper_mesh.py table --run "uniaxial design=out/paper_uniaxial_noise" \
        --run "max design=benchmarks/results/paper_mesh_max/noise_paper_mesh_max" \
        --run "mixed design=benchmarks/results/paper_mesh/noise_paper_mesh" \
        --results benchmarks/results/paper_mesh_uniaxial
    python benchmarks/paper_mesh.py coverage --study out/paper_uniaxial_noise \
        --results benchmarks/results/paper_mesh_uniaxial
    # 7. the PCA in strain units (--pca-scaling none) instead of standardised per cell, 5 + 5 PCs as the
    #    standardised noisy cases keep: the uniaxial design's study again, and where each study loses the
    #    field's information
    #    (benchmarks/information_loss.py, from design_information.py's Jacobians)
    skinid study noise --data out/paper_uniaxial.h5 --designs 0 --gp-fraction 0.7 --restarts 0 --warmup 300 \
        --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --emulator-error on --lengths 0.1 \
        --levels 0.01 0.1 --pca-scaling none --n-components 5 --out out/paper_uniaxial_noise_unscaled
    python benchmarks/paper_mesh.py table --run "unscaled PCA=out/paper_uniaxial_noise_unscaled" \
        --run "standardised PCA=benchmarks/results/paper_mesh_uniaxial/noise_paper_mesh_uniaxial" \
        --results benchmarks/results/paper_mesh_unscaled
    python benchmarks/paper_mesh.py coverage --study out/paper_uniaxial_noise_unscaled \
        --results benchmarks/results/paper_mesh_unscaled
    python benchmarks/information_loss.py --study out/paper_uniaxial_noise --design uniaxial
    python benchmarks/information_loss.py --study out/paper_uniaxial_noise_unscaled --design uniaxial
    # 8. the paper's observable: the mixed design with the skin cells' average strain (~50 min), as step 5
    mpirun -n 2 skinid sweep --config benchmarks/configs/paper_mixed_cell_average.toml \
        --out out/paper_mixed_cell_average.h5
    skinid study noise --data out/paper_mixed_cell_average.h5 --designs 0 --gp-fraction 0.7 --restarts 0 \
        --warmup 300 --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --emulator-error on --lengths 0.1 \
        --levels 0.01 0.1 --out out/paper_cell_average_noise
    python benchmarks/paper_mesh.py table --run "cell average=out/paper_cell_average_noise" \
        --run "surface=benchmarks/results/paper_mesh/noise_paper_mesh" \
        --results benchmarks/results/paper_mesh_cell_average
    python benchmarks/paper_mesh.py coverage --study out/paper_cell_average_noise \
        --results benchmarks/results/paper_mesh_cell_average
    python benchmarks/information_loss.py --study out/paper_cell_average_noise --design mixed \
        --observable top_cell_average
    # 9. step 7 again with the training noise counted once (emulators that record their training data's
    #    noise carry the GPs' latent covariance), and the mixed design's surface data the same way
    skinid study noise --data out/paper_uniaxial.h5 --designs 0 --gp-fraction 0.7 --restarts 0 --warmup 300 \
        --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --emulator-error on --lengths 0.1 \
        --levels 0.01 0.1 --pca-scaling none --n-components 5 --out out/paper_uniaxial_noise_latent
    python benchmarks/paper_mesh.py table --run "latent GP=out/paper_uniaxial_noise_latent" \
        --run "white noise counted twice=benchmarks/results/paper_mesh_unscaled/noise_paper_mesh_unscaled" \
        --results benchmarks/results/paper_mesh_latent
    python benchmarks/paper_mesh.py coverage --study out/paper_uniaxial_noise_latent \
        --results benchmarks/results/paper_mesh_latent
    python benchmarks/information_loss.py --study out/paper_uniaxial_noise_latent --design uniaxial
    mpirun -n 2 skinid sweep --config benchmarks/configs/paper_mixed.toml --out out/paper_mixed.h5
    skinid study noise --data out/paper_mixed.h5 --designs 0 --gp-fraction 0.7 --restarts 0 --warmup 300 \
        --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --emulator-error on --lengths 0.1 \
        --levels 0.01 0.1 --pca-scaling none --n-components 5 --out out/paper_mixed_noise_latent
    python benchmarks/paper_mesh.py table --run "unscaled PCA, latent GP=out/paper_mixed_noise_latent" \
        --run "standardised PCA=benchmarks/results/paper_mesh/noise_paper_mesh" \
        --results benchmarks/results/paper_mesh_mixed_unscaled
    python benchmarks/paper_mesh.py coverage --study out/paper_mixed_noise_latent \
        --results benchmarks/results/paper_mesh_mixed_unscaled
    python benchmarks/information_loss.py --study out/paper_mixed_noise_latent --design mixed
    # 10. step 9's mixed-design study at the three correlation lengths (run first with --lengths 5.0, then
    #     completed with --resume: the cases keep their seeds; the 5 % cases last, listed after 10 % so
    #     that the finished cases keep theirs), the noise-free case on all 20 test materials, and the
    #     noise on the weights
    skinid study noise --data out/paper_mixed.h5 --designs 0 --gp-fraction 0.7 --restarts 0 --warmup 300 \
        --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --emulator-error on --lengths 5.0 1.0 0.1 \
        --levels 0.01 0.1 0.05 --pca-scaling none --n-components 5 --out out/paper_mixed_noise_latent_long
    skinid study test-set --emulator out/paper_mixed_noise_latent_long/cases/clean/emulator --data out/paper_mixed.h5 \
        --designs 0 --materials 74,79,82,88,89,98,99,106,115,119 --warmup 300 --draws 300 --emulator-error on \
        --out out/paper_mixed_clean20/cases/clean/posteriors
    cp -r out/paper_mixed_noise_latent_long/cases/clean/posteriors/material_* \
        out/paper_mixed_clean20/cases/clean/posteriors/
    python benchmarks/paper_mesh.py table --run "unscaled PCA, latent GP=out/paper_mixed_noise_latent_long" \
        --run "standardised PCA=benchmarks/results/paper_mesh/noise_paper_mesh" \
        --results benchmarks/results/paper_mesh_mixed_noise_cases
    python benchmarks/paper_mesh.py coverage --study out/paper_mixed_noise_latent_long \
        --results benchmarks/results/paper_mesh_mixed_noise_cases
    python benchmarks/paper_mesh.py coverage --study out/paper_mixed_clean20 \
        --results benchmarks/results/paper_mesh_mixed_noise_cases/clean_20_materials
    python benchmarks/paper_mesh.py noise-weights --study out/paper_mixed_noise_latent_long \
        --cases s1 s5 s10 m1 m5 m10 l1 l5 l10 --results benchmarks/results/paper_mesh_mixed_noise_cases
    # 11. step 10's study with the default error model (the parameter shift, `shift`): the same cases in
    #     the same order, so with the same noise seeds
    skinid study noise --data out/paper_mixed.h5 --designs 0 --gp-fraction 0.7 --restarts 0 --warmup 300 \
        --draws 300 --materials 3,5,8,9,23,24,30,36,44,55 --lengths 5.0 1.0 0.1 --levels 0.01 0.1 0.05 \
        --pca-scaling none --n-components 5 --out out/paper_mixed_noise_shift
    python benchmarks/paper_mesh.py table --run "shift=out/paper_mixed_noise_shift" \
        --run "on=benchmarks/results/paper_mesh_mixed_noise_cases/noise_paper_mesh_mixed_noise_cases" \
        --results benchmarks/results/paper_mesh_mixed_shift
    python benchmarks/paper_mesh.py coverage --study out/paper_mixed_noise_shift \
        --results benchmarks/results/paper_mesh_mixed_shift

The table gives, per noise case and parameter, the median width of the 95 % interval as a share
of the prior range and the coverage of the truth over the test materials, with the sha256 of the
data each run came from. ``coverage`` reads every posterior of a noise study again and gives, per
noise case and pooled, the coverage of the central 50 % and 95 % intervals and the truth's ranks
(as ``skinid study coverage``); of a study with the clean case alone, the clean case's.
``noise-weights`` gives the sd of each case's added noise on each PC weight over its amplitude: 1
for white noise, more where a correlated noise lies along the smooth leading PCs.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from inference.studies import NoiseCase

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "paper_mesh"
PARAMS = ("mu", "k1", "k2", "kappa", "theta")
SYMBOLS = {"mu": "μ", "k1": "k₁", "k2": "k₂", "kappa": "κ", "theta": "θ"}


def grid_subset(xy: np.ndarray, every: int) -> np.ndarray:
    """Indices of the cells on every ``every``-th row and column of a structured in-plane grid.

    Args:
        xy: (n_cells, 2) cell centres [mm] of a tensor-product (graded) grid.
        every: keep one row (column) in ``every``, spread symmetrically over the grid.
    Returns:
        (n_kept,) sorted cell indices.
    """
    columns = [np.unique(np.round(xy[:, k], 6)) for k in range(2)]
    if len(columns[0]) * len(columns[1]) != len(xy):
        raise ValueError(
            f"the {len(xy)} cells are not a tensor-product grid "
            f"({len(columns[0])} x {len(columns[1])} distinct centres)"
        )
    kept = [c[np.unique(np.round(np.linspace(0, len(c) - 1, -(-len(c) // every))).astype(int))] for c in columns]
    on_x = np.isin(np.round(xy[:, 0], 6), kept[0])
    on_y = np.isin(np.round(xy[:, 1], 6), kept[1])
    return np.flatnonzero(on_x & on_y)


def write_subset(data_path: Path, cells: np.ndarray, out: Path) -> Path:
    """A copy of a dataset holding only ``cells`` (same materials, designs, frames, status)."""
    from skinfem.io import StrainDataset, copy_simulations, create_dataset
    from skinfem.outputs import write_atomically

    data = StrainDataset.open(data_path)

    def write(tmp: Path) -> None:
        create_dataset(
            tmp,
            data.config,
            data.params,
            data.designs,
            data.t,
            data.xy[cells],
            data.volume[cells],
            data.split,
            f"{data.mesh_sha256}:cells{len(cells)}",
            bounds=np.stack([data.lower, data.upper], 1),
            versions=data.versions,
            added_noise=data.added_noise,
        )
        copy_simulations(data, tmp, lambda i: data.strain(i)[:, :, cells])

    return write_atomically(out, write)


@dataclass(frozen=True)
class StudyRun:
    """One noise study's results (``noise_study.json``, its cases by name) under a label."""

    label: str
    folder: Path
    results: dict[str, NoiseCase]

    @classmethod
    def read(cls, spec: str) -> StudyRun:
        from inference.studies import read_noise_study

        label, _, folder = spec.partition("=")
        path = Path(folder) / "noise_study.json"
        if not label or not path.is_file():
            raise SystemExit(f"--run must be LABEL=FOLDER with FOLDER/noise_study.json, got '{spec}'")
        return cls(label, Path(folder), read_noise_study(path))

    def cell(self, case: str, name: str) -> str:
        """'width / coverage' of one parameter in one case, or '—' when the run lacks the case."""
        if case not in self.results:
            return "—"
        study = self.results[case].study
        return f"{study.median_interval_share_of_prior[name]:.2f} / {study.coverage_95[name]:.0%}"

    def identified(self, case: str) -> str:
        if case not in self.results:
            return "—"
        names = [SYMBOLS[n] for n in PARAMS if self.results[case].study.identified[n]]
        return ", ".join(names) or "none"


def side_by_side(runs: list[StudyRun]) -> str:
    """Markdown table: per case, the identified parameters and each run's width / coverage."""
    cases = list(dict.fromkeys(c for run in runs for c in run.results))
    lines = [
        "| case | run | " + " | ".join(SYMBOLS[n] for n in PARAMS) + " | identified |",
        "|---|---|" + "---|" * (len(PARAMS) + 1),
    ]
    for case in cases:
        for run in runs:
            if case in run.results:
                lines.append(
                    f"| {case} | {run.label} | "
                    + " | ".join(run.cell(case, n) for n in PARAMS)
                    + f" | {run.identified(case)} |"
                )
    return "\n".join(lines)


def study_cases(folder: Path) -> dict[str, list]:
    """Per noise case of a study folder: a :class:`inference.coverage.CaseResult` per test material,
    from its ``posterior.nc`` (draws, divergences) and ``summary.json`` (truth, prior)."""
    import arviz as az

    from inference.coverage import case_result
    from inference.posterior_file import PosteriorSummary

    cases = {}
    for case in sorted(p for p in (folder / "cases").iterdir() if (p / "posteriors").is_dir()):
        results = []
        for material in sorted(m.parent for m in (case / "posteriors").glob("material_*/summary.json")):
            summary = PosteriorSummary.load(material / "summary.json")
            tree = az.from_netcdf(material / "posterior.nc")
            draws = np.stack([tree.posterior[n].values.reshape(-1) for n in PARAMS], 1)
            truth = np.array([summary.parameters[n].true for n in PARAMS])
            bounds = np.array([summary.parameters[n].prior for n in PARAMS])
            results.append(case_result(draws, truth, bounds, int(tree.sample_stats["diverging"].values.sum())))
        cases[case.name] = results
    return cases


def noisy_truths(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(truths (n, 5), prior bounds (n, 5, 2)) of the distinct test materials of a noise study's
    noisy cases (of its clean case if it has no other), from their posteriors' ``summary.json``."""
    from inference.posterior_file import PosteriorSummary

    paths = list(folder.glob("cases/*/posteriors/material_*/summary.json"))
    noisy = {p.parents[2].name for p in paths} != {"clean"}
    materials = {}
    for path in paths:
        if path.parents[2].name != "clean" or not noisy:
            summary = PosteriorSummary.load(path)
            materials[path.parent.name] = (
                [summary.parameters[n].true for n in PARAMS],
                [summary.parameters[n].prior for n in PARAMS],
            )
    truths, bounds = zip(*materials.values())
    return np.array(truths), np.array(bounds)


def prior_alone(truths: np.ndarray, bounds: np.ndarray) -> list:
    """What posteriors equal to the uniform prior (``bounds`` (n, 5, 2)) would cover for these
    ``truths`` (n, 5): a :class:`inference.coverage.CaseResult` per material. With a handful of
    materials and a prior-dominated parameter, the coverage of the central 50 % interval is the
    share of the materials in the prior's central half."""
    from inference.coverage import case_result

    uniform = [np.linspace(b[:, 0], b[:, 1], 4001) for b in bounds]  # the prior's quantiles as draws
    return [case_result(draws, t, b, 0) for draws, t, b in zip(uniform, truths, bounds)]


def coverage_table(cases: dict[str, list], prior: list | None = None) -> tuple[str, dict]:
    """Markdown table and JSON record of the 50 % / 95 % coverage per case, pooled over the noisy
    ones, and (``prior``: :func:`prior_alone`, if given) of the prior itself for the same materials."""
    pooled = [r for name, results in cases.items() if name != "clean" for r in results]
    rows, record = [], {}
    for name, results in {**cases, "all noisy cases": pooled, "prior alone": prior or []}.items():
        if not results:
            continue
        c50 = np.mean([r.covered_50 for r in results], axis=0)
        c95 = np.mean([r.covered_95 for r in results], axis=0)
        record[name] = {
            "n": len(results),
            "coverage_50": dict(zip(PARAMS, c50.round(3).tolist())),
            "coverage_95": dict(zip(PARAMS, c95.round(3).tolist())),
        }
        rows.append(f"| {name} | {len(results)} | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in zip(c50, c95)) + " |")
    header = ["| case | n | " + " | ".join(SYMBOLS[n] for n in PARAMS) + " |", "|---|---|" + "---|" * len(PARAMS)]
    return "\n".join(header + rows), record


def noise_on_weights(folder: Path, case: str, draws: int = 400, seed: int = 0) -> dict:
    """The sd of a noise case's noise on each PC weight of its emulator, and that sd over the noise
    amplitude (1 for white noise: an orthonormal basis keeps its variance), from ``draws`` fresh
    fields of the case's noise (its length and amplitude; independent of the noise the PCA saw)."""
    from inference.noise import correlation_factor, noise_fields
    from skinfem.io import COMPONENTS, StrainDataset
    from surrogate.emulator import Emulator

    noisy = StrainDataset.open(folder / "cases" / case / "data.h5")
    emulator = Emulator.load(folder / "cases" / case / "emulator")
    noise = noisy.added_noise
    amplitude = np.asarray(noise.amplitude)
    fields = noise_fields(
        correlation_factor(noisy.xy, noise.length_mm), amplitude, (draws,), np.random.default_rng(seed)
    )
    weights = emulator.weights_of_fields(emulator.dataset_fields(np.concatenate([fields, 0 * fields[:1]])))
    sd = (weights[:-1] - weights[-1]).std(0)  # the weights' map is affine: minus the zero field's
    record = {"length_mm": noise.length_mm, "level": noise.level, "draws": draws}
    for c, part in emulator.weight_slices().items():
        ratio = sd[part] / amplitude[COMPONENTS.index(c)]
        record[c] = {"sd": sd[part].tolist(), "sd_over_amplitude": ratio.round(2).tolist()}
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("subset", help="the dataset on every n-th row and column of its cells")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--every", type=int, default=4)
    p.add_argument("--out", type=Path, required=True)
    p = sub.add_parser("table", help="side-by-side table of noise studies")
    p.add_argument("--run", action="append", required=True, help="LABEL=FOLDER (repeat)")
    p.add_argument("--results", type=Path, default=RESULTS)
    p = sub.add_parser("coverage", help="50 / 95 % coverage and truth ranks of a noise study's posteriors")
    p.add_argument("--study", type=Path, required=True)
    p.add_argument("--results", type=Path, default=RESULTS)
    p = sub.add_parser("noise-weights", help="the sd of each noise case's noise on its emulator's PC weights")
    p.add_argument("--study", type=Path, required=True)
    p.add_argument("--cases", nargs="+", required=True)
    p.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.command == "noise-weights":
        record = {case: noise_on_weights(args.study, case) for case in args.cases}
        args.results.mkdir(parents=True, exist_ok=True)
        (args.results / "noise_on_weights.json").write_text(json.dumps(record, indent=2) + "\n")
        for case, r in record.items():
            print(case, {c: r[c]["sd_over_amplitude"] for c in ("xx", "yy")})
        return
    if args.command == "subset":
        from skinfem.io import StrainDataset

        if args.out.exists():
            raise SystemExit(f"'{args.out}' exists: remove it first")
        cells = grid_subset(StrainDataset.open(args.data).xy, args.every)
        write_subset(args.data, cells, args.out)
        print(f"wrote {args.out}: {len(cells)} cells")
        return
    if args.command == "coverage":
        from inference.coverage import rank_histograms

        cases = study_cases(args.study)
        table, record = coverage_table(cases, prior_alone(*noisy_truths(args.study)))
        args.results.mkdir(parents=True, exist_ok=True)
        (args.results / "coverage.json").write_text(json.dumps({"study": str(args.study), **record}, indent=1) + "\n")
        noisy = np.array([r.rank for name, results in cases.items() if name != "clean" for r in results])
        if len(noisy):
            rank_histograms(noisy, args.results / "ranks_noise_cases.png", f"noise cases: {len(noisy)} posteriors")
        print(table)
        return
    from skinfem.mesh import file_sha256

    runs = [StudyRun.read(spec) for spec in args.run]
    args.results.mkdir(parents=True, exist_ok=True)
    sources = {}
    for run in runs:
        data = next(iter(run.results.values())).data
        sources[run.label] = {
            "folder": str(run.folder),
            "data": data,
            "data_sha256": file_sha256(data) if data and Path(data).is_file() else None,
        }
    table = side_by_side(runs)
    (args.results / "side_by_side.md").write_text(
        "Median width of the 95 % interval as a share of the prior range / coverage of the truth over "
        "the test materials (last frame of each run's design).\n\n" + table + "\n"
    )
    (args.results / "sources.json").write_text(json.dumps(sources, indent=2) + "\n")
    print(table)


if __name__ == "__main__":
    main()
