"""Command line of inference: ``skinid infer``, ``noise``, ``study test-set|setups|noise``, ``check``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _add_sampler(p: argparse.ArgumentParser) -> None:
    p.add_argument("--chains", type=int, default=4)
    p.add_argument("--warmup", type=int, default=500)
    p.add_argument("--draws", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=2, help="chains run in parallel (processes)")
    p.add_argument("--gp-variance", choices=["exact", "mode"], default="exact",
                   help="GP variance at every step (exact) or fixed at the mode (fast)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _ints(text: str | None) -> list[int] | None:
    return None if text is None else [int(v) for v in text.replace(",", " ").split()]


def build_parser(prog: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    if prog.endswith("infer"):
        parser.add_argument("--emulator", type=Path, required=True, help="emulator directory")
        src = parser.add_mutually_exclusive_group(required=True)
        src.add_argument("--data", type=Path, help="dataset (.h5): observe one of its materials")
        src.add_argument("--measurement", type=Path, nargs="+", help="measurement CSV file(s)")
        parser.add_argument("--material", type=int, help="with --data: material index")
        parser.add_argument("--designs", help="with --data: design indices, e.g. '2' or '0,2,4' (default: all)")
        parser.add_argument("--frames", help="with --data: frame indices, e.g. '-1' or '-3,-2,-1' (default: -1)")
        parser.add_argument("--noise", choices=["halfcauchy", "known"], default="halfcauchy",
                            help="unknown noise per component, or the measurement's sd columns")
        parser.add_argument("--out", type=Path, required=True, help="output directory")
        _add_sampler(parser)
        return parser
    if prog.endswith("noise"):
        parser.add_argument("--data", type=Path, required=True, help="clean dataset (.h5)")
        parser.add_argument("--length", type=float, required=True, help="correlation length [mm]")
        parser.add_argument("--level", type=float, required=True,
                            help="amplitude as a fraction of the max |strain| of the training data")
        parser.add_argument("--seed", type=int, default=0)
        parser.add_argument("--out", type=Path, required=True, help="noisy dataset (.h5)")
        return parser
    if prog.endswith("check"):
        parser.add_argument("--measurement", type=Path, nargs="+", required=True, help="measurement CSV file(s)")
        parser.add_argument("--config", help="preset or TOML of the mesh the check runs on "
                                             "(default: the emulator's dataset configuration)")
        start = parser.add_mutually_exclusive_group()
        start.add_argument("--emulator", type=Path, help="emulator directory: its posterior mode is the start "
                                                         "(default: the best of 5 spread points)")
        start.add_argument("--start", type=float, nargs=5, metavar=("MU", "K1", "K2", "KAPPA", "THETA"),
                           help="skin parameters to start the calibration from (MPa, MPa, -, -, deg; "
                                "default: the best of 5 spread points)")
        parser.add_argument("--out", type=Path, required=True,
                            help="report directory (its fe_runs/ keeps finished FE runs: rerunning resumes)")
        parser.add_argument("--noise-sd", type=float, nargs=3, metavar=("XX", "YY", "XY"),
                            help="measurement noise sd per component [strain] (default: the files' sd columns)")
        parser.add_argument("--noise-length", type=float, default=0.0,
                            help="noise correlation length [mm] (default 0: independent points)")
        parser.add_argument("--noise-nugget", type=float, default=0.0,
                            help="uncorrelated share of the noise variance in [0, 1] (default 0)")
        parser.add_argument("--dic-window", type=float, default=1.0,
                            help="the DIC strain window (virtual strain gauge) side [mm] (default 1)")
        parser.add_argument("--spacing", type=float, default=1.0,
                            help="use one measured point per square of this side [mm] (default 1)")
        parser.add_argument("--no-discretisation", action="store_true",
                            help="skip the refined-mesh estimate of the check's discretisation error")
        parser.add_argument("--refine", choices=["uniform", "edge"], default="uniform",
                            help="the estimate's refined mesh: every size halved, or only the membrane-edge "
                                 "cells (for fine or quadratic meshes); layers doubled in both (default uniform)")
        parser.add_argument("--candidates", nargs="+", help="effects to test (default: all registered)")
        parser.add_argument("--add", nargs="+", default=[], help="effects to add, in order, e.g. pre_stretch")
        parser.add_argument("--increments", type=int, help="load increments of the FE runs (default: config's)")
        parser.add_argument("--confirm", type=int, default=2, help="top candidates calibrated for real")
        parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
        return parser
    sub = parser.add_subparsers(dest="study", required=True)
    p = sub.add_parser("test-set", help="posteriors of every test material for one setup")
    p.add_argument("--emulator", type=Path, required=True)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--designs", required=True, help="design indices, e.g. '2'")
    p.add_argument("--frames", default="-1", help="frame indices (default -1)")
    p.add_argument("--materials", help="subset of materials (default: the test split)")
    p.add_argument("--out", type=Path, required=True)
    _add_sampler(p)
    p = sub.add_parser("setups", help="single vs multi-frame vs multi-membrane (the paper's Fig. 8)")
    p.add_argument("--emulator", type=Path, required=True)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--design", type=int, required=True, help="the single design")
    p.add_argument("--n", type=int, default=3, help="frames / membranes in the multi setups")
    p.add_argument("--others", help="the multi-membrane setup's other designs, e.g. '0,13' "
                                    "(default: the n - 1 designs farthest apart in alpha)")
    p.add_argument("--materials", help="subset of materials (default: the test split)")
    p.add_argument("--out", type=Path, required=True)
    _add_sampler(p)
    p = sub.add_parser("noise", help="the paper's 9 noise cases: PCA, GP R², test-set posteriors")
    p.add_argument("--data", type=Path, required=True, help="clean dataset (.h5)")
    p.add_argument("--design", type=int, required=True, help="design index observed (last frame)")
    p.add_argument("--lengths", type=float, nargs="+", default=[0.1, 1.0, 5.0], help="[mm]")
    p.add_argument("--levels", type=float, nargs="+", default=[0.01, 0.05, 0.10])
    p.add_argument("--materials", help="subset of test materials (default: the test split)")
    p.add_argument("--gp-fraction", type=float, default=0.1)
    p.add_argument("--restarts", type=int, default=2)
    p.add_argument("--out", type=Path, required=True)
    _add_sampler(p)
    return parser


def settings_of(args):
    from inference.studies import SamplerSettings

    return SamplerSettings(chains=args.chains, warmup=args.warmup, draws=args.draws, seed=args.seed,
                           n_jobs=args.jobs, gp_variance=args.gp_variance, progress=not args.quiet)


def print_summary(summary: dict, out: Path) -> None:
    print(f"{'':>8} {'median':>10} {'95 % interval':>24} {'R-hat':>6} {'ESS':>6} {'true':>10}")
    for name, e in summary["parameters"].items():
        true = f"{e['true']:.4g}" if "true" in e else ""
        print(f"{name:>8} {e['median']:>10.4g} [{e['q2.5']:>10.4g}, {e['q97.5']:>10.4g}] "
              f"{e['r_hat']:>6.3f} {min(e['ess_bulk'], e['ess_tail']):>6.0f} {true:>10}")
    for w in summary["warnings"]:
        print(f"warning: {w}")
    print(f"{summary['divergences']} divergences, {summary['seconds']:.1f} s\nwrote {out}/posterior.nc, summary.json, corner.png")


def cmd_infer(args) -> None:
    from inference.observations import from_dataset, from_measurements
    from inference.studies import posterior_of
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    emulator = Emulator.load(args.emulator)
    if args.data is not None:
        if args.material is None:
            raise ValueError("--data needs --material")
        obs = from_dataset(StrainDataset.open(args.data), args.material, _ints(args.designs), _ints(args.frames))
    else:
        half = float(emulator.meta.get("block_half_length", 25.0))
        obs = from_measurements(args.measurement, emulator.xy, half)
    summary = posterior_of(emulator, obs, settings_of(args), args.out, noise=args.noise)
    print_summary(summary, args.out)


def cmd_study(args) -> None:
    from inference.studies import setups_plot, spread_designs, test_set_study
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    materials = _ints(args.materials)
    if args.study == "noise":
        from inference.studies import noise_study

        data = StrainDataset.open(args.data)
        noise_study(data, args.out, args.design, settings_of(args), tuple(args.lengths), tuple(args.levels),
                    materials, {"gp_fraction": args.gp_fraction, "restarts": args.restarts})
        print(f"wrote {args.out}/README.md")
        return
    emulator, data = Emulator.load(args.emulator), StrainDataset.open(args.data)
    if args.study == "test-set":
        res = test_set_study(emulator, data, _ints(args.designs), _ints(args.frames), settings_of(args),
                             args.out, materials)
        print(json.dumps(res, indent=2))
        print(f"wrote {args.out}/study.json and accuracy.png")
        return
    others = _ints(args.others) if args.others else spread_designs(data.designs, args.design, args.n)[1:]
    bad = [j for j in [args.design, *others] if not 0 <= j < len(data.designs)]
    if bad:  # before the single and multi-frame studies run, not after
        raise ValueError(f"design {bad[0]} is not in [0, {len(data.designs)}) of {args.data}")
    setups = {
        "single": ([args.design], [-1]),
        f"{args.n} frames": ([args.design], list(range(-args.n, 0))),
        f"{1 + len(others)} membranes": ([args.design, *others], [-1]),
    }
    results = {
        label: test_set_study(emulator, data, d, f, settings_of(args), args.out / label.replace(" ", "_"),
                              materials, label)
        for label, (d, f) in setups.items()
    }
    setups_plot(results, args.out / "setups.png")
    print(json.dumps({k: v["median_interval_share_of_prior"] for k, v in results.items()}, indent=2))
    print(f"wrote {args.out}/setups.png")


def cmd_noise(args) -> None:
    from inference.noise import add_noise
    from skinfem.io import StrainDataset

    if args.out.exists():
        raise ValueError(f"'{args.out}' exists; choose a new --out")
    data = StrainDataset.open(args.data)
    add_noise(data, args.out, args.length, args.level, args.seed)
    print(f"added noise (length {args.length} mm, level {args.level:.0%}, seed {args.seed}) to "
          f"{int((data.status == 1).sum())} simulations\nwrote {args.out}")


def check_inputs(args):
    """Settings, configuration, prior box, emulator, measurements and noise of ``skinid check``."""
    from inference.criticism.check import CheckSettings
    from inference.criticism import NoiseModel
    from inference.observations import check_field_of_view, read_measurement, thin
    from skinfem.config import PARAM_NAMES, config_from_toml, load_config
    from skinfem.dic import StrainGauge
    from skinfem.effects import EFFECTS, effect_parameters
    from surrogate.emulator import Emulator

    settings = CheckSettings(candidates=args.candidates or list(EFFECTS), add=args.add, increments=args.increments,
                             confirm=args.confirm, gauge=StrainGauge(args.dic_window), spacing=args.spacing,
                             discretisation=not args.no_discretisation, refinement=args.refine)
    emulator = None if args.emulator is None else Emulator.load(args.emulator)
    if args.config is not None:
        config = load_config(args.config)
    elif emulator is not None:
        config = config_from_toml(emulator.meta["dataset_config"])
    else:
        raise ValueError("give the mesh to check on with --config (a preset or TOML), or an --emulator")
    bounds = (emulator.param_bounds if emulator is not None
              else np.array([config.sweep.bounds[n] for n in PARAM_NAMES]))
    if args.start is not None:
        outside = [f"{n} = {v:g} not in [{lo:g}, {hi:g}]" for n, v, (lo, hi) in zip(PARAM_NAMES, args.start, bounds)
                   if not lo <= v <= hi]
        if outside:
            raise ValueError(f"--start is outside the prior box: {'; '.join(outside)}")
        settings.start = np.array(args.start)
    half = config.mesh.membrane_size / 2
    n_params = 5 + len(effect_parameters(settings.add))
    measurements = [thin(read_measurement(p, config.mesh.length / 2), args.spacing) for p in args.measurement]
    for m in measurements:
        check_field_of_view(m, half, settings.band or 2 * config.mesh.h_membrane, n_params)
    if args.noise_sd is not None:
        sd = np.array(args.noise_sd)
    elif all(m.sd is not None for m in measurements):
        sd = np.median(np.concatenate([m.sd for m in measurements]), axis=0)
    else:
        raise ValueError("the measurements have no sd_exx, sd_eyy, sd_exy columns: give --noise-sd XX YY XY")
    noise = NoiseModel(sd, args.noise_length, args.noise_nugget)
    return settings, config, bounds, emulator, measurements, noise


def cmd_check(args) -> None:
    from mpi4py import MPI

    from inference.criticism.check import run_check
    from inference.criticism.report import write_report
    from skinfem.parallel import collective

    comm = MPI.COMM_WORLD
    settings, config, bounds, emulator, measurements, noise = collective(comm, lambda: check_inputs(args))
    result = run_check(measurements, noise, settings, config, bounds, emulator, args.mesh_dir, comm,
                       cache_dir=Path(args.out) / "fe_runs")
    if comm.rank == 0:
        path = write_report(result, args.out)
        print(result.diagnosis.text)
        for v in result.versions:
            m = v.metrics
            print(f"{v.calibration.label:>30}: RMSE {m.rmse:.3e}, chi2/dof {m.chi2_per_dof:.3f}, "
                  f"PPC p {m.ppc_p:.3f}, {'structured' if m.structured else 'consistent with noise'}")
        print(f"wrote {path}")


COMMANDS = {"infer": cmd_infer, "study": cmd_study, "noise": cmd_noise, "check": cmd_check}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = argv[0] if argv and argv[0] in COMMANDS else "infer"
    if argv and argv[0] in COMMANDS:
        argv = argv[1:]
    args = build_parser(f"skinid {command}").parse_args(argv)
    from inference.observations import MeasurementError
    from skinfem.parallel import CollectiveError, abort_on_uncaught

    abort_on_uncaught(f"skinid {command}")
    try:
        COMMANDS[command](args)
    except CollectiveError as exc:  # raised on every rank: rank 0 says it once
        if _rank() == 0:
            print(f"skinid {command}: error: {exc}", file=sys.stderr)
        return 2
    except (MeasurementError, ValueError, FileNotFoundError) as exc:
        print(f"skinid {command}: error: {exc}", file=sys.stderr)
        _abort_other_ranks(2)
        return 2
    return 0


def _rank() -> int:
    from mpi4py import MPI

    return MPI.COMM_WORLD.rank


def _abort_other_ranks(code: int) -> None:
    """An error on one rank of several: end the whole job (the others may wait in a collective)."""
    from mpi4py import MPI

    if MPI.COMM_WORLD.size > 1:
        sys.stderr.flush()
        MPI.COMM_WORLD.Abort(code)


if __name__ == "__main__":
    sys.exit(main())
