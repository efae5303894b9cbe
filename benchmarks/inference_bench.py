"""Inference benchmark: wall time and ESS per second of a single-observation posterior.

    python benchmarks/inference_bench.py --emulator EMU --data DATA.h5 [--paper-iterations 2000]

Runs, on the first test material and the "mixed" design (0.05, -0.05), last frame:
- skinid: 4 chains x 1,000 draws after 500 warm-up, chains in 2 processes, one torch thread
  each, NUTS on the torch potential, started at the posterior mode with the Laplace metric;
  with the GP variance exact at every step and fixed at the mode;
- the paper's configuration: one chain, the likelihood evaluated through scikit-learn
  (no gradient reaches the sampler), ``--paper-iterations`` warm-up + the same number of
  draws (the paper used 10,000 + 10,000; the time of that is extrapolated linearly).
Results are merged into benchmarks/results/inference.json (``--skip-paper`` keeps the
recorded paper-configuration run and recomputes the ESS-per-second ratios against it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "inference.json"


def make_paper_posterior(emulator, observed):
    """The same density, its likelihood computed by scikit-learn outside autograd."""
    from inference.model import SkinPosterior

    class SklearnLikelihood(SkinPosterior):
        def log_likelihood(self, params, sigma, scale=1.0):  # no emulator error: scale is 1
            x = np.concatenate(
                [np.repeat(params.detach().numpy()[None], len(self.design_inputs), 0), self.design_inputs.numpy()], 1
            )
            unit = self.emulator.scale(x)
            preds = [gp.predict(unit, return_std=True) for gp in self.emulator.sklearn_gps]
            mean = np.stack([p[0] for p in preds], 1)
            var = np.stack([p[1] ** 2 for p in preds], 1)
            s = sigma.detach().numpy()[self.component_of_weight.numpy()] ** 2
            total = var + s
            r = self.weights.numpy() - mean
            return torch.tensor(-0.5 * np.sum(r**2 / total + np.log(2 * np.pi * total)), dtype=torch.float64)

    return SklearnLikelihood(emulator, observed, emulator_error=False)  # the paper carried no emulator error


def main() -> None:
    """The benchmark's steps in order (options, runs, the results file): longer than a screen on purpose."""
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset
    from inference.sampling import sample_posterior
    from inference.studies import EMULATOR_ERRORS, emulator_error_flags, resolve_emulator_error
    from skinfem.io import StrainDataset, design_index
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--emulator", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--paper-iterations", type=int, default=2000)
    parser.add_argument("--skip-paper", action="store_true")
    parser.add_argument(
        "--variants",
        nargs="+",
        default=["exact", "mode"],
        choices=["exact", "mode"],
        help="GP-variance treatments to time",
    )
    parser.add_argument(
        "--emulator-error",
        default="auto",
        choices=["auto", *EMULATOR_ERRORS],
        help="the emulator error model (auto: skinid infer's default for this emulator)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    emulator, data = Emulator.load(args.emulator), StrainDataset.open(args.data)
    material = int(np.flatnonzero(data.split)[0])
    mixed = design_index(data.designs, (0.05, -0.05), data.path)
    observed = ObservedWeights.project(emulator, from_dataset(data, material, [mixed], [-1]))
    results = {
        "emulator": str(args.emulator),
        "n_gp_rows": emulator.provenance.n_gp_rows,
        "n_gps": int(sum(emulator.n_weights.values())),
        "material": material,
    }
    error = resolve_emulator_error(args.emulator_error, emulator)
    suffix = "" if error == "on" else f"_error_{error}"
    for gp_variance in args.variants:
        post = SkinPosterior(emulator, observed, gp_variance=gp_variance, **emulator_error_flags(error))
        s = sample_posterior(post, chains=4, warmup=500, draws=1000, seed=0, n_jobs=2, progress=False)
        summary = s.summary()
        results[f"skinid_gp_variance_{gp_variance}{suffix}"] = {
            "emulator": str(args.emulator),
            "emulator_error": error,
            "chains": 4,
            "warmup": 500,
            "draws": 1000,
            "seconds": s.seconds,
            "max_r_hat": summary.max_r_hat,
            "min_ess": summary.min_ess,
            "ess_per_second": summary.min_ess / s.seconds,
            "divergences": summary.divergences,
            "gp_variance_over_posterior": summary.to_json()["gp_variance_over_posterior"],
            "medians": {n: e.median for n, e in summary.parameters.items()},
        }
        print(gp_variance, json.dumps(results[f"skinid_gp_variance_{gp_variance}{suffix}"]), flush=True)
    if not args.skip_paper:
        n = args.paper_iterations
        post = make_paper_posterior(emulator, observed)
        s = sample_posterior(post, chains=1, warmup=n, draws=n, seed=0, n_jobs=1, progress=False)
        summary = s.summary()
        results["paper_configuration"] = {
            "chains": 1,
            "warmup": n,
            "draws": n,
            "seconds": s.seconds,
            "seconds_extrapolated_to_10000_plus_10000": s.seconds * 10000 / n,
            "min_ess": summary.min_ess,
            "ess_per_second": summary.min_ess / s.seconds,
            "medians": {k: e.median for k, e in summary.parameters.items()},
        }
        print("paper", json.dumps(results["paper_configuration"]), flush=True)
    from skinfem.config import config_from_toml

    all_results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    name = config_from_toml(emulator.provenance.dataset_config).name
    results = {**all_results.get(name, {}), **results}  # --skip-paper keeps the recorded paper run
    if "paper_configuration" in results:
        paper_rate = results["paper_configuration"]["ess_per_second"]
        for v in args.variants:
            rate = results[f"skinid_gp_variance_{v}{suffix}"]["ess_per_second"]
            results[f"ess_per_second_ratio_{v}{suffix}_over_paper"] = rate / paper_rate
    all_results[name] = results
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(all_results, indent=2) + "\n")


if __name__ == "__main__":
    main()
