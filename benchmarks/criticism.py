"""Model-criticism benchmark on independent data: verdicts over noise seeds, and their cost.

    mpirun -n 2 python benchmarks/criticism.py [--config small] [--cases none pre_stretch ...]
                                               [--seeds 5] [--out out/criticism_bench]
                                               [--data q2 | q2-edge | q2-fine | q2-limit | q2-limit-m8]
                                               [--refine uniform | edge | quadratic | converged]
                                               [--start spread | centre] [--confirm 1]
                                               [--results FILE] [--keep-recorded]

Data the checked model did not make: quadratic elements (Q2) on a mesh graded differently from
``small`` (far size 4 mm, 3 muscle layers; ``--data q2-edge``: also two skin layers and 0.5 mm
cells at the membrane edge, finer than the quadratic check mesh, preset ``check``; ``--data
q2-fine``: 0.25 mm edge cells and four muscle layers, finer than the ``converged`` reference; ``--data
q2-limit``: the Richardson limit of that mesh and the same with 0.5 mm edge cells, as converged as a
real measurement; ``--data q2-limit-m8``: the same limit with eight muscle layers), one material
(mu 1.2e-3 MPa, k1 0.017 MPa, k2 11, kappa 0.285, theta 30 deg), two membranes ((0.05, 0.05),
(0.05, -0.05)), measured like DIC (1 mm strain window) at a jittered 1 mm point cloud with three
holes over +-18 mm, plus correlated noise (sd 1e-3, 2 mm, 30 % uncorrelated), one noise draw per
seed. Cases: no hidden effect, one hidden effect (pre-stretch 1.08 x 1.02 at 30 deg, muscle 2x
stiffer, skin 1.5x thicker), two at once (``two_effects``: the pre-stretch and the stiffer
muscle), or a defect outside the registry (``inclusion``: skin 8x stiffer in a 3.5 mm disc at
(-13, 4) mm), or no effect with the noise understated (``understated_noise``: sd 2e-3 drawn,
1e-3 in the files). Each (case, seed) is one ``skinid check`` with the discretisation estimate
and the true effect added as a version (``--add``), so that the RMSE after adding it is measured
too; two effects take successive rounds (the first check's named effect added in a second check,
whose next round should name the other). ``--confirm`` is the number of candidates each check fits
in full per round (1 in the recorded tables; the CLI's default is 2).

Resumable: every finished check leaves ``<out>/<case>_<seed>/row.json``, and each case's
noise-free data ``<out>/data_<data>_<case>.npy`` (delete them after changing a case); a rerun skips them,
and ``--summarise`` tabulates the finished ones without running more. With ``--keep-recorded``
the rows already in the results file (same checked mesh, data, refinement and start) are kept
and not run again, so that seeds can be added to a recorded table from an empty ``--out``;
without it the results file is written from ``--out``'s rows alone, as a rerun with a new build
should be.
Writes the confusion table (true effect vs verdict), the true effect's rank, RMSE before and
after adding it, seconds and FE runs to benchmarks/results/criticism.json. Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import time
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from mpi4py import MPI

if TYPE_CHECKING:
    from inference.criticism.report_file import ReportDiagnosis, ReportFile, ReportVersion

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "criticism.json"
TRUTH = (1.2e-3, 0.017, 11.0, 0.285, 30.0)
DESIGNS = [(0.05, 0.05), (0.05, -0.05)]
NOISE = dict(sd=np.full(3, 1e-3), length=2.0, nugget=0.3)


INCLUSION = dict(centre=(-13.0, 4.0), radius=3.5, ratio=8.0)  # outside the membrane, inside the view


def hidden_effects() -> dict[str, dict[str, float]]:
    """Hidden registered effects of each case, by qualified parameter name."""
    from skinfem.effects import prestretch_log_strain

    pre_stretch = {f"pre_stretch.{k}": v for k, v in prestretch_log_strain(1.08, 1.02, 30.0).items()}
    muscle = {"muscle_stiffness.log_factor": float(np.log(2.0))}
    return {
        "none": {},
        "pre_stretch": pre_stretch,
        "muscle_stiffness": muscle,
        "skin_thickness": {"skin_thickness.log_factor": float(np.log(1.5))},
        "two_effects": {**pre_stretch, **muscle},
        "inclusion": {},
        "understated_noise": {},
    }


NOISE_DRAWN = {"understated_noise": 2.0}  # drawn noise sd / the sd the files state


def data_case(case: str) -> str:
    """The case whose noise-free data this case measures (the noise cases share "none"'s)."""
    return "none" if case in NOISE_DRAWN else case


def hidden_defects(case: str) -> tuple:
    """Hidden effects outside the registry: the stiff inclusion of case ``inclusion``."""
    from inference.synthetic import StiffInclusion

    return (StiffInclusion(**INCLUSION),) if case == "inclusion" else ()


def true_effects(case: str) -> list[str]:
    return sorted({name.split(".")[0] for name in hidden_effects()[case]})


DATA_MESHES = {  # changes to the small preset
    "q2": {"h_far": 4.0, "muscle_layers": 3},
    "q2-edge": {"h_far": 4.0, "muscle_layers": 3, "skin_layers": 2, "h_edge": 0.5},
    "q2-fine": {"h_far": 4.0, "muscle_layers": 4, "skin_layers": 2, "h_edge": 0.25},
    "q2-fine-coarser": {"h_far": 4.0, "muscle_layers": 4, "skin_layers": 2, "h_edge": 0.5},
    "q2-fine-m8": {"h_far": 4.0, "muscle_layers": 8, "skin_layers": 2, "h_edge": 0.25},
    "q2-fine-coarser-m8": {"h_far": 4.0, "muscle_layers": 8, "skin_layers": 2, "h_edge": 0.5},
}
LIMITS = {  # (coarser, finer): edge cells halved, all else equal
    "q2-limit": ("q2-fine-coarser", "q2-fine"),
    "q2-limit-m8": ("q2-fine-coarser-m8", "q2-fine-m8"),
}


def extrapolated(coarser: np.ndarray, finer: np.ndarray) -> np.ndarray:
    """Richardson extrapolation of measured fields of two meshes whose edge cells differ by a
    factor 2, at the order measured for Q2 edge refinement: finer + (finer - coarser) / (2^p - 1).
    An estimate of the converged field, as a real measurement would be."""
    from inference.criticism.discretisation import OBSERVED_ORDER, richardson_limit

    return richardson_limit(coarser, finer, OBSERVED_ORDER[2])


def describe_data(name: str) -> str:
    if name in LIMITS:
        coarser, finer = (DATA_MESHES[n] for n in LIMITS[name])
        return f"Q2, small preset, Richardson limit of {coarser} and {finer}"
    return f"Q2, small preset with {DATA_MESHES[name]}"


def measured_data(name: str, case: str, points, args, comm) -> np.ndarray:
    """Noise-free data of ``case`` on data mesh ``name`` (or the limit of a pair, :data:`LIMITS`),
    each mesh's fields kept in ``<out>/data_<mesh>_<case>.npy``."""
    fields = [
        data_fields(data_config(mesh), case, points, args.mesh_dir, comm, kept_data_path(args.out, mesh, case))
        for mesh in data_meshes(name)
    ]
    return combined_data(name, fields)


def data_meshes(name: str) -> tuple[str, ...]:
    """The meshes whose fields make data ``name``: itself, or a limit's pair (coarser, finer)."""
    return LIMITS.get(name, (name,))


def kept_data_path(folder: Path, mesh: str, case: str) -> Path:
    """Where the fields of ``case`` on data mesh ``mesh`` are kept."""
    return folder / f"data_{mesh}_{case}.npy"


def combined_data(name: str, fields: list[np.ndarray]) -> np.ndarray:
    """Data ``name`` from its meshes' fields (:func:`data_meshes` order): a limit is extrapolated."""
    return extrapolated(*fields) if name in LIMITS else fields[0]


def data_config(name: str):
    from skinfem.config import load_config

    return load_config("small").with_changes(
        mesh=DATA_MESHES[name], solver={"element_degree": 2, "quadrature_degree": 4}
    )


def data_fields(config, case: str, points, mesh_dir, comm, path: Path) -> np.ndarray:
    """Noise-free data (n_designs, n_points, 3) of every design (one design per rank at a time),
    on every rank; kept in ``path`` (.npy) so that a rerun does not recompute them. Each design's
    field is kept as it finishes (``<path stem>_design<j>.npy``): a killed run loses only the
    designs in progress."""
    from skinfem.parallel import collective

    if path.exists():
        return np.load(path)
    mine = collective(
        comm,
        lambda: {
            j: design_field(config, case, DESIGNS[j], points, mesh_dir, design_path(path, j))
            for j in range(comm.rank, len(DESIGNS), comm.size)
        },
    )
    merged = {j: f for part in comm.allgather(mine) for j, f in part.items()}
    fields = np.stack([merged[j] for j in range(len(DESIGNS))])
    if comm.rank == 0:
        save_npy(path, fields)
        for j in range(len(DESIGNS)):
            design_path(path, j).unlink()
    return fields


def design_path(path: Path, j: int) -> Path:
    return path.with_name(f"{path.stem}_design{j}.npy")


def design_field(config, case: str, design, points, mesh_dir, path: Path) -> np.ndarray:
    """Noise-free data (n_points, 3) of one design, read from ``path`` if a run before made it."""
    from inference.synthetic import measured_fields
    from skinfem.params import SkinParams

    if path.exists():
        return np.load(path)
    (field,) = measured_fields(
        config,
        SkinParams(*TRUTH),
        [design],
        points,
        hidden_effects()[case],
        mesh_dir,
        increments=2,
        defects=hidden_defects(case),
    )
    save_npy(path, field)
    return field


def save_npy(path: Path, array: np.ndarray) -> None:
    """Write ``array`` to ``path`` whole or not at all (through a temporary file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path.with_suffix(".tmp.npy"), array)
    path.with_suffix(".tmp.npy").replace(path)


def box_centre(config: str) -> list[float]:
    """Centre of the checked configuration's prior box of the skin parameters."""
    from skinfem.config import load_config

    return load_config(config).sweep.box.mean(axis=1).tolist()


def verdict_class(diagnosis: ReportDiagnosis, structured: bool) -> str:
    """The effect that explains the residual, or "no missing effect" / "none explains"."""
    best = next((c.effect for c in diagnosis.candidates if c.explains), None)
    if best is not None:
        return best
    return "none explains" if structured else "no missing effect"


def baseline_verdict(report: ReportFile) -> str:
    return verdict_class(report.diagnosis, report.versions[0].metrics.structured)


def check_argv(files, folder: Path, add: list[str], args) -> list[str]:
    """The ``skinid check`` arguments of one check of a case (report in ``folder/report``)."""
    given = [] if args.start == "spread" else ["--start", *map(str, box_centre(args.config))]
    return [
        "check", "--config", args.config, "--measurement", *map(str, files), "--out", str(folder / "report"),
        "--noise-length", "2", "--noise-nugget", "0.3", "--increments", "2", "--confirm", str(args.confirm),
        "--spacing", "2",
        "--mesh-dir", str(args.mesh_dir), "--refine", args.refine, "--resume", *given,
        *(["--add", *add] if add else []), *(["--mesh-drift"] if args.mesh_drift else []),
    ]  # fmt: skip


def check(files, folder: Path, add: list[str], args) -> tuple[ReportFile | None, float]:
    """One ``skinid check`` into ``folder/report`` (its FE runs kept for the next round); returns
    (its report.json on rank 0, else None; seconds)."""
    from inference.__main__ import main as skinid
    from inference.criticism.report_file import read_report

    start = time.perf_counter()
    code = skinid(check_argv(files, folder, add, args))
    seconds = time.perf_counter() - start
    if MPI.COMM_WORLD.rank or code:
        return None, seconds
    return read_report(folder / "report" / "report.json"), seconds


def rounds(files, folder: Path, case: str, args) -> tuple[list[str], list[ReportFile | None], float]:
    """The checks of one case: a single effect is added in the same check (its RMSE after adding
    it is measured); two effects take successive rounds: the first check's named effect, if it
    is a true one, is added in a second check, whose next round should name the other.
    Returns (verdicts, reports, seconds); reports are None on ranks other than 0."""
    true = true_effects(case)
    if len(true) < 2:
        report, seconds = check(files, folder, true, args)
        return [baseline_verdict(report)] if report else [], [report], seconds
    report, seconds = check(files, folder, [], args)
    first = MPI.COMM_WORLD.bcast(baseline_verdict(report) if report else None)
    if first not in true:
        return [first], [report], seconds
    second_report, more = check(files, folder, [first], args)
    second = second_report and verdict_class(second_report.next_round, second_report.versions[-1].metrics.structured)
    return [first, second], [report, second_report], seconds + more


def estimates_json(version: ReportVersion) -> dict[str, dict[str, float]]:
    """A version's estimates as report.json has them: {parameter: {"value", "sd"}}."""
    return {name: dataclasses.asdict(e) for name, e in version.estimates.items()}


def run_case(case: str, seed: int, fields, points, args, comm) -> dict:
    """One case's checks; returns its row (rank 0) and writes it, with the report, to out/case_seed."""
    from inference.criticism import NoiseModel
    from inference.synthetic import write_noisy

    folder = args.out / f"{case}_{seed}"
    files = None
    if comm.rank == 0:
        drawn = NoiseModel(**{**NOISE, "sd": NOISE["sd"] * NOISE_DRAWN.get(case, 1.0)})
        files = write_noisy(fields, points, DESIGNS, drawn, folder / "m", seed, stated_sd=NOISE["sd"])
    verdicts, reports, seconds = rounds(comm.bcast(files), folder, case, args)
    peaks = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2)
    if comm.rank or not all(reports):
        return {}
    first, last = reports[0], reports[-1]
    true = true_effects(case)
    effects = [c.effect for c in first.diagnosis.candidates]
    ranks = [effects.index(e) + 1 for e in true if e in effects]
    spot = first.diagnosis.hotspot
    baseline = first.versions[0]
    final = last.versions[-1] if len(last.versions) > 1 else None  # with the true effect added
    noise = first.noise_statement
    row = {
        "case": case,
        "seed": seed,
        "confirm": args.confirm,
        "verdict": ", then ".join(verdicts),
        "noise_factor": {"drawn": NOISE_DRAWN.get(case, 1.0), "estimated": noise.factor},
        "rank_of_true_effect": min(ranks) if ranks else None,
        "rmse_baseline": baseline.metrics.rmse,
        "added": [v.label for v in last.versions[1:]],
        "rmse_with_true_effect": None if final is None else final.metrics.rmse,
        "noise_rms": baseline.metrics.noise_rms,
        "discretisation_sigma": first.discretisation.sigma,
        "carried_sigma": first.discretisation.remaining_sigma,
        "discretisation_amplitude": first.discretisation.amplitude,
        "hotspot": dataclasses.asdict(spot),
        "hotspot_to_inclusion_mm": (
            float(np.hypot(spot.x - INCLUSION["centre"][0], spot.y - INCLUSION["centre"][1]))
            if case == "inclusion"
            else None
        ),
        "failed_runs": sum(len(r.failed_runs) for r in reports),
        "seconds": seconds,
        "fe_runs": sum(
            r.timings.compare_fe_runs
            + r.timings.diagnose_fe_runs
            + r.timings.add_fe_runs
            + r.timings.next_round_fe_runs
            for r in reports
        ),
        "fe_runs_continued": first.timings.fe_runs_continued,
        "fe_runs_read_from_cache": sum(r.timings.fe_runs_read_from_cache for r in reports),  # a resumed check
        "refined_seconds": first.timings.refined_s,
        "peak_memory_gb_per_rank": peaks,  # each rank process's so far (including earlier rows it ran)
        "estimates_baseline": estimates_json(baseline),
        "estimates_with_true_effect": None if final is None else estimates_json(final),
    }
    (folder / "row.json").write_text(json.dumps(row, indent=2) + "\n")
    return row


