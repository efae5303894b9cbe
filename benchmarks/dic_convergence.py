"""Convergence of what the check compares: the DIC surface strain at scattered points.

    python benchmarks/dic_convergence.py [meshes | refinements | edge | paper | finer | graded]
        [--out benchmarks/results/dic_convergence.json]

One material (mu 1.2e-3 MPa, k1 0.017 MPa, k2 11, kappa 0.285, theta 30 deg), the mixed design
(0.05, -0.05) at t = 1, measured by the DIC operator (1 mm window) at a DIC-like point cloud
over +-20 mm (1 mm step, jitter, 3 holes). Meshes around the ``small`` preset: in-plane size
under the membrane / far (mm), skin layers s, muscle layers m, Q1 or Q2 elements. Each field
is compared with the finest (Q2, 2/3 mm, s2, m4): relative RMS difference over all points and
in bands of max(|x|, |y|) (under the membrane < 8 mm, the edge band 8-12 mm, far field
> 12 mm). Seconds: the second simulation of a model (forms compiled, mesh cached), 1 rank.

``refinements``: from the quadratic check mesh (Q2, 2/6 mm, s2 m2), how much the field moves
when only the layers through the thickness are doubled and when only the in-plane sizes are
halved — which refinement a two-mesh estimate of its error must make (seconds: one
simulation). ``edge``: series refined only at the membrane edge (``mesh.h_edge``), each field
compared with the previous one in its series. ``paper``: the paper preset's error per region
against a Richardson-extrapolated quadratic reference, and whether each observable converges
through the thickness (the DIC surface strain, and the average over the top layer of skin cells
that the datasets hold). ``finer``: the same Q2 series one edge halving further (0.25 mm), so
that the limit is extrapolated from edge cells 1, 0.5 and 0.25 mm and the 0.5 mm mesh (the
``converged`` preset, the check's ``converged`` reference) is measured against a limit it is not
the finest member of; with a 0.35 mm candidate. ``graded``: edge cells that double away from
the edge (``mesh.edge_growth`` = 2) at 0.25, 0.125 and 0.0625 mm, against the ``finer`` limit and
against their own, and 0.125 mm ones with far cells of 2 and 2.5 mm or growing by 1.5 and 1.4;
the ``check`` preset's mesh and graded versions of it, one with its muscle layers doubled (4 -> 8).
The parts are merged into the same file. Numbers are recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
PARAMS = (1.2e-3, 0.017, 11.0, 0.285, 30.0)
BANDS = {"under the membrane (< 8 mm)": (0, 8), "edge band (8-12 mm)": (8, 12), "far field (> 12 mm)": (12, 99)}
MESHES = [  # (degree, h_membrane, h_far, skin_layers, muscle_layers)
    (1, 2, 6, 1, 2),
    (1, 2, 6, 1, 4),
    (1, 2, 3, 1, 2),
    (1, 2, 6, 2, 2),
    (1, 1, 3, 2, 4),
    (1, 2, 3, 2, 4),
    (2, 2, 6, 1, 2),
    (2, 2, 4, 1, 3),
    (2, 2, 4, 2, 3),
    (2, 2, 3, 2, 4),
]


EDGE_SERIES = [  # (degree, h_membrane, h_far, skin_layers, muscle_layers, h_edge)
    [(2, 2, 6, 2, 2, 0.0), (2, 2, 6, 2, 2, 1.0), (2, 2, 6, 2, 2, 0.5)],
    [(1, 2, 6, 2, 2, 0.0), (1, 2, 6, 2, 2, 0.5), (1, 2, 6, 2, 2, 0.25), (1, 2, 6, 4, 4, 0.25)],
]
REFINEMENTS = {
    "base": (2, 2, 6, 2, 2),
    "layers doubled": (2, 2, 6, 4, 4),
    "skin layers doubled": (2, 2, 6, 4, 2),
    "muscle layers doubled": (2, 2, 6, 2, 4),
    "in-plane halved": (2, 1, 3, 2, 2),
}


def label(mesh) -> str:
    degree, hm, hf, s, m, *edge = mesh
    text = f"Q{degree} {hm:g}/{hf:g} mm, s{s} m{m}" + (f", edge {edge[0]:g} mm" if edge and edge[0] else "")
    return text + (f" growth {edge[1]:g}" if len(edge) > 1 else "")


def measure(mesh, xy, mesh_dir, warm: bool = True, cells: bool = False):
    """DIC strain (n, 3) at xy, seconds of one simulation (after a first one if ``warm``), dofs;
    with ``cells`` also the top skin cells' average log strain (n_cells, 3) and their centroids."""
    from skinfem.config import load_config
    from skinfem.dic import StrainGauge, SurfaceStrainGauge
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    degree, hm, hf, s, m, *edge = mesh
    h_edge, growth = (*edge, 0.0, 0.0)[:2]
    config = load_config("small").with_changes(
        mesh={
            "h_membrane": hm,
            "h_far": hf,
            "skin_layers": s,
            "muscle_layers": m,
            "h_edge": h_edge,
            "edge_growth": growth,
        },
        solver={"increments": 2, "element_degree": degree, "quadrature_degree": 2 * degree},
        observable={"kind": "top_cell_average"},
    )
    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir)
    gauge = SurfaceStrainGauge(model.u, xy, StrainGauge(1.0))
    if warm:
        model.simulate(SkinParams(*PARAMS), Design(0.05, -0.05))
    start = time.perf_counter()
    frames = model.simulate(SkinParams(*PARAMS), Design(0.05, -0.05))
    seconds = time.perf_counter() - start
    if cells:
        return gauge(), seconds, model.n_dofs, (frames.strain[-1], frames.xy)
    return gauge(), seconds, model.n_dofs


