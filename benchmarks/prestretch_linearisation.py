"""How far the pre-stretch's linearisation at zero predicts a finite pre-stretch's strain field.

    python benchmarks/prestretch_linearisation.py [--config small] [--mesh-dir meshes]
                                                  [--out benchmarks/results/prestretch_linearisation.json]

`skinid check` ranks candidate effects by a score test built from their derivative at the
null effect (docs/criticism-overview.md, step 3). At zero pre-stretch every fiber of the
unloaded skin sits at the tension-only switch (Ebar = 0), so the derivative there is one-sided:
the model's is the compressive side's (fibers slack); the tensile side's is the exact derivative
at a pre-stretch of 1e-6 times the true one. For the 1.08 x 1.02 pre-stretch at 30 deg of the
criticism benchmarks, scaled by s (and its mirror, -1), on the check's two designs (last frame,
DIC points on a 2 mm grid over +-18 mm, 1 mm strain window, the skin of those benchmarks), this
records the field change Delta f = f(s eps) - f(0) and, for each side's Jacobian J,
|Delta f - J s eps| / |Delta f| and the cosine of Delta f and J eps, also after both are made
orthogonal to the skin parameters' columns (what a score test sees: what re-tuning the skin
cannot absorb; unweighted). One process; recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SCALES = (1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0, -1.0)
TENSILE_SIDE = 1e-6  # the tensile side's Jacobian is taken at this fraction of the pre-stretch


def linearisation_errors(config_name: str, mesh_dir: Path) -> dict:
    """Per scale of the pre-stretch: the field change's norm and each side's prediction error."""
    from criticism import DESIGNS, TRUTH, hidden_effects
    from mpi4py import MPI

    from inference.forward import FEForward, PointSet
    from skinfem.config import N_SKIN, load_config

    config = load_config(config_name)
    g = np.arange(-18.0, 18.1, 2.0)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    observations = [PointSet(np.array(d), 1.0, xy) for d in DESIGNS]
    forward = FEForward(
        config, observations, config.sweep.box, mesh_dir, increments=2, comm=MPI.COMM_SELF, continuation=False
    )
    hidden = hidden_effects()["pre_stretch"]
    names, eps = list(hidden), np.array(list(hidden.values()))
    x0 = forward.null.copy()
    x0[:N_SKIN] = TRUTH

    def at(scale: float) -> np.ndarray:
        x = x0.copy()
        x[forward.index(names)] = scale * eps
        return x

    start = time.perf_counter()
    skin = list(forward.names[:N_SKIN])
    ((f0, compressive),) = forward.evaluate_with_jacobian([x0], names + skin)
    ((_, tensile),) = forward.evaluate_with_jacobian([at(TENSILE_SIDE)], names)
    q, _ = np.linalg.qr(compressive[..., len(names) :].reshape(-1, len(skin)))
    rows = []
    for scale in SCALES:
        change = (forward(at(scale)) - f0).ravel()
        row = {"scale": scale, "change_rms": float(np.sqrt(np.mean(change**2)))}
        for side, jacobian in (("compressive", compressive), ("tensile", tensile)):
            predicted = (jacobian[..., : len(names)] @ eps).ravel()
            row |= agreement(change, scale * predicted, side)
            row |= agreement(*(v - q @ (q.T @ v) for v in (change, scale * predicted)), f"{side}_beyond_skin")
        print(row, flush=True)
        rows.append(row)
    return {
        "pre_stretch": dict(zip(names, eps.tolist())),
        "skin": list(TRUTH),
        "dofs": forward.model.n_dofs,
        "seconds": round(time.perf_counter() - start, 1),
        "rows": rows,
    }


def agreement(change: np.ndarray, predicted: np.ndarray, label: str) -> dict[str, float]:
    """|change - predicted| / |change| and the cosine of the two (flattened fields)."""
    norm = np.linalg.norm(change)
    return {
        f"{label}_relative_error": float(np.linalg.norm(change - predicted) / norm),
        f"{label}_cosine": float(change @ predicted / norm / np.linalg.norm(predicted)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small")
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--out", type=Path, default=HERE / "results" / "prestretch_linearisation.json")
    args = parser.parse_args()
    record = linearisation_errors(args.config, args.mesh_dir)
    old = json.loads(args.out.read_text()) if args.out.exists() else {}
    old[args.config] = {"command": f"python benchmarks/prestretch_linearisation.py --config {args.config}", **record}
    args.out.write_text(json.dumps(old, indent=2) + "\n")


if __name__ == "__main__":
    main()