PHASES = ("setup", "compare", "refined", "diagnose", "add", "next_round")
BEST_CANDIDATE = ("effect", "delta_bic", "share_explained", "confounding", "fitted", "mesh_share", "mesh_like")
CANDIDATE_TEST = ("effect", "statistic", "dof", "p_value", "delta_bic", "fitted", "mesh_share", "mesh_like")


def mesh_shares(diagnosis: ReportDiagnosis) -> dict[str, float | None]:
    """Each candidate's share of the check mesh's own error (None in reports written before it was measured)."""
    return {c.effect: c.mesh_share for c in diagnosis.candidates}


def report_summary(folder: Path) -> dict:
    """From the case's (last) report.json: seconds, FE runs and solver work of each phase, the baseline's
    chi^2/dof and posterior-predictive p, its best candidate, every candidate's share of the mesh's own
    error and targeted (score) test, and the competing larger model error."""
    from inference.criticism.report_file import read_report

    report = read_report(folder / "report" / "report.json")
    timings = dataclasses.asdict(report.timings)
    best = report.diagnosis.candidates[0] if report.diagnosis.candidates else None
    larger = report.diagnosis.larger_model_error
    return {
        "phases": {f"{p}{unit}": timings[f"{p}{unit}"] for p in PHASES for unit in ("_s", "_fe_runs")},
        "work": timings["work"],  # Newton steps, factorisations, triangular solves per phase (None: not counted)
        "chi2_per_dof": report.versions[0].metrics.chi2_per_dof,
        "ppc_p": report.versions[0].metrics.ppc_p,
        "best_candidate": best and {key: getattr(best, key) for key in BEST_CANDIDATE},
        "mesh_shares": mesh_shares(report.diagnosis),
        "candidates": [{key: getattr(c, key) for key in CANDIDATE_TEST} for c in report.diagnosis.candidates],
        "next_round_mesh_shares": report.next_round and mesh_shares(report.next_round),
        "larger_model_error": larger and dataclasses.asdict(larger),
    }


