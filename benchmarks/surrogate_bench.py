"""Surrogate benchmark: PC counts, held-out accuracy, fit time and batched prediction time.

    python benchmarks/surrogate_bench.py --data out/study/study.h5 [--fractions 0.1 0.2]

For every GP training fraction: fit on the training materials, validate on the test
materials, time one batched prediction of 1,000 parameter sets (mean fields; and mean +
variance of the weights). Results are merged into benchmarks/results/surrogate.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "surrogate.json"


def time_prediction(emulator, n: int = 1000, repeats: int = 5, threads: int = 2) -> dict:
    torch.set_num_threads(threads)
    rng = np.random.default_rng(0)
    params = rng.uniform(emulator.lower[:5], emulator.upper[:5], size=(n, 5))
    emulator.predict_fields(params, [0.05, -0.05], 1.0)  # warm-up
    best_fields = min(_timed(lambda: emulator.predict_fields(params, [0.05, -0.05], 1.0)) for _ in range(repeats))
    from surrogate.emulator import model_inputs

    x = torch.as_tensor(model_inputs(params, [0.05, -0.05], 1.0))
    with torch.no_grad():
        best_var = min(_timed(lambda: emulator.predict_weights(x, return_var=True)) for _ in range(repeats))
    return {
        "batch": n,
        "fields_mean_ms": 1e3 * best_fields,
        "weights_mean_and_variance_ms": 1e3 * best_var,
        "torch_threads": torch.get_num_threads(),
    }


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    from skinfem.io import StrainDataset
    from surrogate.emulator import fit_emulator
    from surrogate.validation import validate

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path)
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.1])
    parser.add_argument("--restarts", type=int, default=2)
    parser.add_argument("--save", type=Path, help="save the emulator of the first fraction here")
    parser.add_argument("--predict-only", type=Path, help="only time predictions of this emulator directory")
    args = parser.parse_args()
    if args.predict_only:
        from surrogate.emulator import Emulator

        emulator = Emulator.load(args.predict_only)
        timings = {t: time_prediction(emulator, threads=t) for t in (1, 2)}
        print(json.dumps(timings, indent=2))
        results = json.loads(RESULTS.read_text())
        results[f"prediction_{args.predict_only.name}"] = timings
        RESULTS.write_text(json.dumps(results, indent=2) + "\n")
        return
    data = StrainDataset.open(args.data)
    rows = []
    for k, fraction in enumerate(args.fractions):
        start = time.perf_counter()
        emulator = fit_emulator(data, gp_fraction=fraction, restarts=args.restarts)
        fit_seconds = time.perf_counter() - start
        if args.save and k == 0:
            emulator.save(args.save)
        report, _ = validate(emulator, data)
        row = {
            "dataset": str(args.data),
            "config": data.config.name,
            "gp_fraction": fraction,
            "n_gp_rows": emulator.provenance.n_gp_rows,
            "n_training_rows": emulator.provenance.n_training_rows,
            "n_components": emulator.n_weights,
            "explained_variance_at_M": {
                c: float(np.cumsum(p.explained_variance_ratio_)[p.n_components_ - 1]) for c, p in emulator.pcas.items()
            },
            "fit_seconds": fit_seconds,
            "validation": report.to_json()["components"],
            "prediction": time_prediction(emulator),
        }
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "validation"}), flush=True)
        for c, r in report.components.items():
            print(c, "R2", np.round(r.r2_per_pc, 4).tolist(), "rmse", r.field_rmse, "floor", r.pca_floor_rmse)
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    results[data.config.name] = rows
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
