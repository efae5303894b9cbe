"""Command line of inference: ``skinid infer``, ``noise``, ``study``, ``check``, ``measurement``."""

from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path

import numpy as np

from inference.cli_inputs import (
    check_indices,
    check_input_paths,
    check_same_mesh,
    check_sampler,
    check_strain_scale,
    design_indices,
    int_list,
    one_design,
)
from inference.cli_parsers import build_parser
from skinfem.cli import refuse


def settings_of(args, emulator=None):
    """The sampler settings of the command line; ``--emulator-error auto`` resolved for
    ``emulator`` (None: emulators the command fits itself)."""
    from inference.studies import SamplerSettings, emulator_error_flags, resolve_emulator_error

    return SamplerSettings(
        chains=args.chains,
        warmup=args.warmup,
        draws=args.draws,
        seed=args.seed,
        n_jobs=args.jobs,
        gp_variance=args.gp_variance,
        progress=not args.quiet,
        **emulator_error_flags(resolve_emulator_error(args.emulator_error, emulator)),
    )


def print_summary(summary, out: Path) -> None:
    """The table of an :class:`inference.posterior_file.PosteriorSummary`, its warnings and error budget."""
    width = max(map(len, summary.parameters))
    print(f"{'':>{width}} {'median':>10} {'95 % interval':>24} {'R-hat':>6} {'ESS':>6} {'true':>10}")
    for name, e in summary.parameters.items():
        true = "" if e.true is None else f"{e.true:.4g}"
        interval = f"[{e.q2_5:>10.4g}, {e.q97_5:>10.4g}]"
        print(f"{name:>{width}} {e.median:>10.4g} {interval} {e.r_hat:>6.3f} {e.ess:>6.0f} {true:>10}")
    for w in summary.warnings:
        print(f"warning: {w}")
    if summary.error_budget_statement:
        print(summary.error_budget_statement[0].upper() + summary.error_budget_statement[1:])
    print(f"{summary.divergences} divergences, {summary.seconds:.1f} s")
    print(f"wrote {out}/posterior.nc, summary.json, corner.png")


def cmd_infer(args) -> None:
    from inference.observations import from_dataset, map_to_cells, read_measurement
    from inference.studies import posterior_of
    from skinfem.config import config_from_toml
    from skinfem.io import StrainDataset
    from skinfem.outputs import check_output
    from surrogate.emulator import Emulator

    check_output(args.out, args.force, directory=True)
    check_sampler(args)
    emulator = Emulator.load(args.emulator)
    if args.data is not None:
        if args.material is None:
            raise ValueError("--data needs --material")
        data = StrainDataset.open(args.data)
        check_same_mesh(data, emulator)
        designs = design_indices(args.designs, data.designs, args.data)
        obs = from_dataset(data, args.material, designs, int_list(args.frames, "--frames"))
    else:
        membrane_half = config_from_toml(emulator.provenance.dataset_config).mesh.membrane_size / 2
        measurements = [read_measurement(p, emulator.provenance.block_half_length) for p in args.measurement]
        for m in measurements:
            check_strain_scale(m, membrane_half)
        obs = [map_to_cells(m, emulator.xy) for m in measurements]
    summary = posterior_of(emulator, obs, settings_of(args, emulator), args.out, noise=args.noise)
    print_summary(summary, args.out)


def cmd_study(args) -> None:
    from skinfem.io import StrainDataset
    from skinfem.outputs import check_output, remove_output
    from surrogate.emulator import Emulator

    check_output(args.out, args.force, directory=True, resume=args.resume)
    check_sampler(args)
    data = StrainDataset.open(args.data)
    emulator = None if args.study == "noise" else Emulator.load(args.emulator)
    if emulator is not None:
        check_same_mesh(data, emulator)
    n_mat, n_des, n_frames, _ = data.shape
    check_indices("--materials", int_list(args.materials, "--materials"), n_mat, args.data, negative=False)
    if args.study in ("setups", "noise"):
        args.designs = one_design(args.designs, data.designs, args.data)
    elif args.study == "test-set":
        args.designs = design_indices(args.designs, data.designs, args.data)
        check_indices("--designs", args.designs, n_des, args.data)
        check_indices("--frames", int_list(args.frames, "--frames"), n_frames, args.data)
    if args.study == "noise":
        _check_noise_study(args, n_des)
    designs = _setups_designs(args, data) if args.study == "setups" else None
    if args.study == "coverage":
        _check_coverage(args, {"frames": n_frames, "membranes": n_des}.get(args.setup), n_des)
    if args.force:  # the inputs are read and checked: start over
        remove_output(args.out)
    if args.study == "noise":
        _noise_study(args, data)
    elif args.study == "coverage":
        _coverage(args, emulator, data)
    elif args.study == "test-set":
        _test_set(args, emulator, data)
    else:
        _setups(args, emulator, data, designs)


