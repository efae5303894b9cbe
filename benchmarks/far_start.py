"""Cost of solving an equilibrium from a start far from it, by pseudo-time setting.

    python benchmarks/far_start.py [--config small] [--loads 0.1 0.125 0.15 0.175 0.2]
                                   [--first-steps 1 3 10] [--min-growths 2 4] [--refactor-krylov 10]
                                   [--out benchmarks/results/far_start.json]
    python benchmarks/far_start.py --transfer [--designs 0.05,0.05 0.05,-0.05] [--refactor-krylov 10]
                                   [--out benchmarks/results/far_start_transfer.json]

A refined run of the discretisation estimate starts from another mesh's fields, which it solves
by pseudo-transient continuation (``SkinModel._solve_far_start``, :mod:`skinfem.pseudo_time`).
Here the far start is made reproducible and cheap: zero displacement at the full load of each
design (biaxial (a, a) and mixed (a, -a) for each load a, up to four times the paper's), three
materials of the box. Per first pseudo-time step (``skinfem.pseudo_time.FIRST_STEP``,
dimensionless: the shift is the tangent's diagonal / dt), smallest growth of dt after a kept
step (``--min-growths``, ``skinfem.pseudo_time.MIN_GROWTH``) and ``--refactor-krylov``
(``solver.refactor_krylov``: 0 factorises at every step, n > 0 keeps a factorisation as
GMRES's preconditioner until a solve needs more than n iterations): the factorisations, the
runs that gave up (they fall back to a load ramp), seconds, and for runs that converged the
largest difference from the ramped equilibrium of :meth:`SkinModel.simulate` relative to its
largest displacement (equilibrium does not depend on the path). The residual homotopy and the
Newton–LU that preceded pseudo-time were measured on the same starts:
``benchmarks/results/homotopy.json``, ``far_start.json`` and ``far_start_reuse.json``.
``--transfer``: the refined run that stalled the homotopy, reproduced — the stiffer-muscle seed-4
check on the quadratic check mesh (``criticism_q2_muscle_seed4_rerun.json``, ``third_rerun``:
its biaxial design's refined run took 48 factorisations, 1,629 s): the check mesh's equilibrium at
that check's calibrated baseline, interpolated onto its edge refinement (224k dofs) and solved
there as a transferred run is (one rank, ~5 minutes and ~10 GB per design); each design and
``--refactor-krylov`` is kept under its own key of the results file and not run again.
Every record names the step control it ran with (first dt, smallest growth, and
``skinfem.pseudo_time.LINEARITY``: dt grows 10x after two steps that did what their linearisation
predicted; ``far_start_linear.json`` and ``far_start_transfer_linear.json`` since that rule).
Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from skinfem.params import Design, SkinParams

HERE = Path(__file__).resolve().parent
MATERIALS = {  # mu [MPa], k1 [MPa], k2, kappa, theta [deg]
    "reference": (1.2e-3, 0.017, 11.0, 0.285, 30.0),
    "soft": (6e-4, 0.01, 5.0, 0.2, 0.0),
    "stiff": (2.4e-3, 0.03, 20.0, 0.1, 60.0),
}
CAP = 12  # Newton iterations of a later frame, as for a transferred run (inference.forward)
# the baseline calibrated by the stiffer-muscle seed-4 check (its report); its biaxial design's
# refined run stalled the residual homotopy
TRANSFER_PARAMS = (6.04e-4, 0.0117, 8.31, 0.2842, 26.2)


def cases(loads) -> list[tuple[str, SkinParams, Design]]:
    """Every (material, parameters, design): the biaxial (a, a) and mixed (a, -a) designs at each load a."""
    from skinfem.params import Design, SkinParams

    return [
        (material, SkinParams.from_array(np.array(values)), Design(a, a22))
        for material, values in MATERIALS.items()
        for a in loads
        for a22 in (a, -a)
    ]


def set_pseudo_time(first_step: float, min_growth: float) -> None:
    """The first dt and the smallest growth of dt that the model's pseudo-time steps use."""
    import skinfem.pseudo_time

    skinfem.pseudo_time.FIRST_STEP, skinfem.pseudo_time.MIN_GROWTH = first_step, min_growth


