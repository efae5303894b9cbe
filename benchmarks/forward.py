"""Forward-model benchmark: time per simulation, Newton iterations, memory, time breakdown,
and a mesh/element convergence table.

    python benchmarks/forward.py timing [--config paper] [--ranks 1 2] [--refactor-krylov 10 0]
                                        [--repeat 3] [--petsc KEY=VALUE ...] [--label _x]
    python benchmarks/forward.py convergence
    python benchmarks/forward.py tolerance [--config paper] [--results ...]
    python benchmarks/forward.py run-one CONFIG OUT.json   # (internal, under mpirun)

``--refactor-krylov`` values are timed one after another: the default (LU reused as GMRES
preconditioner, refactorised when GMRES needs > 10 iterations per Newton step) and 0 (plain
Newton with a factorisation at every step), recorded as ``timing_<config>_<n>rank`` and
``timing_<config>_<n>rank_refactor0`` (+ ``--label``). Each timing run makes ``--repeat``
simulations with one model, as a sweep does, and keeps the median wall time: this machine's
speed varies by ±15 % from minute to minute. ``--petsc`` adds options to the model's solver
(e.g. ``--petsc mat_mumps_icntl_7=3`` for another ordering) to measure solver levers;
``--results benchmarks/results/forward_levers.json`` keeps such runs apart.

``tolerance`` solves the same simulation with looser Newton (``solver.atol``) and GMRES
(``solver.krylov_rtol``) tolerances on the ranks of COMM_WORLD and records, per pair, the
factorizations, triangular solves, Newton iterations and the largest relative L2 change of a
frame's skin strain against the default tolerances (the bound for an unchanged field:
1e-6); key ``newton_tolerance_<config>``.

Results are merged into benchmarks/results/forward.json. Numbers are recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "forward.json"
PARAMS = dict(mu=1.2e-3, k1=0.017, k2=12.0, kappa=0.28, theta=30.0)
DESIGN = dict(alpha11=0.05, alpha22=-0.05)  # the paper's "mixed" design
EVENTS = {
    "factorization": ("MatLUFactorNum", "MatLUFactorSym"),
    "triangular_solves": ("MatSolve",),
    "jacobian_assembly": ("SNESJacobianEval",),
    "residual_assembly": ("SNESFunctionEval",),
}


def merge_results(key: str, value, results: Path = RESULTS) -> None:
    results.parent.mkdir(parents=True, exist_ok=True)
    data = json.loads(results.read_text()) if results.exists() else {}
    data[key] = value
    results.write_text(json.dumps(data, indent=2) + "\n")


def run_one(config_source: str, out: str, mesh_dir: str, refactor_krylov: int, petsc: list[str], repeat: int) -> None:
    """``repeat`` simulations on the ranks of COMM_WORLD; rank 0 writes timings to ``out``
    (median wall time; breakdown and counts per simulation).

    ``petsc``: extra ``KEY=VALUE`` PETSc options for the model's solver (without its prefix).

    Longer than a screen: the timed runs and the record of every counter, in order.
    """
    import dataclasses

    from mpi4py import MPI

    from skinfem.config import load_config
    from skinfem.fenics import PETSc
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    comm = MPI.COMM_WORLD
    config = load_config(config_source)
    config = dataclasses.replace(config, solver=dataclasses.replace(config.solver, refactor_krylov=refactor_krylov))
    t0 = time.perf_counter()
    model = SkinModel(config, comm, mesh_dir=mesh_dir)
    options = PETSc.Options(model.problem.solver.getOptionsPrefix())
    for item in petsc:
        key, _, value = item.partition("=")
        options[key] = value
    model.problem.solver.setFromOptions()
    setup = time.perf_counter() - t0
    PETSc.Log.begin()
    seconds = []
    for _ in range(repeat):  # the same simulation again: a sweep reuses the model like this
        frames = model.simulate(SkinParams(**PARAMS), Design(**DESIGN))
        seconds.append(frames.seconds)
    t1 = time.perf_counter()
    for _ in range(3):
        model.strain_sampler()
    strain_seconds = (time.perf_counter() - t1) / 3 * len(frames.t)
    breakdown = {}
    for name, events in EVENTS.items():
        breakdown[name] = sum(PETSc.Log.Event(e).getPerfInfo()["time"] for e in events) / repeat
    breakdown = {k: comm.allreduce(v, op=MPI.MAX) for k, v in breakdown.items()}
    breakdown["strain_postprocessing"] = strain_seconds
    breakdown["setup_mesh_read_and_jit"] = setup
    solves = comm.allreduce(PETSc.Log.Event("MatSolve").getPerfInfo()["count"], op=MPI.MAX) // repeat
    peak_mb = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, op=MPI.SUM)
    if comm.rank == 0:
        last = frames.strain[-1]
        Path(out).write_text(
            json.dumps(
                {
                    "config": config.name,
                    "ranks": comm.size,
                    "dofs": model.n_dofs,
                    "skin_cells": len(frames.xy),
                    "seconds_per_simulation": float(np.median(seconds)),
                    "seconds_of_each_repeat": seconds,
                    "newton_iterations_per_increment": frames.newton_iterations,
                    "refactor_krylov": refactor_krylov,
                    "petsc_options": petsc,
                    "factorizations": model.factorizations,
                    "triangular_solves": solves,
                    "cutbacks": frames.cutbacks,
                    "peak_memory_mb_all_ranks": peak_mb,
                    "breakdown_seconds": breakdown,
                    "max_abs_strain_xx_yy": [float(np.abs(last[:, 0]).max()), float(np.abs(last[:, 1]).max())],
                },
                indent=2,
            )
        )


def timing(
    config: str,
    ranks: list[int],
    mesh_dir: str,
    refactor_krylov: list[int],
    petsc: list[str],
    label: str,
    repeat: int,
    results: Path,
) -> None:
    mpirun = Path(sys.executable).with_name("mpirun")
    name = Path(config).stem
    for k in refactor_krylov:
        for n in ranks:
            out = Path(f"/tmp/skinid-forward-{name}-{n}-{k}.json")
            cmd = [
                sys.executable,
                __file__,
                "run-one",
                config,
                str(out),
                "--mesh-dir",
                mesh_dir,
                "--refactor-krylov",
                str(k),
                "--repeat",
                str(repeat),
                *(f"--petsc={p}" for p in petsc),
            ]
            if n > 1:
                cmd = [str(mpirun), "-n", str(n), *cmd]
            env = {**os.environ, "OMP_NUM_THREADS": "1"}
            subprocess.run(cmd, check=True, env=env)
            result = json.loads(out.read_text())
            print(json.dumps(result, indent=2))
            merge_results(f"timing_{name}_{n}rank" + ("" if k else "_refactor0") + label, result, results)


def coarse_average(fine_xy, fine_values, coarse_xy, coarse_edges):
    """Average fine-cell values over the coarse cells that contain their centroids."""
    ix = np.searchsorted(coarse_edges, fine_xy[:, 0]) - 1
    iy = np.searchsorted(coarse_edges, fine_xy[:, 1]) - 1
    n = len(coarse_edges) - 1
    sums = np.zeros((n * n, fine_values.shape[1]))
    counts = np.zeros(n * n)
    np.add.at(sums, iy * n + ix, fine_values)
    np.add.at(counts, iy * n + ix, 1)
    grid = sums / np.maximum(counts, 1)[:, None]
    cx = np.searchsorted(coarse_edges, coarse_xy[:, 0]) - 1
    cy = np.searchsorted(coarse_edges, coarse_xy[:, 1]) - 1
    return grid[cy * n + cx]


def convergence(mesh_dir: str) -> None:
    """Change of the skin strain field between meshes and elements (relative L2 over cells).

    Each run is compared with a finer one by averaging the finer field over the coarser
    cells (the in-plane grids nest when h_membrane halves and h_far scales with it).

    Longer than a screen: the table of meshes and elements, then each comparison, in order.
    """
    from mpi4py import MPI

    from skinfem.config import Config, load_config
    from skinfem.mesh import inplane_coordinates
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    runs = {}
    paper = load_config("paper").mesh
    far = paper.h_far / paper.h_membrane  # the paper preset's grading, kept as h changes,
    cases = [  # except at h = 2, where it would leave a 13 mm edge cell: 8 mm there
        ("Q1 h=2", dict(h_membrane=2.0, h_far=8.0), 1, 2),
        ("Q1 h=1", dict(h_membrane=1.0, h_far=far * 1.0), 1, 2),
        ("Q1 h=0.5 (paper)", dict(h_membrane=paper.h_membrane, h_far=paper.h_far), 1, 2),
        ("Q1 h=0.25", dict(h_membrane=0.25, h_far=far * 0.25), 1, 2),
        ("Q2 h=2", dict(h_membrane=2.0, h_far=8.0), 2, 4),
    ]
    for label, mesh, degree, qdeg in cases:
        cfg = Config(name="conv").with_changes(mesh=mesh, solver={"element_degree": degree, "quadrature_degree": qdeg})
        t0 = time.perf_counter()
        model = SkinModel(cfg, MPI.COMM_WORLD, mesh_dir=mesh_dir)
        frames = model.simulate(SkinParams(**PARAMS), Design(**DESIGN))
        runs[label] = dict(
            xy=frames.xy,
            strain=frames.strain[-1],
            edges=inplane_coordinates(cfg.mesh),
            dofs=model.n_dofs,
            h_far=mesh["h_far"],
            skin_cells=len(frames.xy),
            seconds=time.perf_counter() - t0,
        )
        print(label, model.n_dofs, "dofs", f"{runs[label]['seconds']:.1f} s", flush=True)

    def rel_l2(coarse, fine):
        avg = coarse_average(runs[fine]["xy"], runs[fine]["strain"], runs[coarse]["xy"], runs[coarse]["edges"])
        a = runs[coarse]["strain"][:, :2]
        return float(np.linalg.norm(a - avg[:, :2]) / np.linalg.norm(avg[:, :2]))

    pairs = [
        ("Q1 h=2", "Q1 h=1"),
        ("Q1 h=1", "Q1 h=0.5 (paper)"),
        ("Q1 h=0.5 (paper)", "Q1 h=0.25"),
        ("Q1 h=2", "Q1 h=0.5 (paper)"),
        ("Q1 h=2", "Q1 h=0.25"),
        ("Q1 h=2", "Q2 h=2"),
        ("Q2 h=2", "Q1 h=0.25"),
    ]
    table = [{"coarse": c, "fine": f, "relative_l2_change_exx_eyy": rel_l2(c, f)} for c, f in pairs]
    keep = ("dofs", "h_far", "skin_cells", "seconds")
    meta = {
        k: {**{q: v[q] for q in keep}, "max_abs_exx_eyy": np.abs(v["strain"][:, :2]).max(0).tolist()}
        for k, v in runs.items()
    }
    for row in table:
        print(f"{row['coarse']:>18} vs {row['fine']:<18} {row['relative_l2_change_exx_eyy']:.4f}")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    merge_results(
        "convergence", {"params": PARAMS, "design": DESIGN, "runs": meta, "table": table, "peak_memory_mb": peak_mb}
    )


TOLERANCES = [(1e-10, 1e-8), (1e-9, 1e-8), (1e-8, 1e-8), (1e-8, 1e-5), (3e-8, 1e-8), (1e-7, 1e-8)]


def tolerance(config_source: str, mesh_dir: str, results: Path) -> None:
    """The field change and work of each (atol [N], krylov_rtol) pair of TOLERANCES (first: the
    defaults, the reference)."""
    import dataclasses

    from mpi4py import MPI

    from skinfem.config import load_config
    from skinfem.fenics import PETSc
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    comm, base, rows, reference = MPI.COMM_WORLD, load_config(config_source), [], None
    PETSc.Log.begin()
    for atol, krylov_rtol in TOLERANCES:
        solver = dataclasses.replace(base.solver, atol=atol, krylov_rtol=krylov_rtol)
        model = SkinModel(dataclasses.replace(base, solver=solver), comm, mesh_dir=mesh_dir)
        before = PETSc.Log.Event("MatSolve").getPerfInfo()["count"]
        frames = model.simulate(SkinParams(**PARAMS), Design(**DESIGN))
        strain = np.asarray(frames.strain)  # (n_frames, n_cells, 3)
        reference = strain if reference is None else reference
        change = [np.linalg.norm(a - b) / np.linalg.norm(b) for a, b in zip(strain, reference)]
        rows.append(
            {
                "atol": atol,
                "krylov_rtol": krylov_rtol,
                "seconds": frames.seconds,
                "newton_iterations_per_increment": frames.newton_iterations,
                "factorizations": model.factorizations,
                "triangular_solves": comm.allreduce(
                    PETSc.Log.Event("MatSolve").getPerfInfo()["count"] - before, op=MPI.MAX
                ),
                "max_relative_change_of_a_frame": float(max(change)),
            }
        )
        if comm.rank == 0:
            print(rows[-1], flush=True)
    if comm.rank == 0:
        merge_results(f"newton_tolerance_{base.name}", {"ranks": comm.size, "rows": rows}, results)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("part", choices=["timing", "convergence", "tolerance", "run-one"])
    parser.add_argument("args", nargs="*")
    parser.add_argument("--config", default="paper")
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--mesh-dir", default="meshes")
    parser.add_argument("--refactor-krylov", type=int, nargs="+", default=[10, 0])
    parser.add_argument(
        "--petsc",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra PETSc option of the model's solver (repeatable), e.g. pc_type=lu",
    )
    parser.add_argument("--label", default="", help="suffix of the result keys, e.g. _lu")
    parser.add_argument(
        "--repeat",
        type=int,
        default=3,
        help="simulations per timing run (the machine's speed varies; the median is kept)",
    )
    parser.add_argument(
        "--results",
        type=Path,
        default=RESULTS,
        help="JSON file the timings are merged into (levers: results/forward_levers.json)",
    )
    a = parser.parse_args()
    if a.repeat < 1:
        parser.error(f"--repeat must be >= 1, got {a.repeat}")
    bad = [p for p in a.petsc if "=" not in p or not p.split("=", 1)[0]]
    if bad:
        parser.error(f"--petsc takes KEY=VALUE (VALUE may be empty), got '{bad[0]}'")
    if a.part == "run-one":
        run_one(a.args[0], a.args[1], a.mesh_dir, a.refactor_krylov[0], a.petsc, a.repeat)
    elif a.part == "timing":
        timing(a.config, a.ranks, a.mesh_dir, a.refactor_krylov, a.petsc, a.label, a.repeat, a.results)
    elif a.part == "tolerance":
        tolerance(a.config, a.mesh_dir, a.results)
    else:
        convergence(a.mesh_dir)


if __name__ == "__main__":
    main()
