"""Convergence of what the check compares: the DIC surface strain at scattered points.

    python benchmarks/dic_convergence.py [--out benchmarks/results/dic_convergence.json]

One material (mu 1.2e-3 MPa, k1 0.017 MPa, k2 11, kappa 0.285, theta 30 deg), the mixed design
(0.05, -0.05) at t = 1, measured by the DIC operator (1 mm window) at a DIC-like point cloud
over +-20 mm (1 mm step, jitter, 3 holes). Meshes around the ``small`` preset: in-plane size
under the membrane / far (mm), skin layers s, muscle layers m, Q1 or Q2 elements. Each field
is compared with the finest (Q2, 2/3 mm, s2, m4): relative RMS difference over all points and
in bands of max(|x|, |y|) (under the membrane < 8 mm, the edge band 8-12 mm, far field
> 12 mm). Seconds: the second simulation of a model (forms compiled, mesh cached), 1 rank.
Numbers are recorded, not asserted.
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
    (1, 2, 6, 1, 2), (1, 2, 6, 1, 4), (1, 2, 3, 1, 2), (1, 2, 6, 2, 2), (1, 1, 3, 2, 4), (1, 2, 3, 2, 4),
    (2, 2, 6, 1, 2), (2, 2, 4, 1, 3), (2, 2, 4, 2, 3), (2, 2, 3, 2, 4),
]


def label(mesh) -> str:
    degree, hm, hf, s, m = mesh
    return f"Q{degree} {hm:g}/{hf:g} mm, s{s} m{m}"


def measure(mesh, xy, mesh_dir) -> tuple[np.ndarray, float, int]:
    from skinfem.config import load_config
    from skinfem.dic import StrainGauge, SurfaceStrainGauge
    from skinfem.model import SkinModel
    from skinfem.params import Design, SkinParams

    degree, hm, hf, s, m = mesh
    config = load_config("small").with_changes(
        mesh={"h_membrane": hm, "h_far": hf, "skin_layers": s, "muscle_layers": m},
        solver={"increments": 2, "element_degree": degree, "quadrature_degree": 2 * degree})
    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir)
    gauge = SurfaceStrainGauge(model.u, xy, StrainGauge(1.0))
    model.simulate(SkinParams(*PARAMS), Design(0.05, -0.05))
    start = time.perf_counter()
    model.simulate(SkinParams(*PARAMS), Design(0.05, -0.05))
    return gauge(), time.perf_counter() - start, model.n_dofs


def main() -> None:
    from inference.synthetic import dic_points

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "results" / "dic_convergence.json")
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    args = parser.parse_args()
    xy = dic_points(20.0, 1.0, np.random.default_rng(0))
    fields, rows = {}, []
    for mesh in MESHES:
        fields[mesh], seconds, dofs = measure(mesh, xy, args.mesh_dir)
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
    result = {"command": "python benchmarks/dic_convergence.py", "points": len(xy), "window_mm": 1.0,
              "reference": label(MESHES[-1]), "field_rms": float(np.sqrt(np.mean(reference**2))), "meshes": rows}
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for row in rows:
        print(f"{row['mesh']:>20}: {row['relative_rms_vs_finest']:.3f} "
              + " ".join(f"{row[b]:.3f}" for b in BANDS) + f"  {row['seconds']} s, {row['dofs']} dofs")


if __name__ == "__main__":
    main()