def run_variant(model, runs_of: list, ramped: list[np.ndarray]) -> dict:
    """Every case of ``runs_of`` (:func:`cases`) from zero at the full load; per run:
    factorisations, converged, seconds, the solve's record and the difference from the case's
    ramped equilibrium (``ramped``, same order)."""
    from skinfem.model import Factorisation

    runs = []
    for (material, params, design), reference in zip(runs_of, ramped):
        zero = [(1.0, np.zeros_like(model.u.x.array))]
        start = time.perf_counter()
        converged = model.solve_frames(params, design, zero, max_iterations=CAP, factorisation=Factorisation.EVERY_STEP)
        row = {
            "material": material,
            "design": [design.alpha11, design.alpha22],
            "converged": converged,
            "factorizations": model.factorizations,
            "seconds": round(time.perf_counter() - start, 2),
            "far_start": dataclasses.asdict(model.far_starts[-1]),
        }
        if converged:
            error = np.abs(model.u.x.array - reference).max() / np.abs(reference).max()
            row["difference_from_ramp"] = float(error)
        runs.append(row)
    return {
        "factorizations": sum(r["factorizations"] for r in runs),
        "gave_up": sum(not r["converged"] for r in runs),
        "seconds": round(sum(r["seconds"] for r in runs), 1),
        "largest_difference_from_ramp": max(r.get("difference_from_ramp", 0.0) for r in runs),
        "runs": runs,
    }


def transfer_guess(mesh_dir: Path, params: SkinParams, design: Design) -> tuple:
    """The check mesh's equilibrium at ``params`` and the full load of ``design``, and the seconds
    it took (``--transfer``)."""
    from skinfem.config import load_config
    from skinfem.continuation import ConvergedStates
    from skinfem.model import SkinModel

    start = time.perf_counter()
    coarse = SkinModel(load_config("check").with_changes(solver={"increments": 2}), mesh_dir=mesh_dir)
    coarse.simulate(params, design)
    states = ConvergedStates(np.zeros(5), None, {1.0: coarse.u.x.array.copy()})
    return coarse, states, time.perf_counter() - start


def run_transfer(coarse, states, params: SkinParams, design: Design, refactor_krylov: int, mesh_dir: Path) -> dict:
    """The transferred refined run of ``--transfer`` (module doc) from ``coarse``'s ``states``,
    with ``refactor_krylov``: dofs, seconds, converged, factorisations, the solve's record."""
    import skinfem.pseudo_time
    from inference.criticism.discretisation import refined_config
    from skinfem.continuation import transfer
    from skinfem.model import Factorisation, SkinModel

    fine_config = refined_config(coarse.config, "edge").with_changes(solver={"refactor_krylov": refactor_krylov})
    fine = SkinModel(fine_config, mesh_dir=mesh_dir)
    guess = transfer(states, coarse.V, fine.V).frames[1.0]
    start = time.perf_counter()
    converged = fine.solve_frames(
        params, design, [(1.0, guess)], max_iterations=CAP, factorisation=Factorisation.EVERY_STEP
    )
    return {
        "first_step": skinfem.pseudo_time.FIRST_STEP,
        "min_growth": skinfem.pseudo_time.MIN_GROWTH,
        "linearity": skinfem.pseudo_time.LINEARITY,
        "params": TRANSFER_PARAMS,
        "design": [design.alpha11, design.alpha22],
        "dofs": [coarse.n_dofs, fine.n_dofs],
        "refined_seconds": round(time.perf_counter() - start, 1),
        "converged": converged,
        "factorizations": fine.factorizations,
        "far_start": dataclasses.asdict(fine.far_starts[-1]),
    }