def _check_noise_study(args, n_designs: int) -> None:
    """Refuse the options of ``study noise`` that are out of range."""
    check_indices("--designs", [args.designs], n_designs, args.data, negative=False)
    for option, values in (("--lengths", args.lengths), ("--levels", args.levels)):
        bad = [v for v in values if not (math.isfinite(v) and v > 0)]
        if bad:
            raise ValueError(f"{option} must be positive numbers, got {bad[0]}")
    if not 0 < args.gp_fraction <= 1:
        raise ValueError(f"--gp-fraction must be in (0, 1], got {args.gp_fraction}")
    if args.restarts < 0:
        raise ValueError(f"--restarts must be >= 0, got {args.restarts}")
    if args.n_components is not None and args.n_components < 1:
        raise ValueError(f"--n-components must be >= 1, got {args.n_components}")


def _check_coverage(args, n_max: int | None, n_designs: int) -> None:
    """Refuse the options of ``study coverage`` that are out of range (n_max: the dataset's
    designs for the membranes setup, its frames for the frames setup; None: --n is not used;
    n_designs: the dataset's designs)."""
    if n_max is not None and not 1 <= args.n <= n_max:
        raise ValueError(f"--n must be in [1, {n_max}] for the {args.setup} setup of {args.data}, got {args.n}")
    if not (math.isfinite(args.noise_sd) and args.noise_sd >= 0):
        raise ValueError(f"--noise-sd must be >= 0, got {args.noise_sd}")
    if args.noise_seeds < 1:
        raise ValueError(f"--noise-seeds must be >= 1, got {args.noise_seeds}")
    if args.starts is not None and not 1 <= args.starts <= n_designs:
        raise ValueError(f"--starts must be in [1, {n_designs}], got {args.starts}")
    if args.data_from == "model" and args.noise_sd <= 0:
        raise ValueError("--data-from model needs a stated --noise-sd > 0 (an unknown sd's prior is too wide)")


def _coverage(args, emulator, data) -> None:
    from inference.coverage import coverage_study

    res = coverage_study(
        emulator,
        data,
        args.setup,
        settings_of(args, emulator),
        args.out,
        args.n,
        args.noise_sd,
        args.noise_seeds,
        int_list(args.materials, "--materials"),
        args.starts,
        args.data_from,
    )
    for name, e in res.parameters.items():
        print(
            f"{name:>6}: 95 % intervals cover {e.coverage_95:.2f} (sd {e.binomial_sd_95:.2f}), "
            f"50 % intervals {e.coverage_50:.2f} (sd {e.binomial_sd_50:.2f})"
            + ("" if e.rms_z is None else f", truth {e.rms_z:.2f} posterior sd from the mean (RMS; 1 if calibrated)")
        )
    print(f"{res.n_cases} cases of {res.n_materials} materials (sd over materials); wrote {args.out}/coverage.json")


def _noise_study(args, data) -> None:
    from inference.studies import noise_study

    noise_study(
        data,
        args.out,
        args.designs,
        settings_of(args),
        tuple(args.lengths),
        tuple(args.levels),
        int_list(args.materials, "--materials"),
        {"gp_fraction": args.gp_fraction, "restarts": args.restarts, "pca_scaling": args.pca_scaling}
        | ({} if args.n_components is None else {"n_components": args.n_components}),
    )
    print(f"wrote {args.out}/README.md")


def _test_set(args, emulator, data) -> None:
    from inference.studies import test_set_study

    res = test_set_study(
        emulator,
        data,
        args.designs,
        int_list(args.frames, "--frames"),
        settings_of(args, emulator),
        args.out,
        int_list(args.materials, "--materials"),
    )
    print(json.dumps(res.to_json(), indent=2))
    print(f"wrote {args.out}/study.json and accuracy.png")


