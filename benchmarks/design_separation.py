"""Which membrane designs tell the candidate effects apart, and is it the designs or the mesh?

    mpirun -n 2 python benchmarks/design_separation.py [--config small] [--designs all | recorded]
                                                       [--data self | q2-limit] [--data-dir DIR]
                                                       [--out out/design_separation] [--results FILE]

The check confuses some candidates on the two membranes of the criticism benchmark: a 2x
stiffer muscle with compressibility, the pre-stretch with compressibility when both the
pre-stretch and the muscle are hidden (docs/criticism.md §18-20). Is that the designs or the
check's mesh? At the criticism benchmark's material and hidden effects
(``benchmarks/criticism.py``: its truth, its DIC point cloud thinned to one point per 2 mm
square as its checks thin it, its correlated noise of sd 1e-3, the last frame), every model of
a case (its true effects, and rivals; each a set of effects freed beside the skin parameters)
is calibrated on noise-free data (Levenberg-Marquardt from the truth without effects, within
the prior box: :func:`inference.criticism.calibration.calibrate`) and its chi^2 recorded:

- ``--data self``: the checked mesh's own fields, so the true model fits them exactly
  (chi^2 = 0, a test of the fits) and what a rival leaves is the designs' power to tell it from
  the truth, with no mesh error in the way. Design sets: the recorded pair, and (``--designs
  all``) the pair plus each other design of the configuration's sweep.
- ``--data q2-limit``: the criticism benchmark's converged data of the recorded pair (its
  ``data_<mesh>_<case>.npy`` in ``--data-dir``, the Richardson limit of its two Q2 meshes), as
  the check sees them but without its correction of and allowance for its mesh's error: what
  each model leaves then includes that error, and how much of it a rival absorbs.

A rival's fit is repeated from a far start where the checks found it (``Case.far_start``),
lest its fit from the null stop in a local minimum. With noise a fitted comparison spreads by
about 2 sqrt(chi^2 difference): a difference of a few tens is needed before the check's choice
between two models is reliable. FE runs are kept in ``--out`` (a rerun reads them). Recorded,
not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
RECORDED = [(0.05, 0.05), (0.05, -0.05)]  # the designs of the criticism benchmark's checks


@dataclass(frozen=True)
class Case:
    """A hidden case of benchmarks/criticism.py and the models fitted to its data: the true one
    and rivals, each a tuple of effects freed beside the skin parameters (() is the skin alone).
    A model with a parameter in ``far_start`` is fitted a second time, started there (where the
    checks on converged data found it, docs/criticism.md §18-20)."""

    hidden: str
    true: tuple[str, ...]
    rivals: tuple[tuple[str, ...], ...]
    far_start: tuple[tuple[str, float], ...] = ()


COMPRESSIBLE = (("compressibility.log_factor", -0.53),)  # K/mu 0.59x: its fits on the converged data
PAIR = ("pre_stretch", "muscle_stiffness")
CASES = [
    Case("none", (), (("compressibility",), ("muscle_stiffness",)), COMPRESSIBLE),
    Case("muscle_stiffness", ("muscle_stiffness",), ((), ("compressibility",), ("skin_thickness",)), COMPRESSIBLE),
    Case("pre_stretch", ("pre_stretch",), (("compressibility",),)),
    Case("skin_thickness", ("skin_thickness",), ((),)),
    Case(
        "two_effects", PAIR, (("pre_stretch",), ("compressibility",), ("pre_stretch", "compressibility")), COMPRESSIBLE
    ),
]


def check_points(spacing: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The criticism benchmark's point cloud (n, 2) [mm] and the indices (m,) of the points its
    checks keep (one per ``spacing`` square)."""
    from inference.observations import thinned
    from inference.synthetic import dic_points

    cloud = dic_points(18.0, 1.0, np.random.default_rng(0))
    return cloud, thinned(cloud, spacing)


def case_fields(forward, case: Case, x0: np.ndarray, points: tuple[np.ndarray, np.ndarray], args, comm) -> np.ndarray:
    """Noise-free data (n_designs, m, 3) of ``case``: the checked mesh's own fields at the truth,
    or (``args.data`` a limit) the criticism benchmark's converged data at the ``kept`` points
    of its cloud (computed into ``--data-dir`` if missing, as that benchmark does)."""
    from criticism import hidden_effects, measured_data

    if args.data != "self":
        source = argparse.Namespace(out=args.data_dir, mesh_dir=args.mesh_dir)
        cloud, kept = points
        return measured_data(args.data, case.hidden, cloud, source, comm)[:, kept]
    hidden = hidden_effects()[case.hidden]
    x_true = x0.copy()
    x_true[forward.index(list(hidden))] = list(hidden.values())
    (fields,) = forward.evaluate_many([x_true])
    if fields is None:
        raise RuntimeError(f"{case.hidden} does not converge: {forward.failures[-1].message}")
    return fields


