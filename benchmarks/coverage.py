"""Coverage of the posterior intervals on held-out materials, per observation setup and noise.

    python benchmarks/coverage.py --emulator EMU --data TEST.h5 [--setups single frames membranes]
        [--noise-sd 0 0.002] [--emulator-error on scaled shift off shift-scaled] [--n 3]
        [--store out/coverage] [--starts 1] [--results benchmarks/results/coverage_fresh]
        [--data-from model] [--noise-seeds 1]

For every setup x noise sd x error model, ``inference.coverage.coverage_study`` runs every case
(test materials of TEST.h5 x starting designs; resumable in ``--store``); its summary (with the
cases run by this call and their seconds per case, when it ran any) is written to
<results>/<label>.json (default benchmarks/results/coverage/) and its rank histograms to
ranks_<label>.png there. Sampler: 2 chains x 500 draws after 300 warm-up in one process (run
setups or halves of ``--materials`` in parallel processes instead), the GP variance fixed at the
mode (the default 4 x 1000 exact-variance posterior is too slow for hundreds of cases on 2 cores).
``--data-from model``: each case's truth drawn from the prior and its PC weights from the
likelihood (``inference.coverage.run_case``), with a stated ``--noise-sd`` > 0: the posterior's
own model, calibrated by construction; labels end in ``_model-data``. ``--noise-seeds K``: K cases
per material and starting design, each with its own noise draw (and with ``--data-from model`` its
own truth and weights); labels end in ``_seedsK`` when K > 1. ``shift-scaled``, measured here
only: ``shift`` with the material scale lambda sampled too (heavier tails between materials).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "coverage"
# an error model the product does not offer, measured here: the material scale on `shift`
DIAGNOSTIC_ERRORS = {"shift-scaled": {"emulator_error": True, "emulator_scale": True, "emulator_shift": True}}
TIMING = ("cases_run", "seconds_per_case")


def main() -> None:
    from inference.studies import EMULATOR_ERRORS, SamplerSettings, emulator_error_flags
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--emulator", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True, help="dataset of test materials")
    parser.add_argument("--setups", nargs="+", default=["single", "frames", "membranes"])
    parser.add_argument("--noise-sd", type=float, nargs="+", default=[0.0])
    parser.add_argument("--emulator-error", nargs="+", choices=[*EMULATOR_ERRORS, *DIAGNOSTIC_ERRORS], default=["on"])
    parser.add_argument("--store", type=Path, default=Path("out/coverage"))
    parser.add_argument(
        "--materials",
        type=int,
        nargs="+",
        help="only these test materials (a second process can share a study's cases)",
    )
    parser.add_argument("--n", type=int, default=3, help="frames or membranes observed (frames, membranes setups)")
    parser.add_argument("--starts", type=int, help="starting designs per material (default: all; 1: independent cases)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder of the summaries and rank histograms")
    parser.add_argument(
        "--data-from",
        choices=["fe", "model"],
        default="fe",
        help="the test materials' FE strains, or truths from the prior and weights from the posterior's own model",
    )
    parser.add_argument("--noise-seeds", type=int, default=1, help="cases per material and design (noise draws)")
    args = parser.parse_args()
    if args.noise_seeds < 1:
        parser.error(f"--noise-seeds must be >= 1, got {args.noise_seeds}")
    if args.data_from == "model" and min(args.noise_sd) <= 0:
        parser.error("--data-from model needs a stated --noise-sd > 0")
    emulator, data = Emulator.load(args.emulator), StrainDataset.open(args.data)
    args.results.mkdir(exist_ok=True)
    for error in args.emulator_error:
        settings = SamplerSettings(
            chains=2,
            warmup=300,
            draws=500,
            n_jobs=1,
            gp_variance="mode",
            progress=False,
            **(DIAGNOSTIC_ERRORS.get(error) or emulator_error_flags(error)),
        )
        for sd in args.noise_sd:
            for setup in args.setups:
                count = "" if args.n == 3 or setup == "single" else str(args.n)
                source = "_model-data" if args.data_from == "model" else ""
                seeds = f"_seeds{args.noise_seeds}" if args.noise_seeds > 1 else ""
                label = f"{setup}{count}_noise{sd:g}_error-{error}{source}{seeds}"
                summary = run_study(args, emulator, data, setup, settings, sd, label)
                print(label, {n: (e.coverage_50, e.coverage_95) for n, e in summary.parameters.items()}, flush=True)


def material_scale(emulator) -> list[float] | None:
    """(shape, rate) of the emulator's material scale, or None (an emulator without one)."""
    excess = emulator.held_out_excess
    return None if excess is None or excess.material_scale is None else list(excess.material_scale)


def own_cases(cases: Path, materials: list[int] | None) -> int:
    """Finished cases in ``cases`` of ``materials`` (None: all), not those of another process
    sharing the store (case files are named m<material>_...)."""
    names = [p.name for p in cases.glob("m*.json")]
    return len(names) if materials is None else sum(int(n.split("_")[0][1:]) in materials for n in names)


def run_study(args, emulator, data, setup: str, settings, sd: float, label: str):
    """One coverage study, written to ``<results>/<label>.json`` with the seconds per case of the
    cases this call ran (a pass that only summarises keeps the previous file's timing)."""
    from inference.coverage import coverage_study

    cases = args.store / label / "cases"
    done_before = own_cases(cases, args.materials)
    start = time.perf_counter()
    summary = coverage_study(
        emulator,
        data,
        setup,
        settings,
        args.store / label,
        n=args.n,
        noise_sd=sd,
        noise_seeds=args.noise_seeds,
        materials=args.materials,
        starts=args.starts,
        data_from=args.data_from,
    )
    run = own_cases(cases, args.materials) - done_before
    timing = {"cases_run": run, "seconds_per_case": (time.perf_counter() - start) / run} if run else {}
    path = args.results / f"{label}.json"
    if not run and path.exists():
        timing = {k: v for k, v in json.loads(path.read_text()).items() if k in TIMING}
    record = {
        **summary.to_json(),
        **timing,
        "emulator": str(args.emulator),
        "material_scale": material_scale(emulator) if settings.emulator_scale else None,
        "parameter_shift": emulator.held_out_excess.parameter_shift.to_json() if settings.emulator_shift else None,
        "data": str(args.data),
        "starts_per_material": args.starts,
    }
    path.write_text(json.dumps(record, indent=2) + "\n")
    shutil.copy(args.store / label / "ranks.png", args.results / f"ranks_{label}.png")
    return summary


if __name__ == "__main__":
    main()
