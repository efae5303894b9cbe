"""Which design and which observable inform which skin parameter: the fields' Fisher information.

    mpirun -n 2 python benchmarks/design_information.py [--config paper] [--materials 3,5]
        [--designs max=0.05,0.05 mixed=0.05,-0.05 uniaxial=0.05,0] [--noise-sd 1e-3]
        [--out out/design_information] [--results benchmarks/results/design_information.json]

The paper-mesh noise studies (benchmarks/paper_mesh.py) found the "mixed" design informing more
than the "max" design, and the surface strain a camera sees informing θ less than the paper
reports for its cell-average strain. This measures why, without an emulator: for each material
(indices into the configuration's sweep; ``centre``: the prior box's centre) and single design,
the last frame's field is differentiated with respect to the five skin parameters by forward
differences of whole simulations (step: ``--step`` × each parameter's prior range), observed
both ways from the same solutions — the skin surface strain at each top cell's centre
(``observable.kind = "surface"``, skinid's) and the average strain of each top skin cell
(``"top_cell_average"``, the paper's: the mid-thickness strain with one skin layer).

With white noise of sd σ on every cell and component, the linearised (Cramér–Rao) posterior
sd of parameter k is σ sqrt((JᵀJ)⁻¹)_kk; reported as the 95 % width 2 × 1.96 sd over the prior
range — the linearised counterpart of the noise studies' widths (above ~1 the data do not
inform the parameter and the prior sets the width) — and the share of each region's cells in
the parameter's information diagonal (JᵀJ)_kk: under the membrane (max(|x|, |y|) < 8 mm), the
8–12 mm band around its edge, the far field. Each (material, design) is solved on one rank
(6 simulations) and kept in ``--out`` (a rerun reads it). Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
PARAMS = ("mu", "k1", "k2", "kappa", "theta")
OBSERVABLES = ("surface", "top_cell_average")
REGIONS = {"under the membrane": (0.0, 8.0), "edge band 8-12 mm": (8.0, 12.0), "far field": (12.0, np.inf)}


@dataclass(frozen=True)
class Information:
    """The linearised information of one field about the skin parameters.

    Attributes:
        width_95: 95 % Cramér–Rao width / prior range per parameter from the whole field
            (E_xx, E_yy, E_xy of every cell; white noise of ``noise_sd``).
        width_95_xx_yy: the same from E_xx and E_yy only (the emulators' components).
        region_share: per region, its share of each parameter's information diagonal (whole field).
        noise_sd: σ of the white noise on every cell and component [-].
    """

    width_95: dict[str, float]
    width_95_xx_yy: dict[str, float]
    region_share: dict[str, dict[str, float]]
    noise_sd: float


def widths(fisher: np.ndarray) -> dict[str, float]:
    """95 % Cramér–Rao widths 2 × 1.96 sqrt(diag(F⁻¹)) per parameter of a Fisher matrix (5, 5)."""
    return dict(zip(PARAMS, (2 * 1.96 * np.sqrt(np.diag(np.linalg.inv(fisher)))).tolist(), strict=True))


def information(jacobian: np.ndarray, ring: np.ndarray, prior_range: np.ndarray, noise_sd: float) -> Information:
    """The Cramér–Rao widths and regional shares of a field's Jacobian.

    Args:
        jacobian: (n_cells, 3, 5) d strain / d parameter [per unit of each parameter].
        ring: (n_cells,) max(|x|, |y|) of each cell centre [mm].
        prior_range: (5,) width of each parameter's prior box [its units].
        noise_sd: white noise sd on every cell and component [-].
    """
    scaled = jacobian * prior_range  # per prior range: the widths come out as shares of it
    flat, xx_yy = scaled.reshape(-1, len(PARAMS)), scaled[:, :2].reshape(-1, len(PARAMS))
    diagonal = np.einsum("nck,nck->k", scaled, scaled)
    share = {
        name: dict(zip(PARAMS, (np.einsum("nck,nck->k", scaled[mask], scaled[mask]) / diagonal).tolist(), strict=True))
        for name, (low, high) in REGIONS.items()
        if (mask := (ring >= low) & (ring < high)).any()
    }
    return Information(
        width_95=widths(flat.T @ flat / noise_sd**2),
        width_95_xx_yy=widths(xx_yy.T @ xx_yy / noise_sd**2),
        region_share=share,
        noise_sd=noise_sd,
    )


def last_fields(model, cell_average, params, design) -> dict[str, np.ndarray]:
    """The last frame's (n_cells, 3) surface strain and cell-average strain of one simulation."""
    seen = {}

    def at_last_frame(t: float) -> None:
        if t == 1.0:
            seen["top_cell_average"] = cell_average()

    frames = model.simulate(params, design, on_frame=at_last_frame)
    return {"surface": frames.strain[-1], **seen}


def jacobians(model, cell_average, x: np.ndarray, bounds: np.ndarray, design, step: float):
    """Both observables' last fields and forward-difference Jacobians (n_cells, 3, 5) at the
    parameters ``x`` (5,); each step is ``step`` of the prior range ``bounds`` (5, 2), taken
    inward at the box's upper bound."""
    from skinfem.params import SkinParams

    base = last_fields(model, cell_average, SkinParams(*x), design)
    columns = {name: [] for name in OBSERVABLES}
    for k in range(len(PARAMS)):
        h = step * (bounds[k, 1] - bounds[k, 0])
        h = -h if x[k] + h > bounds[k, 1] else h
        moved = last_fields(model, cell_average, SkinParams(*(x + h * np.eye(len(PARAMS))[k])), design)
        for name in OBSERVABLES:
            columns[name].append((moved[name] - base[name]) / h)
    return base, {name: np.stack(columns[name], axis=-1) for name in OBSERVABLES}


def solve_task(config, x: np.ndarray, alpha: tuple[float, float], step: float, path: Path) -> None:
    """Both observables' fields and Jacobians of one (material ``x``, design ``alpha``), on one
    rank, saved to ``path`` (.npz)."""
    from skinfem.fenics import ufl
    from skinfem.mesh import TAGS
    from skinfem.model import SkinModel
    from skinfem.outputs import write_atomically
    from skinfem.params import Design
    from skinfem.strain import SkinStrainSampler, top_skin_cells

    model = SkinModel(config, MPI.COMM_SELF)
    depth = config.mesh.skin_thickness / config.mesh.skin_layers
    cells = top_skin_cells(model.mesh, model.cell_tags, TAGS["skin"], depth)
    grad_u = ufl.Identity(3) + ufl.grad(model.u)
    cell_average = SkinStrainSampler(model.u, cells, config.solver.quadrature_degree, grad_u)
    t0 = time.perf_counter()
    base, jac = jacobians(model, cell_average, x, config.sweep.box, Design(*alpha), step)
    arrays = {f"field_{n}": base[n] for n in OBSERVABLES} | {f"jacobian_{n}": jac[n] for n in OBSERVABLES}
    seconds = time.perf_counter() - t0
    write_atomically(path, lambda tmp: np.savez(tmp, xy=model.strain_sampler.xy, seconds=seconds, **arrays))


def materials(config, spec: str) -> dict[str, np.ndarray]:
    """Named parameter vectors (5,): ``centre`` (of the prior box) or indices into the sweep's materials."""
    from skinfem.sweep import SweepPlan

    plan = SweepPlan.from_config(config)
    return {name: plan.bounds.mean(axis=1) if name == "centre" else plan.params[int(name)] for name in spec.split(",")}


def summarise(config, tasks: dict[tuple[str, str], Path], noise_sd: float) -> dict:
    """Per material, design and observable: the information (:class:`Information`) and the
    field's RMS [-]."""
    box = config.sweep.box
    record: dict = {}
    for (material, design), path in tasks.items():
        with np.load(path) as f:
            ring = np.abs(f["xy"]).max(axis=1)
            for name in OBSERVABLES:
                info = information(f[f"jacobian_{name}"], ring, box[:, 1] - box[:, 0], noise_sd)
                entry = record.setdefault(material, {}).setdefault(design, {})
                entry[name] = {**asdict(info), "field_rms": float(np.sqrt(np.mean(f[f"field_{name}"] ** 2)))}
                entry["seconds"] = float(f["seconds"])
    return record


WIDTHS = {"width_95": "E_xx, E_yy, E_xy", "width_95_xx_yy": "E_xx, E_yy"}


def medians(record: dict) -> dict:
    """Per design and observable: the median over the materials of each parameter's widths and
    of each region's share of its information."""
    designs = next(iter(record.values()))
    out: dict = {}
    for design in designs:
        for name in OBSERVABLES:
            entries = [record[m][design][name] for m in record]
            median = {key: {p: float(np.median([e[key][p] for e in entries])) for p in PARAMS} for key in WIDTHS}
            median["region_share"] = {
                region: {p: float(np.median([e["region_share"][region][p] for e in entries])) for p in PARAMS}
                for region in entries[0]["region_share"]
            }
            out.setdefault(design, {})[name] = median
    return out


def table(summary: dict) -> str:
    """Markdown: the median 95 % Cramér–Rao width / prior range per design, observable and what
    is kept of the field, with the edge band's share of each parameter's information in brackets."""
    header = "| design | observable | kept | " + " | ".join(PARAMS) + " |"
    lines = [header, "|---|---|---|" + "---|" * len(PARAMS)]
    for design, observables in summary.items():
        for name, entry in observables.items():
            band = entry["region_share"].get("edge band 8-12 mm", {})
            for key, kept in WIDTHS.items():
                suffix = {p: f" ({band.get(p, 0.0):.0%})" if key == "width_95" else "" for p in PARAMS}
                cells = " | ".join(f"{entry[key][p]:.3g}{suffix[p]}" for p in PARAMS)
                lines.append(f"| {design} | {name} | {kept} | {cells} |")
    return "\n".join(lines)


def parse_design(spec: str) -> tuple[str, tuple[float, float]]:
    name, _, alpha = spec.partition("=")
    a11, a22 = (float(v) for v in alpha.split(","))
    return name, (a11, a22)


def main() -> None:
    from skinfem.config import load_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="paper")
    parser.add_argument("--materials", default="centre", help="comma-separated: centre and/or sweep indices")
    parser.add_argument("--designs", nargs="+", default=["max=0.05,0.05", "mixed=0.05,-0.05", "uniaxial=0.05,0"])
    parser.add_argument("--step", type=float, default=1e-3, help="difference step / prior range")
    parser.add_argument("--noise-sd", type=float, default=1e-3)
    parser.add_argument("--out", type=Path, default=Path("out/design_information"))
    parser.add_argument("--results", type=Path, default=HERE / "results" / "design_information.json")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    config = load_config(args.config)
    tasks = {
        (m, d): (x, alpha, args.out / f"{args.config}_{m}_{d}.npz")
        for m, x in materials(config, args.materials).items()
        for d, alpha in map(parse_design, args.designs)
    }
    args.out.mkdir(parents=True, exist_ok=True)
    for x, alpha, path in list(tasks.values())[comm.rank :: comm.size]:
        if not path.exists():
            solve_task(config, x, alpha, args.step, path)
    comm.barrier()
    if comm.rank == 0:
        record = summarise(config, {key: path for key, (_, _, path) in tasks.items()}, args.noise_sd)
        results = json.loads(args.results.read_text()) if args.results.exists() else {}
        command = (
            f"mpirun -n {comm.size} python benchmarks/design_information.py --config {args.config} "
            f"--materials {args.materials} --noise-sd {args.noise_sd:g} --step {args.step:g}"
        )
        summary = medians(record)
        results[args.config] = {"command": command, "median_over_materials": summary, "materials": record}
        args.results.write_text(json.dumps(results, indent=2) + "\n")
        print(table(summary))


if __name__ == "__main__":
    main()