def fit_models(config, designs, points: tuple[np.ndarray, np.ndarray], args, comm, on_case) -> dict:
    """On ``designs``: each model of each case calibrated on the case's noise-free data; its
    chi^2, parameters, FE runs and seconds. ``on_case`` is called with the cases done so far
    after each one."""
    from criticism import NOISE, TRUTH

    from inference.criticism.data import Data, NoiseModel
    from inference.forward import FEForward, PointSet
    from skinfem.effects import get_effect

    cloud, kept = points
    xy = cloud[kept]
    observations = [PointSet(np.array(d), 1.0, xy) for d in designs]
    forward = FEForward(config, observations, config.sweep.box, args.mesh_dir, 2, comm, args.out / "fe_runs")
    x0 = forward.null.copy()
    x0[:5] = TRUTH
    out = {}
    for case in CASES:
        fields = case_fields(forward, case, x0, points, args, comm)
        shape = fields.shape[:2]
        data = Data(fields, np.ones(shape, bool), np.broadcast_to(xy, (*shape, 2)).copy(), NoiseModel(**NOISE))
        fits = {}
        for model in (case.true, *case.rivals):
            added = [q for name in model for q in get_effect(name).qualified_names()]
            free = [*range(5), *forward.index(added)]
            label = " + ".join(model) or "skin alone"
            starts = {label: x0}
            far = [(q, v) for q, v in case.far_start if q in added]
            if far:
                x_far = x0.copy()
                x_far[forward.index([q for q, _ in far])] = [v for _, v in far]
                starts[f"{label}, from " + ", ".join(f"{q} = {v:g}" for q, v in far)] = x_far
            for name, start in starts.items():
                fits[name] = fit(forward, data, start, free, f"{case.hidden}: {name}")
        out[case.hidden] = {"n": data.n, "true": " + ".join(case.true) or "skin alone", "fits": fits}
        on_case(out)
    return out


def fit(forward, data, x0: np.ndarray, free: list[int], label: str) -> dict:
    """One rival model calibrated from ``x0``: its chi^2, free parameters, FE runs, seconds, rejected steps."""
    from inference.criticism.calibration import calibrate

    runs0 = forward.runs
    cal = calibrate(forward, data, x0, free, label=label)
    return {
        "chi2": cal.chi2,
        "x": {forward.names[i]: float(cal.x[i]) for i in free},
        "fe_runs": forward.runs - runs0,
        "seconds": cal.seconds,
        "rejected": len(cal.rejected),
    }


def design_sets(designs: list[tuple[float, float]], which: str) -> list[list[tuple[float, float]]]:
    """The recorded pair, and (``which`` = "all") the pair plus each other design of ``designs``."""
    others = [d for d in designs if d not in RECORDED] if which == "all" else []
    return [RECORDED, *([*RECORDED, d] for d in others)]


def main() -> None:
    import skinfem.model  # noqa: F401  (PETSc initialises collectively: import on every rank first)
    from skinfem.config import load_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small", help="the checked mesh (preset or TOML)")
    parser.add_argument("--designs", choices=["all", "recorded"], default="all")
    parser.add_argument("--out", type=Path, default=Path("out/design_separation"))
    parser.add_argument("--data", choices=["self", "q2-limit"], default="self", help="the noise-free data")
    parser.add_argument(
        "--data-dir", type=Path, default=Path("out/criticism_bench"), help="the criticism benchmark's --out"
    )
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--results", type=Path, default=HERE / "results" / "design_separation.json")
    args = parser.parse_args()
    if args.data != "self" and args.designs != "recorded":
        parser.error("the converged data exist for the recorded designs only: give --designs recorded")
    comm = MPI.COMM_WORLD
    config = load_config(args.config)
    designs = [tuple(round(a, 12) for a in d) for d in config.sweep.designs]
    points = check_points()
    sets: list[dict] = []
    for chosen in design_sets(designs, args.designs):
        start = time.perf_counter()
        current = {"designs": chosen, "cases": {}, "seconds": None}
        sets.append(current)

        def progress(cases: dict) -> None:
            current["cases"] = cases
            if comm.rank == 0:
                write_results(args, comm.size, len(points[1]), sets, finished=False)

        fit_models(config, chosen, points, args, comm, progress)
        current["seconds"] = time.perf_counter() - start
    if comm.rank == 0:
        write_results(args, comm.size, len(points[1]), sets, finished=True)


def write_results(args, ranks: int, n_points: int, sets: list[dict], finished: bool) -> None:
    """The results file (``n_points``: the kept points per design): the design sets fitted so far
    (``finished`` False while cases remain: a stopped run keeps its finished fits here, and its
    FE runs in ``--out``)."""
    result = {
        "command": (
            f"mpirun -n {ranks} python benchmarks/design_separation.py --config {args.config} "
            f"--designs {args.designs} --data {args.data} --data-dir {args.data_dir} --out {args.out} "
            f"--results {args.results}"
        ),
        "finished": finished,
        "config": args.config,
        "points": n_points,
        "data": args.data,
        "frame": 1.0,
        "noise": "sd 1e-3, correlation length 2 mm, nugget 0.3 (benchmarks/criticism.py)",
        "design_sets": sets,
    }
    args.results.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