def main() -> None:
    from inference.synthetic import dic_points

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "part", nargs="?", choices=["meshes", "refinements", "edge", "paper", "finer", "graded"], default="meshes"
    )
    parser.add_argument("--out", type=Path, default=HERE / "results" / "dic_convergence.json")
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument(
        "--store",
        type=Path,
        default=Path("out/dic_convergence"),
        help="finished meshes of the paper part, kept so that a killed run resumes",
    )
    args = parser.parse_args()
    xy = dic_points(20.0, 1.0, np.random.default_rng(0))
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    if args.part == "refinements":
        result["refinements"] = refinements(xy, args.mesh_dir)
    elif args.part == "edge":
        result["edge"] = edge_series(xy, args.mesh_dir)
    elif args.part == "paper":
        result["paper"] = paper_errors(xy, args.mesh_dir, args.store)
    elif args.part in ("finer", "graded"):
        result[args.part] = (finer_errors if args.part == "finer" else graded_errors)(xy, args.mesh_dir, args.store)
        if MPI.COMM_WORLD.rank:
            return
    else:
        result.update(meshes(xy, args.mesh_dir))
    args.out.write_text(json.dumps(result, indent=2) + "\n")


def band_changes(field, previous, xy) -> dict[str, float]:
    """Relative RMS of field - previous, over all points and per band."""
    diff, ring = field - previous, np.max(np.abs(xy), axis=1)
    out = {"all points": float(np.sqrt(np.mean(diff**2) / np.mean(previous**2)))}
    for band, (lo, hi) in BANDS.items():
        sel = (ring >= lo) & (ring < hi)
        out[band] = float(np.sqrt(np.mean(diff[sel] ** 2) / np.mean(previous[sel] ** 2)))
    return out


def edge_series(xy, mesh_dir) -> dict:
    """Each mesh of EDGE_SERIES against the previous one of its series."""
    series = []
    for meshes in EDGE_SERIES:
        rows, previous = [], None
        for mesh in meshes:
            field, seconds, dofs = measure(mesh, xy, mesh_dir, warm=False)
            row = {"mesh": label(mesh), "dofs": dofs, "seconds": round(seconds, 1)}
            if previous is not None:
                row["change_from_previous"] = band_changes(field, previous, xy)
            rows.append(row)
            previous = field
            print(row, flush=True)
        series.append(rows)
    return {"command": "python benchmarks/dic_convergence.py edge", "series": series}


