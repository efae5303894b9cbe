"""Cost of one ramped simulation by its number of load increments.

    python benchmarks/ramp_increments.py [--config check] [--increments 2 3 5 10]
                                         [--out benchmarks/results/ramp_increments.json]

A check's first FE run of each design (and any run that cannot continue from a nearby one)
ramps the load from zero (``SkinModel.simulate``) in ``solver.increments`` equal steps, halved
after a failed one. Few increments mean few Newton solves but each from farther away: more
Newton iterations per increment, factorisations and cut-backs. Here the biaxial (0.05, 0.05)
and mixed (0.05, -0.05) designs at the centre of the preset's prior box, on one process as in a
check (one design per rank), for each number of increments: seconds, factorisations, Newton
iterations per accepted increment and cut-backs. Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DESIGNS = ((0.05, 0.05), (0.05, -0.05))


def ramp_costs(config_name: str, increments: list[int], mesh_dir: Path) -> dict:
    """Per number of increments and design: the ramped simulation's cost at the box centre."""
    from skinfem.config import load_config
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    base = load_config(config_name)
    params = SkinParams.from_array(base.sweep.box.mean(axis=1))
    rows = []
    for n in increments:
        model = SkinModel(base.with_changes(solver={"increments": n}), mesh_dir=mesh_dir)
        for design in (Design(*d) for d in DESIGNS):
            start = time.perf_counter()
            result = model.simulate(params, design)
            row = {
                "increments": n,
                "design": [design.alpha11, design.alpha22],
                "seconds": round(time.perf_counter() - start, 1),
                "factorizations": model.factorizations,
                "newton_iterations": list(result.newton_iterations),
                "cutbacks": result.cutbacks,
            }
            print(row, flush=True)
            rows.append(row)
    return {"params": params.as_array().tolist(), "dofs": model.n_dofs, "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="check")
    parser.add_argument("--increments", nargs="+", type=int, default=[2, 3, 5, 10])
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--out", type=Path, default=HERE / "results" / "ramp_increments.json")
    args = parser.parse_args()
    record = ramp_costs(args.config, args.increments, args.mesh_dir)
    command = (
        f"python benchmarks/ramp_increments.py --config {args.config}"
        f" --increments {' '.join(map(str, args.increments))}"
    )
    args.out.write_text(json.dumps({"command": command, "config": args.config, **record}, indent=1) + "\n")


if __name__ == "__main__":
    main()