def _setups_designs(args, data) -> list[int]:
    """The single design, then the multi-membrane setup's others, checked before any study runs."""
    from inference.studies import spread_designs

    others = (
        design_indices(args.others, data.designs, args.data, "--others")
        if args.others
        else spread_designs(data.designs, args.designs, args.n)[1:]
    )
    bad = [j for j in [args.designs, *others] if not 0 <= j < len(data.designs)]
    if bad:
        raise ValueError(f"design {bad[0]} is not in [0, {len(data.designs)}) of {args.data}")
    return [args.designs, *others]


def _setups(args, emulator, data, designs: list[int]) -> None:
    from inference.studies import setups_plot, test_set_study

    single = designs[0]
    setups = {
        "single": ([single], [-1]),
        f"{args.n} frames": ([single], list(range(-args.n, 0))),
        f"{len(designs)} membranes": (designs, [-1]),
    }
    results = {
        label: test_set_study(
            emulator,
            data,
            d,
            f,
            settings_of(args, emulator),
            args.out / label.replace(" ", "_"),
            int_list(args.materials, "--materials"),
            label,
        )
        for label, (d, f) in setups.items()
    }
    setups_plot(results, args.out / "setups.png")
    print(json.dumps({k: v.median_interval_share_of_prior for k, v in results.items()}, indent=2))
    print(f"wrote {args.out}/setups.png")


def cmd_noise(args) -> None:
    from inference.noise import add_noise, check_clean
    from skinfem.io import StrainDataset
    from skinfem.outputs import check_output

    check_output(args.out, args.force)
    if args.out.suffix not in (".h5", ".hdf5"):
        raise ValueError(f"--out must end in .h5, got '{args.out}'")
    if not (math.isfinite(args.length) and args.length > 0):
        raise ValueError(f"--length: the noise length scale must be > 0 mm, got {args.length}")
    if not 0 <= args.level < 1:
        raise ValueError(f"--level: the noise level must be a fraction in [0, 1), got {args.level}")
    data = StrainDataset.open(args.data)
    check_clean(data)
    add_noise(data, args.out, args.length, args.level, args.seed)
    print(
        f"added noise (length {args.length} mm, level {args.level:.0%}, seed {args.seed}) to "
        f"{int((data.status == 1).sum())} simulations\nwrote {args.out}"
    )


def check_inputs(args):
    """Settings, configuration, prior box, emulator, measurements and noise of ``skinid check``."""
    from inference.criticism import NoiseModel
    from inference.criticism.check import CheckSettings
    from inference.criticism.discretisation import default_refinement
    from inference.observations import check_field_of_view, read_measurement, thin
    from skinfem.config import PARAM_NAMES, config_from_toml, load_config
    from skinfem.dic import StrainGauge
    from skinfem.effects import EFFECTS, effect_parameters
    from skinfem.outputs import check_output
    from surrogate.emulator import Emulator

    check_output(args.out, args.force, directory=True, resume=args.resume)
    _check_check_options(args)
    emulator = None if args.emulator is None else Emulator.load(args.emulator)
    if args.config is not None:
        config = load_config(args.config)
    elif emulator is not None:
        config = config_from_toml(emulator.provenance.dataset_config)
    else:
        raise ValueError("give the mesh to check on with --config (a preset or TOML), or an --emulator")
    settings = CheckSettings(
        candidates=args.candidates or list(EFFECTS),
        add=args.add,
        increments=args.increments,
        confirm=args.confirm,
        gauge=StrainGauge(args.dic_window),
        spacing=args.spacing,
        discretisation=not args.no_discretisation,
        refinement=default_refinement(config) if args.refine == "auto" else args.refine,
        mesh_drift=args.mesh_drift,
    )
    bounds = emulator.param_bounds if emulator is not None else config.sweep.box
    if args.start is not None:
        outside = [
            f"{n} = {v:g} not in [{lo:g}, {hi:g}]"
            for n, v, (lo, hi) in zip(PARAM_NAMES, args.start, bounds)
            if not lo <= v <= hi
        ]
        if outside:
            raise ValueError(f"--start is outside the prior box: {'; '.join(outside)}")
        settings.start = np.array(args.start)
    membrane = settings.membrane(config)
    n_params = 5 + len(effect_parameters(settings.add))
    measurements = [thin(read_measurement(p, config.mesh.length / 2), args.spacing) for p in args.measurement]
    for m in measurements:
        check_field_of_view(m, membrane, n_params)
        check_strain_scale(m, membrane.half)
    if args.noise_sd is not None:
        sd = np.array(args.noise_sd)
    elif all(m.sd is not None for m in measurements):
        sd = np.median(np.concatenate([m.sd for m in measurements]), axis=0)
    else:
        raise ValueError("the measurements have no sd_exx, sd_eyy, sd_exy columns: give --noise-sd XX YY XY")
    noise = NoiseModel(sd, args.noise_length, args.noise_nugget)
    return settings, config, bounds, emulator, measurements, noise


