"""How far apart two of ``benchmarks/criticism.py``'s data are, per region of the DIC points.

    python benchmarks/limit_data.py --data out/crit_graded_m8 q2-limit-m8 \
        --against out/crit_graded q2-limit --case none --results benchmarks/results/limit_data_m8.json

Each data set is read from the fields ``benchmarks/criticism.py`` kept in its ``--out`` folder
(``data_<mesh>_<case>.npy``, the limit extrapolated from its pair of meshes as there; nothing is
computed). Relative RMS difference of (E_xx, E_yy) of both designs over all points and in the
bands of ``benchmarks/dic_convergence.py`` (under the membrane, the 8-12 mm edge band, the far
field), relative to ``--against``; also each limit's two meshes against each other. Recorded,
not asserted.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def kept_fields(bench, folder: Path, name: str, case: str) -> list[np.ndarray]:
    """The kept fields (n_designs, n_points, 3) of ``name``'s meshes (one, or a limit's pair)."""
    paths = [bench.kept_data_path(folder, mesh, case) for mesh in bench.data_meshes(name)]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise SystemExit(f"limit_data.py: error: {', '.join(missing)} not made yet (run benchmarks/criticism.py)")
    return [np.load(p) for p in paths]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs=2, metavar=("FOLDER", "NAME"), required=True)
    parser.add_argument("--against", nargs=2, metavar=("FOLDER", "NAME"), required=True)
    parser.add_argument("--case", default="none")
    parser.add_argument("--results", type=Path, required=True)
    args = parser.parse_args()
    import criticism as bench
    import dic_convergence as convergence

    from inference.synthetic import dic_points

    xy = np.tile(dic_points(18.0, 1.0, np.random.default_rng(0)), (len(bench.DESIGNS), 1))  # as criticism.py
    fields = {name: kept_fields(bench, Path(folder), name, args.case) for folder, name in (args.data, args.against)}

    def surface(field: np.ndarray) -> np.ndarray:  # (n_designs * n_points, 2)
        return field[..., :2].reshape(-1, 2)

    name, reference = fields
    data, against = (surface(bench.combined_data(n, p)) for n, p in fields.items())
    record = {
        "command": "python benchmarks/limit_data.py --data {} {} --against {} {} --case {}".format(
            *args.data, *args.against, args.case
        ),
        "case": args.case,
        f"{name} against {reference}": convergence.band_changes(data, against, xy),
        **{
            f"{n}: finer mesh against coarser": convergence.band_changes(surface(p[1]), surface(p[0]), xy)
            for n, p in fields.items()
            if n in bench.LIMITS
        },
    }
    args.results.write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