def setup_flags(args) -> str:
    """The options that make two runs' rows comparable: the data and how the check is set up."""
    drift = " --mesh-drift" if args.mesh_drift else ""
    return f"--data {args.data} --refine {args.refine} --start {args.start} --confirm {args.confirm}{drift}"


def recorded_rows(args) -> dict[tuple[str, int], dict]:
    """With ``--keep-recorded``, the rows already in the results file, by (case, seed): kept, and
    not run again. A results file of another setup (checked mesh, data, refinement, start) then
    ends the run with one line."""
    if not (args.keep_recorded and args.results.exists()):
        return {}
    try:
        earlier = json.loads(args.results.read_text())
        config, command, rows = earlier["checked_config"], earlier["command"], earlier["rows"]
        recorded = {(row["case"], row["seed"]): row for row in rows}
    except (ValueError, KeyError, TypeError):
        message = f"{args.results} is not a results file of this benchmark; pass another --results"
    else:
        if config == args.config and command.endswith(setup_flags(args)):
            return recorded
        message = f"{args.results} holds checks of another setup ({command}); pass another --results"
    raise SystemExit(message if MPI.COMM_WORLD.rank == 0 else 1)  # every rank reads the file: one line


def verdict_label(row: dict) -> str:
    """A row's verdict, and whether the check found the stated noise too small."""
    understated = row.get("noise_factor", {}).get("estimated", 1.0) > 1.0
    return row["verdict"] + (" (noise understated)" if understated else "")


