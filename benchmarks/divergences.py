"""Where a posterior's NUTS transitions diverge, and what smaller steps cost.

    python benchmarks/divergences.py --emulator out/study/emu --data out/study/study.h5 --case 44 4

One single-observation posterior (test material, design index; last frame, noise-free data,
unknown noise, GP variance at the mode, 2 chains x 500 draws after 300 warm-up: the coverage
study's sampler) sampled at NUTS's default target acceptance without the rerun, with a longer
warm-up, and at the rerun's target acceptance (``inference.sampling.RESAMPLE_ACCEPT``). Per run
and chain: divergences, step size, leapfrog steps per draw, the spread of the unconstrained
draws (logit of the prior box for the skin parameters, log for the noise sigmas) and the median
log sigma of all and of the divergent draws. Results: benchmarks/results/divergences.json,
rewritten after each run.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "divergences.json"


@dataclass(frozen=True)
class ChainRun:
    divergences: int
    step_size: float
    leapfrog_steps_per_draw: float
    unconstrained_sd: list[float]  # per coordinate, in the posterior's names' order
    median_log_sigma: list[float]  # per noise sigma
    median_log_sigma_divergent: list[float] | None


def chain_runs(posterior, samples) -> list[ChainRun]:
    u = posterior.unconstrain(torch.as_tensor(samples.draws)).numpy()  # (chains, draws, dim)
    out = []
    for c in range(u.shape[0]):
        log_sigma, diverging = u[c, :, 5 : 5 + posterior.n_sigma], samples.diverging[c]
        out.append(
            ChainRun(
                int(diverging.sum()),
                float(samples.step_sizes[c]),
                float(samples.stats["n_steps"][c].mean()),
                np.round(u[c].std(0), 3).tolist(),
                np.round(np.median(log_sigma, 0), 2).tolist(),
                np.round(np.median(log_sigma[diverging], 0), 2).tolist() if diverging.any() else None,
            )
        )
    return out


def main() -> None:
    from inference.model import ObservedWeights, SkinPosterior
    from inference.observations import from_dataset
    from inference.sampling import RESAMPLE_ACCEPT, TARGET_ACCEPT, sample_posterior
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--emulator", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--case", type=int, nargs=2, required=True, metavar=("MATERIAL", "DESIGN"))
    args = parser.parse_args()
    emulator, data = Emulator.load(args.emulator), StrainDataset.open(args.data)
    material, design = args.case
    if not (0 <= material < len(data.params) and 0 <= design < len(data.designs)):
        parser.error(f"--case: material must be in [0, {len(data.params)}), design in [0, {len(data.designs)})")
    observations = from_dataset(data, material, [design], [-1])
    record = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    runs = {}
    for name, target, warmup in [
        ("default", TARGET_ACCEPT, 300),
        ("default, 600 warm-up", TARGET_ACCEPT, 600),
        ("rerun", RESAMPLE_ACCEPT, 300),
    ]:
        posterior = SkinPosterior(emulator, ObservedWeights.project(emulator, observations), gp_variance="mode")
        settings = {"chains": 2, "warmup": warmup, "draws": 500, "n_jobs": 1, "progress": False}
        samples = sample_posterior(posterior, **settings, target_accept=target, resample=False)
        runs[name] = {
            "target_accept": target,
            "warmup": warmup,
            "seconds": samples.seconds,
            "chains": [asdict(r) for r in chain_runs(posterior, samples)],
        }
        print(name, [r["divergences"] for r in runs[name]["chains"]], f"{samples.seconds:.0f} s", flush=True)
        record[f"{args.data} material {material} design {design}"] = {
            "emulator": str(args.emulator),
            "names": list(posterior.names),
            "truth": data.params[material].tolist(),
            "runs": runs,
        }
        RESULTS.write_text(json.dumps(record, indent=2) + "\n")  # each finished run is kept


if __name__ == "__main__":
    main()