def refinements(xy, mesh_dir) -> dict:
    """How far each one-directional refinement of the Q2 check mesh moves the field."""
    fields, seconds, dofs = {}, {}, {}
    for name, mesh in REFINEMENTS.items():
        fields[name], seconds[name], dofs[name] = measure(mesh, xy, mesh_dir, warm=False)
        print(name, seconds[name], flush=True)
    base = fields["base"]
    ring = np.max(np.abs(xy), axis=1)
    rows = []
    for name in list(REFINEMENTS)[1:]:
        diff = fields[name] - base
        row = {
            "refinement": name,
            "mesh": label(REFINEMENTS[name]),
            "dofs": dofs[name],
            "seconds": round(seconds[name], 1),
            "relative_rms_change": float(np.sqrt(np.mean(diff**2) / np.mean(base**2))),
        }
        for band, (lo, hi) in BANDS.items():
            sel = (ring >= lo) & (ring < hi)
            row[band] = float(np.sqrt(np.mean(diff[sel] ** 2) / np.mean(base[sel] ** 2)))
        rows.append(row)
        print(row, flush=True)
    return {
        "command": "python benchmarks/dic_convergence.py refinements",
        "base": label(REFINEMENTS["base"]),
        "base_seconds": round(seconds["base"], 1),
        "base_dofs": dofs["base"],
        "rows": rows,
    }


PAPER = (1, 0.5, 2.8, 1, 5, 0.0)
PAPER_SKIN_LAYERS = [PAPER, (1, 0.5, 2.8, 2, 5, 0.0), (1, 0.5, 2.8, 4, 5, 0.0)]
PAPER_REFERENCE = [(2, 2, 4, 2, 4, 0.0), (2, 2, 4, 2, 4, 1.0), (2, 2, 4, 2, 4, 0.5)]
PAPER_CANDIDATES = [(1, 0.5, 2.8, 4, 5, 0.25), (2, 2, 4, 3, 4, 1.0), (2, 2, 4, 2, 8, 1.0)]
FINER_REFERENCE = [*PAPER_REFERENCE[1:], (2, 2, 4, 2, 4, 0.25)]
FINER_CANDIDATES = [(2, 2, 4, 2, 4, 0.35)]
GRADED_SERIES = [(2, 2, 4, 2, 4, h, 2.0) for h in (0.25, 0.125, 0.0625)]  # mesh.edge_growth = 2
GRADED_CANDIDATES = [  # smaller far cells; slower growth
    *[(2, 2, hf, 2, 4, 0.125, 2.0) for hf in (2.0, 2.5)],
    *[(2, 2, 4, 2, 4, 0.125, growth) for growth in (1.5, 1.4)],
]
CHECK_CANDIDATES = [  # the `check` preset's mesh (far cells 6 mm, two muscle layers) and graded ones
    (2, 2, 6, 2, 2, 1.0),
    (2, 2, 6, 2, 2, 0.25, 2.0),
    (2, 2, 6, 2, 2, 0.125, 1.5),
    (2, 2, 6, 2, 4, 0.25, 2.0),
    (2, 2, 6, 2, 8, 0.25, 2.0),  # muscle layers doubled, as the check's refinement does
]


def richardson(coarse, medium, fine) -> tuple[np.ndarray, float]:
    """Extrapolated field and observed order from three fields at halving mesh sizes: the order
    from the RMS changes, the limit of the two finer ones at that order."""
    from inference.criticism.discretisation import richardson_limit

    ratio = np.sqrt(np.mean((medium - coarse) ** 2) / np.mean((fine - medium) ** 2))
    order = float(np.log2(ratio))
    return richardson_limit(medium, fine, order), order


