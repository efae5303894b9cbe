"""Cost of the residual homotopy's Newton, with and without its stall stop.

    python benchmarks/homotopy.py [--config small] [--loads 0.1 0.125 0.15 0.175 0.2]
                                  [--linesearches bt cp l2] [--out benchmarks/results/homotopy.json]

A refined run of the discretisation estimate starts from another mesh's fields and, when
Newton–LU from there fails, solves R(u) = (1 - s) R(u0) for s rising to 1
(``SkinModel._residual_homotopy``). Without a stall stop, a homotopy step whose Newton stalls
(damped steps that barely reduce the residual) runs to the iteration cap (12) before the step
is halved.
Here the same far start is made reproducible and cheap: zero displacement at the full load of
each design (biaxial (a, a) and mixed (a, -a) for each load a), three materials of the box.
Per variant (``stall stop``: Newton judged every ``HOMOTOPY_STRETCH`` iterations, given up
after a stretch whose residual did not fall below ``HOMOTOPY_CONTRACTION`` times its start;
``no stall stop``: one stretch of the whole cap; each with one of PETSc's line searches,
``--linesearches``: ``bt``, backtracking on |R|², the default; ``cp``, the critical point of the
energy along the Newton direction — the residual is the gradient of the total energy less the
homotopy's constant load, so that energy is a merit function; ``l2``, a secant on |R|²): the
factorisations (one per Newton–LU step), the runs that gave up (they fall back to a load ramp),
and seconds; for runs that converged, the largest difference from the ramped equilibrium of
:meth:`SkinModel.simulate` relative to its largest displacement (equilibrium does not depend on
the path). Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
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
CAP = 12  # Newton–LU steps per homotopy step, as for a transferred run (inference.forward)


def cases(loads) -> list[tuple[str, SkinParams, Design]]:
    """Every (material, parameters, design): the biaxial (a, a) and mixed (a, -a) designs at each load a."""
    from skinfem.params import Design, SkinParams

    return [
        (material, SkinParams.from_array(np.array(values)), Design(a, a22))
        for material, values in MATERIALS.items()
        for a in loads
        for a22 in (a, -a)
    ]


def run_variant(model, stretch: int, linesearch: str, runs_of: list, ramped: list[np.ndarray]) -> dict:
    """Every case of ``runs_of`` (:func:`cases`) from zero at the full load with Newton judged
    every ``stretch`` iterations and damped by PETSc's ``linesearch``; per run: factorisations,
    converged, seconds, homotopy steps, and the difference from the case's ramped equilibrium
    (``ramped``, same order)."""
    import skinfem.model
    from skinfem.model import Factorisation

    skinfem.model.HOMOTOPY_STRETCH = stretch
    skinfem.model.HOMOTOPY_LINESEARCH = linesearch
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
            "homotopy_steps": [dataclasses.asdict(h) for h in model.homotopy_steps],
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


def main() -> None:
    import skinfem.model
    from skinfem.config import load_config
    from skinfem.model import SkinModel

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small")
    parser.add_argument("--loads", nargs="+", type=float, default=[0.1, 0.125, 0.15, 0.175, 0.2])
    parser.add_argument(
        "--linesearches", nargs="+", default=["bt", "cp", "l2"], help="PETSc line searches tried with the stall stop"
    )
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--out", type=Path, default=HERE / "results" / "homotopy.json")
    args = parser.parse_args()
    model = SkinModel(load_config(args.config), mesh_dir=args.mesh_dir)
    runs_of = cases(args.loads)
    ramped = []
    for _, params, design in runs_of:
        model.simulate(params, design)
        ramped.append(model.u.x.array.copy())
    stall_stop = skinfem.model.HOMOTOPY_STRETCH
    stop = f"stall stop ({stall_stop} iterations, contraction {skinfem.model.HOMOTOPY_CONTRACTION})"
    variants = {f"{stop}, {search} line search": (stall_stop, search) for search in args.linesearches}
    default = skinfem.model.HOMOTOPY_LINESEARCH
    variants[f"no stall stop, {default} line search"] = (CAP, default)
    results = {name: run_variant(model, *variant, runs_of, ramped) for name, variant in variants.items()}
    for name, result in results.items():
        print(name, {k: v for k, v in result.items() if k != "runs"}, flush=True)
    command = (
        f"python benchmarks/homotopy.py --config {args.config} --loads {' '.join(map(str, args.loads))}"
        f" --linesearches {' '.join(args.linesearches)}"
    )
    summary = {"command": command, "config": args.config, "dofs": model.n_dofs, "cap": CAP, "variants": results}
    args.out.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
