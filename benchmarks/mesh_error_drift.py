"""Does the check mesh's own error move with the parameters enough to hide an effect?

    python benchmarks/mesh_error_drift.py [--config check] [--refine edge]
                                          [--cases skin_thickness muscle_stiffness pre_stretch]
                                          [--out out/mesh_error_drift] [--results FILE]

(one rank on a 24 GB machine: the refined mesh's run with derivatives takes 9.4 GB on one rank
and was killed at 12.6 GB on one of two ranks)

The check corrects its model by a fitted multiple ``a`` of one two-mesh shift s0 = R(x0) - C(x0)
(``CorrectedForward``: C the check mesh, R its refined mesh), estimated at the baseline x0. When
a candidate moves the model far from x0, the mesh's error there, s1 = R(x1) - C(x1), may differ
from s0; data from a better mesh then carry that drift d = s1 - s0 beside the effect's signature
g = C(x1) - C(x0). With R standing for the better mesh (the measurement):

- the effect fitted at its true value leaves what the skin parameters and ``a`` cannot absorb of
  d (the stale correction's error), ``|P d|^2``;
- the skin alone, re-tuned, leaves ``|P (g + d)|^2``;

(P: projection off the whitened skin Jacobian of C at x0 and off s0, i.e. a linearised
calibration of the skin parameters and ``a``). When ``|P d|^2`` is not far below ``|P (g + d)|^2``
the effect cannot win against a compensated skin, however large its own signature ``|P g|^2``.

At the criticism benchmark's material (its truth without effects: x0), designs, thinned point
cloud and noise model (``benchmarks/criticism.py``); each case's hidden effect is x1. Whitened by
the noise alone and by the noise with the carried mesh error (as the check whitens). Also what
the first-order drift (:func:`~inference.criticism.discretisation.mesh_error_drift`, the check's
``--mesh-drift``) misses of the drift. FE runs are
kept in ``--out`` (a rerun reads them). Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent


def projector_off(columns: np.ndarray) -> np.ndarray:
    """(n, n) projection onto the orthogonal complement of ``columns`` (n, k)."""
    q, _ = np.linalg.qr(columns)
    return np.eye(len(q)) - q @ q.T


def drift_numbers(whiten, jacobian: np.ndarray, c0, r0, c1, r1, linear_drift) -> dict:
    """Whitened squared norms [chi^2 units] of the shift, signature and drift of one case
    (module doc), and what the first-order drift ``linear_drift`` (the same shape as the fields)
    misses of the drift; ``whiten`` maps an (n_obs, n_pts, 3) field difference to (n,)."""
    s0, s1, g = whiten(r0 - c0), whiten(r1 - c1), whiten(c1 - c0)
    d = s1 - s0  # the whitening is linear
    miss = d - whiten(linear_drift)
    skin = np.stack([whiten(jacobian[..., k]) for k in range(jacobian.shape[-1])], -1)
    p = projector_off(np.column_stack([skin, s0]))
    a_best = float(s1 @ s0 / (s0 @ s0))

    def sq(v):
        return float(v @ v)

    return {
        "shift_at_x0": sq(s0),
        "shift_at_x1": sq(s1),
        "shift_at_x1_best_multiple_of_x0s": a_best,
        "shift_at_x1_beyond_that_multiple": sq(s1 - a_best * s0),
        "signature": sq(g),
        "signature_beyond_skin": sq(p @ g),
        "drift_beyond_skin": sq(p @ d),
        "drift_first_order_miss_beyond_skin": sq(p @ miss),
        "signature_plus_drift_beyond_skin": sq(p @ (g + d)),
        "cosine_signature_drift_beyond_skin": float((p @ g) @ (p @ d) / np.sqrt(sq(p @ g) * sq(p @ d))),
    }


def main() -> None:
    from criticism import DESIGNS, NOISE, TRUTH, hidden_effects
    from design_separation import check_points

    import skinfem.model  # noqa: F401  (PETSc initialises collectively: import on every rank first)
    from inference.criticism.data import Data, NoiseModel
    from inference.criticism.discretisation import estimate, mesh_error_drift, refined_config
    from inference.forward import FEForward, PointSet
    from skinfem.config import PARAM_NAMES, load_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="check")
    parser.add_argument("--refine", default="edge")
    parser.add_argument("--cases", nargs="+", default=["skin_thickness", "muscle_stiffness", "pre_stretch"])
    parser.add_argument("--out", type=Path, default=Path("out/mesh_error_drift"))
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--results", type=Path, default=HERE / "results" / "mesh_error_drift.json")
    args = parser.parse_args()
    comm, start = MPI.COMM_WORLD, time.perf_counter()
    config = load_config(args.config)
    cloud, kept = check_points()
    xy = cloud[kept]
    observations = [PointSet(np.array(d), 1.0, xy) for d in DESIGNS]
    meshes = [config, refined_config(config, args.refine)]
    coarse, fine = (
        FEForward(c, observations, config.sweep.box, args.mesh_dir, 2, comm, args.out / "fe_runs") for c in meshes
    )
    x0 = coarse.null.copy()
    x0[:5] = TRUTH
    shape = (len(DESIGNS), len(xy))
    data = Data(
        np.zeros((*shape, 3)), np.ones(shape, bool), np.broadcast_to(xy, (*shape, 2)).copy(), NoiseModel(**NOISE)
    )
    coarse.evaluate_many([x0])
    fine.continue_from(coarse, x0)
    drift = mesh_error_drift(coarse, fine, x0, data.masks)
    ((c0, jacobian),) = coarse.evaluate_with_jacobian([x0], list(PARAM_NAMES))
    disc = estimate(coarse, fine, x0, data, args.refine)
    carried = data.with_model_error(disc.model_error(data.xy, data.masks))
    r0 = c0 + disc.shift
    results = {
        "config": args.config,
        "refine": args.refine,
        "n": data.n,
        "carried_sigma": disc.remaining_sigma,
        "cases": {},
    }
    for case in args.cases:
        x1 = x0.copy()
        hidden = hidden_effects()[case]
        x1[coarse.index(list(hidden))] = list(hidden.values())
        (c1,), (r1,) = coarse.evaluate_many([x1]), fine.evaluate_many([x1])
        results["cases"][case] = {
            "effect": hidden,
            "noise_only": drift_numbers(data.whiten, jacobian, c0, r0, c1, r1, drift @ (x1 - x0)),
            "noise_and_carried_error": drift_numbers(carried.whiten, jacobian, c0, r0, c1, r1, drift @ (x1 - x0)),
        }
        results["seconds"] = time.perf_counter() - start
        if comm.rank == 0:
            args.results.write_text(json.dumps(results, indent=2) + "\n")
            print(case, json.dumps(results["cases"][case], indent=1), flush=True)


if __name__ == "__main__":
    main()