def write_transfer(args) -> None:
    """``--transfer``: the stalled transfer for every design and ``--refactor-krylov``, with the
    model's pseudo-time settings unless given; a variant already in the results file is not run
    again."""
    import skinfem.pseudo_time as pt
    from skinfem.config import load_config
    from skinfem.params import Design, SkinParams

    first_step = (args.first_steps or [pt.FIRST_STEP])[0]
    growth = (args.min_growths or [pt.MIN_GROWTH])[0]
    set_pseudo_time(first_step, growth)
    out = args.out or HERE / "results" / "far_start_transfer.json"
    results = json.loads(out.read_text()) if out.exists() else {"variants": {}}
    params = SkinParams.from_array(np.array(TRANSFER_PARAMS))
    refactors = args.refactor_krylov or [load_config("check").solver.refactor_krylov]
    for design in (Design(*map(float, d.split(","))) for d in args.designs):
        coarse = None
        for refactor in refactors:
            key = f"design ({design.alpha11:g}, {design.alpha22:g}), refactor_krylov {refactor}"
            if key in results["variants"]:
                continue
            if coarse is None:
                coarse, states, seconds = transfer_guess(args.mesh_dir, params, design)
            command = (
                f"python benchmarks/far_start.py --transfer --first-steps {first_step:g} --min-growths {growth:g}"
                f" --designs {design.alpha11:g},{design.alpha22:g} --refactor-krylov {refactor}"
            )
            record = run_transfer(coarse, states, params, design, refactor, args.mesh_dir)
            results["variants"][key] = {"command": command, "check_mesh_seconds": round(seconds, 1), **record}
            print(key, {k: v for k, v in record.items() if k != "far_start"}, flush=True)
            out.write_text(json.dumps(results, indent=1) + "\n")


def write_far_starts(args) -> None:
    """The 30 far starts on ``args.config`` for every ``--refactor-krylov``, smallest growth and
    first step."""
    import skinfem.pseudo_time
    from skinfem.config import load_config
    from skinfem.model import SkinModel

    first_steps, growths = args.first_steps or [1.0, 3.0, 10.0], args.min_growths or [2.0, 4.0]
    refactors = args.refactor_krylov or [load_config(args.config).solver.refactor_krylov]
    runs_of, results = cases(args.loads), {}
    for refactor in refactors:
        config = load_config(args.config).with_changes(solver={"refactor_krylov": refactor})
        model = SkinModel(config, mesh_dir=args.mesh_dir)
        ramped = []
        for _, params, design in runs_of:
            model.simulate(params, design)
            ramped.append(model.u.x.array.copy())
        for growth, dt in itertools.product(growths, first_steps):
            set_pseudo_time(dt, growth)
            name = f"first pseudo-time step {dt:g}, growth at least {growth:g}x, refactor_krylov {refactor}"
            results[name] = result = run_variant(model, runs_of, ramped)
            print(name, {k: v for k, v in result.items() if k != "runs"}, flush=True)
    command = (
        f"python benchmarks/far_start.py --config {args.config} --loads {' '.join(map(str, args.loads))}"
        f" --first-steps {' '.join(map(str, first_steps))} --min-growths {' '.join(map(str, growths))}"
        f" --refactor-krylov {' '.join(map(str, refactors))}"
    )
    summary = {
        "command": command,
        "config": args.config,
        "dofs": model.n_dofs,
        "cap": CAP,
        "linearity": skinfem.pseudo_time.LINEARITY,
        "variants": results,
    }
    (args.out or HERE / "results" / "far_start.json").write_text(json.dumps(summary, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small")
    parser.add_argument("--loads", nargs="+", type=float, default=[0.1, 0.125, 0.15, 0.175, 0.2])
    parser.add_argument("--first-steps", nargs="+", type=float, help="default: 1 3 10 (--transfer: the model's)")
    parser.add_argument("--min-growths", nargs="+", type=float, help="default: 2 4 (--transfer: the model's)")
    parser.add_argument("--refactor-krylov", nargs="+", type=int, help="default: the config's (10)")
    parser.add_argument("--transfer", action="store_true", help="the quadratic check mesh's stalled transfer")
    parser.add_argument("--designs", nargs="+", default=["0.05,0.05"], help="--transfer: alpha11,alpha22 each")
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    (write_transfer if args.transfer else write_far_starts)(args)


if __name__ == "__main__":
    main()