def measure_resumable(mesh, xy, mesh_dir, store: Path):
    """``measure(..., cells=True)`` whose result is kept in ``store`` (one .npz per mesh), so that a
    killed run resumes at the first mesh it had not finished."""
    path = store / (label(mesh).replace(" ", "_").replace("/", "-").replace(",", "") + ".npz")
    if not path.exists():
        field, seconds, dofs, (cell_strain, cell_xy) = measure(mesh, xy, mesh_dir, warm=False, cells=True)
        store.mkdir(parents=True, exist_ok=True)
        np.savez(
            path.with_suffix(".part.npz"),
            field=field,
            seconds=seconds,
            dofs=dofs,
            cell_strain=cell_strain,
            cell_xy=cell_xy,
        )
        path.with_suffix(".part.npz").replace(path)
    with np.load(path) as f:
        return f["field"], float(f["seconds"]), int(f["dofs"]), (f["cell_strain"], f["cell_xy"])


def against_richardson(meshes, series, xy, mesh_dir, store: Path):
    """Each mesh's DIC field (``measure_resumable``) and its error per region against the
    Richardson extrapolation of ``series`` (three of the meshes at halving edge cells).
    Returns (the results' common part: reference, order, field RMS, rows; surface fields,
    top-cell fields; the extrapolated reference field)."""
    surface, cells, rows = {}, {}, []
    for mesh in meshes:
        surface[mesh], seconds, dofs, cells[mesh] = measure_resumable(mesh, xy, mesh_dir, store)
        rows.append({"mesh": label(mesh), "dofs": dofs, "seconds": round(seconds, 1)})
        print(rows[-1], flush=True)
    reference, order = richardson(*(surface[m] for m in series))
    for row, mesh in zip(rows, meshes):
        row["error_vs_reference"] = band_changes(surface[mesh], reference, xy)
        print(row["mesh"], {k: round(v, 4) for k, v in row["error_vs_reference"].items()}, flush=True)
    summary = {
        "reference": "Richardson extrapolation of " + ", ".join(label(m) for m in series),
        "observed_order": order,
        "field_rms": float(np.sqrt(np.mean(reference**2))),
        "meshes": rows,
    }
    return summary, surface, cells, reference


def paper_errors(xy, mesh_dir, store: Path) -> dict:
    """The paper preset and its refinements against a Richardson-extrapolated Q2 reference
    (edge cells 2, 1, 0.5 mm); the skin-layer series compares both observables."""
    meshes = [*PAPER_SKIN_LAYERS, *PAPER_REFERENCE, *PAPER_CANDIDATES]
    summary, surface, cells, _ = against_richardson(meshes, PAPER_REFERENCE, xy, mesh_dir, store)
    layers = []
    for previous, mesh in zip(PAPER_SKIN_LAYERS, PAPER_SKIN_LAYERS[1:]):
        layers.append(
            {
                "from": label(previous),
                "to": label(mesh),
                "surface_strain": band_changes(surface[mesh], surface[previous], xy),
                "top_cell_average": band_changes(cells[mesh][0], cells[previous][0], cells[mesh][1]),
            }
        )
        print(layers[-1], flush=True)
    return {"command": "python benchmarks/dic_convergence.py paper", **summary, "skin_layers": layers}


SECONDS_ACROSS_RANKS = "one simulation on one rank, the other rank simulating another mesh"


def across_ranks(meshes, series, xy, mesh_dir, store: Path):
    """:func:`against_richardson` after each rank has simulated every size-th mesh into ``store``
    (one simulation per rank at a time)."""
    comm = MPI.COMM_WORLD
    for mesh in meshes[comm.rank :: comm.size]:
        measure_resumable(mesh, xy, mesh_dir, store)
    comm.Barrier()
    return against_richardson(meshes, series, xy, mesh_dir, store)