def _check_check_options(args) -> None:
    """Refuse the numeric options of ``skinid check`` that its settings and noise model do not test."""
    if not (math.isfinite(args.noise_length) and args.noise_length >= 0):
        raise ValueError(f"--noise-length must be a number >= 0 mm, got {args.noise_length}")
    if not (math.isfinite(args.noise_nugget) and 0 <= args.noise_nugget <= 1):
        raise ValueError(f"--noise-nugget must be in [0, 1], got {args.noise_nugget}")
    if args.noise_length > 0 and args.noise_nugget == 0:
        raise ValueError(
            "--noise-length > 0 needs --noise-nugget > 0 (e.g. 0.3): a noise without an uncorrelated part "
            "has a singular correlation between close points, and whitening by it would amplify misfits"
        )
    if args.increments is not None and args.increments < 1:
        raise ValueError(f"--increments must be >= 1, got {args.increments}")
    if args.confirm < 0:
        raise ValueError(f"--confirm must be >= 0, got {args.confirm}")


def show_progress(logger: str, shown: bool) -> None:
    """Write the INFO lines of ``logger`` to stderr with the time of day if ``shown`` (one rank
    only), else only its warnings; one handler per process however often a command runs in it."""
    log = logging.getLogger(logger)
    log.setLevel(logging.INFO if shown else logging.WARNING)
    if shown and not log.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s  %(message)s", datefmt="%H:%M:%S"))
        log.addHandler(handler)


def cmd_check(args) -> None:
    from mpi4py import MPI

    from inference.criticism.check import run_check
    from inference.criticism.report import write_report
    from skinfem.outputs import remove_output
    from skinfem.parallel import collective, on_root

    comm = MPI.COMM_WORLD
    settings, config, bounds, emulator, measurements, noise = collective(comm, lambda: check_inputs(args))
    show_progress("inference.criticism", comm.rank == 0 and not args.quiet)
    if args.force:  # the inputs are read and checked: start over, without the old report's FE runs
        on_root(comm, lambda: remove_output(args.out))
    result = run_check(
        measurements,
        noise,
        settings,
        config,
        bounds,
        emulator,
        args.mesh_dir,
        comm,
        cache_dir=Path(args.out) / "fe_runs",
    )
    if comm.rank == 0:
        path = write_report(result, args.out)
        print(result.diagnosis.text)
        for v in result.versions:
            m = v.metrics
            print(
                f"{v.calibration.label:>30}: RMSE {m.rmse:.3e}, chi2/dof {m.chi2_per_dof:.3f}, "
                f"PPC p {m.ppc_p:.3f}, {'structured' if m.structured else 'consistent with noise'}"
            )
        print(f"wrote {path}")


def dic_settings(args):
    """ImportSettings of ``skinid measurement`` from its options and the configuration's sizes."""
    from inference.dic_import import ImportSettings
    from inference.dic_readers import TableOptions
    from skinfem.config import load_config

    mesh = load_config(args.config).mesh
    delimiter = {"tab": "\t", "\\t": "\t"}.get(args.delimiter, args.delimiter)
    table = TableOptions(
        delimiter=delimiter,
        decimal=args.decimal,
        encoding=args.encoding,
        columns=tuple(args.columns) if args.columns else None,
        units=args.units,
        missing=tuple(args.missing),
        skip=args.skip,
    )
    return ImportSettings(
        format=args.format,
        mm_per_px=args.mm_per_px,
        centre=tuple(args.centre),
        rotation=args.rotation,
        flip_y=args.flip_y,
        strain=args.strain,
        percent=args.percent,
        membrane_half=mesh.membrane_size / 2,
        block_half=mesh.length / 2,
        table=table,
    )