def markdown_table(rows: list[dict]) -> str:
    """One line per case: verdicts, the true effect's rank, medians of RMSE (before / after adding
    the true effect), the check mesh's own error and the carried part [noise sd], and seconds."""

    def median(values) -> float | None:
        values = [v for v in values if v is not None]
        return float(np.median(values)) if values else None

    def number(value, fmt: str) -> str:
        return "—" if value is None else format(value, fmt)

    lines = [
        "| hidden effect | checks | verdicts | true effect ranked first | RMSE baseline | RMSE with the true "
        "effect added | own error / carried [σ] | seconds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case in dict.fromkeys(row["case"] for row in rows):
        mine = [row for row in rows if row["case"] == case]
        verdicts = ", ".join(f"{v}: {n}" for v, n in Counter(map(verdict_label, mine)).items())
        ranks = [row["rank_of_true_effect"] for row in mine]
        first = f"{ranks.count(1)}/{len(mine)}" if true_effects(case) else "—"
        rmse, added = median(r["rmse_baseline"] for r in mine), median(r["rmse_with_true_effect"] for r in mine)
        own, carried = median(r["discretisation_sigma"] for r in mine), median(r.get("carried_sigma") for r in mine)
        seconds = median(r["seconds"] for r in mine)
        lines.append(
            f"| {case} | {len(mine)} | {verdicts} | {first} | {number(rmse, '.2e')} | {number(added, '.2e')} "
            f"| {number(own, '.1f')} / {number(carried, '.1f')} | {number(seconds, '.0f')} |"
        )
    return "\n".join(lines)


def main() -> None:
    """The benchmark's steps in order (options, cases by seed, the results file): longer than a screen on purpose."""
    import skinfem.model  # noqa: F401  (PETSc initialises collectively: import on every rank first)
    from inference.criticism.discretisation import REFINEMENTS
    from inference.synthetic import dic_points

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="small", help="the checked mesh (preset or TOML)")
    parser.add_argument("--cases", nargs="+", default=list(hidden_effects()))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("out/criticism_bench"))
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--summarise", action="store_true", help="only tabulate the finished checks")
    parser.add_argument(
        "--data", choices=[*DATA_MESHES, *LIMITS], default="q2", help="the data's discretisation (or their limit)"
    )
    parser.add_argument(
        "--refine",
        choices=list(REFINEMENTS),
        default="uniform",
        help="the check's better mesh for its discretisation estimate",
    )
    parser.add_argument(
        "--start",
        choices=["spread", "centre"],
        default="spread",
        help="calibration start: best of 5 spread points, or the box centre",
    )
    parser.add_argument(
        "--confirm",
        type=int,
        default=1,
        help="candidates fitted in full per round (the CLI's default is 2; 1 keeps the recorded tables' setup)",
    )
    parser.add_argument(
        "--mesh-drift", action="store_true", help="the checks' mesh-error correction follows the parameters"
    )
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument(
        "--keep-recorded", action="store_true", help="keep the results file's rows and run only the missing ones"
    )
    args = parser.parse_args()
    if args.confirm < 0:  # before the data's FE runs, not after them in the first check
        parser.error(f"--confirm must be >= 0, got {args.confirm}")
    comm = MPI.COMM_WORLD
    points = dic_points(18.0, 1.0, np.random.default_rng(0))
    recorded = recorded_rows(args)
    fields = {}
    for seed in [] if args.summarise else range(args.seeds):  # seed by seed: a stopped run has every case
        for case in args.cases:
            if (case, seed) not in recorded and not (args.out / f"{case}_{seed}" / "row.json").exists():
                source = data_case(case)
                if source not in fields:
                    fields[source] = measured_data(args.data, source, points, args, comm)
                run_case(case, seed, fields[source], points, args, comm)
    finished = {
        (case, s): {
            **json.loads((args.out / f"{case}_{s}" / "row.json").read_text()),
            **report_summary(args.out / f"{case}_{s}"),
        }
        for case in args.cases
        for s in range(args.seeds)
        if (args.out / f"{case}_{s}" / "row.json").exists()
    }
    by_case = {case: i for i, case in enumerate(dict.fromkeys([*args.cases, *(c for c, _ in recorded)]))}
    rows = [row for _, row in sorted({**recorded, **finished}.items(), key=lambda kv: (by_case[kv[0][0]], kv[0][1]))]
    if comm.rank == 0:
        confusion: dict[str, dict[str, int]] = {}
        for row in rows:
            confusion.setdefault(row["case"], {}).setdefault(verdict_label(row), 0)
            confusion[row["case"]][verdict_label(row)] += 1
        command = (
            f"mpirun -n 2 python benchmarks/criticism.py --config {args.config} --cases {' '.join(by_case)} "
            f"--seeds {1 + max((row['seed'] for row in rows), default=args.seeds - 1)} {setup_flags(args)}"
        )
        args.results.write_text(
            json.dumps(
                {
                    "command": command,
                    "checked_config": args.config,
                    "data": describe_data(args.data),
                    "noise": {"sd": NOISE["sd"].tolist(), "length_mm": 2.0, "nugget": 0.3},
                    "confusion": confusion,
                    "rows": rows,
                },
                indent=2,
            )
            + "\n"
        )
        print(markdown_table(rows))


if __name__ == "__main__":
    main()
