"""How far the rigid-membrane limit is from the elastic membrane, and how much faster it is.

    python benchmarks/rigid_limit.py [--config paper] [--out benchmarks/results/rigid_limit.json]

``membrane.model = "rigid"`` prescribes the footprint's in-plane displacement u = t (alpha11 x,
alpha22 y) instead of modelling the bonded 1 mm lamina (10^7 times stiffer than the skin). For
every design of the configuration at the centre of the parameter box, and for the "mixed" design
(0.05, -0.05) at four corners of the box, both models are run (one model each, reused as in a
sweep; 1 rank) and their last-frame observables (the skin surface strain per top cell) compared:
relative RMS difference over all cells and in bands of max(|x|, |y|) (under the membrane < 8 mm,
edge band 8-12 mm, far field > 12 mm), seconds and Newton iterations of each simulation.
Resumable: finished rows are kept in the results file and skipped. Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from dic_convergence import band_changes
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
MIXED = (0.05, -0.05)


def cases(config) -> list[tuple[str, np.ndarray, tuple[float, float]]]:
    """(name, skin parameters (5,), design): the box centre with every design, and four corners
    (all low, all high, soft/stiff-fibred, stiff/soft-fibred; theta 0 or 90 deg) with MIXED."""
    box = config.sweep.box
    low, high = box[:, 0], box[:, 1]
    centre = box.mean(axis=1)
    corners = {
        "low": low,
        "high": high,
        "mu low, k1 k2 high": np.r_[low[0], high[1:3], centre[3], low[4]],
        "mu high, k1 k2 low": np.r_[high[0], low[1:3], centre[3], high[4]],
    }
    rows = [(f"centre, design {tuple(d)}", centre, tuple(d)) for d in config.sweep.designs]
    return rows + [(f"{name}, design {MIXED}", p, MIXED) for name, p in corners.items()]


def main() -> None:
    from skinfem.config import load_config
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="paper")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "rigid_limit.json")
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    args = parser.parse_args()
    config = load_config(args.config)
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    result.update(command=f"python benchmarks/rigid_limit.py --config {args.config}", config=config.name)
    rows = result.setdefault("rows", [])
    done = {row["case"] for row in rows}
    models = {
        kind: SkinModel(config.with_changes(membrane={"model": kind}), MPI.COMM_SELF, mesh_dir=args.mesh_dir)
        for kind in ("elastic", "rigid")
    }
    result["dofs"] = {kind: model.n_dofs for kind, model in models.items()}
    for name, params, design in cases(config):
        if name in done:
            continue
        frames = {
            kind: model.simulate(SkinParams.from_array(params), Design(*design)) for kind, model in models.items()
        }
        elastic, rigid = frames["elastic"], frames["rigid"]
        rows.append(
            {
                "case": name,
                "params": params.tolist(),
                "design": list(design),
                "difference": band_changes(rigid.strain[-1], elastic.strain[-1], elastic.xy),
                "max_abs_strain": {k: float(np.abs(f.strain[-1]).max()) for k, f in frames.items()},
                "seconds": {k: round(f.seconds, 2) for k, f in frames.items()},
                "newton_iterations": {k: sum(f.newton_iterations) for k, f in frames.items()},
            }
        )
        print(rows[-1], flush=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