def _dic_field(args, settings):
    """Import ``args.file`` and say what was read and what could not be decided."""
    from inference.dic_import import load_dic

    field = load_dic(args.file, settings)
    print(
        f"read {field.n_rows} rows of {args.file} ({field.format}): {field.n_missing} missing, "
        f"{field.n_outside} outside the model block (|x|, |y| <= {settings.block_half:g} mm), "
        f"{len(field.xy)} points kept"
    )
    if field.notes:
        print("could not decide: " + "; ".join(field.notes))
    return field


def _measurement_show(args, settings) -> None:
    from inference.dic_import import assess_plausibility
    from inference.observations import HEADER, read_measurement
    from inference.plots import plot_field

    if args.file.is_file() and args.file.read_bytes().startswith(HEADER.encode()):
        if args.alpha is not None or args.t is not None:
            raise ValueError(
                f"{args.file} is a skinid measurement: its design and load fraction are in it (drop --alpha, --t)"
            )
        m = read_measurement(args.file, settings.block_half)
        xy, strain, alpha, t = m.xy, m.strain, m.alpha, m.t
    else:
        if args.t is not None and args.alpha is None:
            raise ValueError("--t is the load fraction of a design: give the design with --alpha")
        field = _dic_field(args, settings)
        xy, strain, alpha, t = field.xy, field.strain, args.alpha, 1.0 if args.t is None else args.t
    title = f"{args.file.name}: {len(xy)} points in the membrane frame"
    if alpha is not None:
        summary = assess_plausibility(xy, strain, alpha, t, settings.membrane_half).summary()
        print(summary)
        title += "\n" + summary
    try:
        print(f"wrote {plot_field(xy, strain, args.out, settings.membrane_half, title)}")
    except OSError as exc:
        raise ValueError(f"cannot write '{args.out}': {exc.strerror or exc}") from None


def cmd_measurement(args) -> None:
    from inference.dic_import import assess_plausibility, save_measurement
    from inference.observations import MeasurementError, load_fraction_problem
    from skinfem.outputs import check_output

    check_output(args.out, args.force)
    if args.t is not None and (problem := load_fraction_problem(args.t)):  # before the file is read
        raise ValueError(f"--t: the load fraction {problem}")
    settings = dic_settings(args)
    if args.action == "show":
        _measurement_show(args, settings)
        return
    field = _dic_field(args, settings)
    m = field.measurement(args.alpha, args.t)
    if not args.no_check:
        check = assess_plausibility(m.xy, m.strain, m.alpha, m.t, settings.membrane_half)
        if check.problem is not None:
            raise MeasurementError(f"{args.file}: {check.problem} (or skip this check with --no-check)")
        print(check.summary())
    print(f"wrote {save_measurement(m, args.out, settings.block_half)}")


COMMANDS = {
    "infer": cmd_infer,
    "study": cmd_study,
    "noise": cmd_noise,
    "check": cmd_check,
    "measurement": cmd_measurement,
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = argv[0] if argv and argv[0] in COMMANDS else "infer"
    if argv and argv[0] in COMMANDS:
        argv = argv[1:]
    args = build_parser(f"skinid {command}").parse_args(argv)
    from inference.observations import MeasurementError
    from skinfem.parallel import CollectiveError, abort_on_uncaught

    prog = " ".join(["skinid", command, *filter(None, [getattr(args, "study", None), getattr(args, "action", None)])])
    abort_on_uncaught(prog)
    try:
        check_input_paths(args)
    except FileNotFoundError as exc:  # the same on every rank: rank 0 says it once
        return refuse(prog, exc, show=_rank() == 0)
    try:
        COMMANDS[command](args)
    except CollectiveError as exc:  # raised on every rank: rank 0 says it once
        return refuse(prog, exc, show=_rank() == 0)
    except (MeasurementError, ValueError, FileNotFoundError) as exc:
        code = refuse(prog, exc)
        _abort_other_ranks(code)
        return code
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