def finer_errors(xy, mesh_dir, store: Path) -> dict:
    """The paper preset, the Q2 series with edge cells 1, 0.5, 0.25 mm and the candidates against
    the Richardson extrapolation of that series, and each member's change from the previous one.
    Under mpirun each rank first simulates every size-th mesh (one rank each) into ``store``."""
    summary, surface, _, _ = across_ranks(
        [PAPER, *FINER_REFERENCE, *FINER_CANDIDATES], FINER_REFERENCE, xy, mesh_dir, store
    )
    changes = [
        {"from": label(a), "to": label(b), "change": band_changes(surface[b], surface[a], xy)}
        for a, b in zip(FINER_REFERENCE, FINER_REFERENCE[1:])
    ]
    return {
        "command": "mpirun -n 2 python benchmarks/dic_convergence.py finer",
        "seconds_note": SECONDS_ACROSS_RANKS,
        **summary,
        "series_changes": changes,
    }


def graded_errors(xy, mesh_dir, store: Path) -> dict:
    """Edge cells that double away from the membrane edge (``mesh.edge_growth`` = 2; 0.25, 0.125,
    0.0625 mm) against two limits: the Richardson extrapolation of the ``finer`` series (edge
    cells 1, 0.5, 0.25 mm, one progression per side) and that of the graded series itself —
    two routes to the same limit where the far cells are the same —, and candidates with smaller
    far cells or a slower growth, and the ``check`` preset's mesh with graded versions of it.
    Under mpirun each rank simulates every size-th mesh."""
    meshes = [PAPER, *FINER_REFERENCE, *GRADED_SERIES, *GRADED_CANDIDATES, *CHECK_CANDIDATES]
    summary, surface, _, finer_limit = across_ranks(meshes, FINER_REFERENCE, xy, mesh_dir, store)
    graded_limit, graded_order = richardson(*(surface[m] for m in GRADED_SERIES))
    for row, mesh in zip(summary["meshes"], meshes):
        row["error_vs_graded_limit"] = band_changes(surface[mesh], graded_limit, xy)
    return {
        "command": "mpirun -n 2 python benchmarks/dic_convergence.py graded",
        "seconds_note": SECONDS_ACROSS_RANKS,
        **summary,
        "graded_reference": "Richardson extrapolation of " + ", ".join(label(m) for m in GRADED_SERIES),
        "graded_observed_order": graded_order,
        "limits_differ_by": band_changes(graded_limit, finer_limit, xy),
        "muscle_layers_4_to_8": band_changes(surface[CHECK_CANDIDATES[-1]], surface[CHECK_CANDIDATES[-2]], xy),
    }


def meshes(xy, mesh_dir) -> dict:
    """Every mesh of MESHES against the finest."""
    fields, rows = {}, []
    for mesh in MESHES:
        fields[mesh], seconds, dofs = measure(mesh, xy, mesh_dir)
        rows.append({"mesh": label(mesh), "dofs": dofs, "seconds": round(seconds, 2)})
        print(rows[-1], flush=True)
    reference = fields[MESHES[-1]]
    ring = np.max(np.abs(xy), axis=1)
    for row, mesh in zip(rows, MESHES):
        diff = fields[mesh] - reference
        row["relative_rms_vs_finest"] = float(np.sqrt(np.mean(diff**2) / np.mean(reference**2)))
        row["absolute_rms_vs_finest"] = float(np.sqrt(np.mean(diff**2)))
        for name, (lo, hi) in BANDS.items():
            sel = (ring >= lo) & (ring < hi)
            row[name] = float(np.sqrt(np.mean(diff[sel] ** 2) / np.mean(reference[sel] ** 2)))
    for row in rows:
        print(
            f"{row['mesh']:>20}: {row['relative_rms_vs_finest']:.3f} "
            + " ".join(f"{row[b]:.3f}" for b in BANDS)
            + f"  {row['seconds']} s, {row['dofs']} dofs"
        )
    return {
        "command": "python benchmarks/dic_convergence.py",
        "points": len(xy),
        "window_mm": 1.0,
        "reference": label(MESHES[-1]),
        "field_rms": float(np.sqrt(np.mean(reference**2))),
        "meshes": rows,
    }


if __name__ == "__main__":
    main()
