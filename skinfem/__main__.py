"""Command line of skinfem: ``skinid mesh|simulate|sweep|merge|info`` (also ``python -m skinfem``).

``mesh``, ``simulate`` and ``sweep`` run under ``mpirun -n k``. Errors in the input are reported as one
line on stderr with exit status 2; an existing output is not replaced without ``--force``, and
nothing is half-written (:mod:`skinfem.outputs`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from skinfem.cli import ROUTES, CommandParser, add_command, add_design, add_output, refuse
from skinfem.config import PARAM_NAMES, ConfigError, load_config
from skinfem.mesh import DEFAULT_MESH_DIR


def _add_config(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", default="small", help="TOML file or built-in preset (small, study, paper, check, converged)"
    )
    parser.add_argument("--mesh-dir", type=Path, default=DEFAULT_MESH_DIR, help="mesh directory")


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="skinid", description="the forward model: mesh, simulate, sweep, merge, info")
    sub = parser.add_subparsers(dest="command", required=True)

    p = add_command(sub, "mesh", ROUTES["mesh"][1])
    _add_config(p)
    p.add_argument("--force", action="store_true", help="regenerate the mesh file if it exists")

    p = add_command(sub, "simulate", ROUTES["simulate"][1])
    _add_config(p)
    meaning = {
        "mu": "[MPa]",
        "k1": "[MPa]",
        "k2": "[-]",
        "kappa": "[-], fibre dispersion in [0, 1/3]",
        "theta": "[deg], fibre angle from the x (alpha11) axis towards y",
    }
    for name in PARAM_NAMES:
        p.add_argument(f"--{name}", type=float, required=True, help=f"skin {name} {meaning[name]}")
    add_design(p, "the membrane design: eigen-strains along x and y", required=True)
    add_output(p, "output dataset (.h5)", replaces="--out and --fields")
    p.add_argument("--fields", type=Path, help="also write ParaView fields (.xdmf and its .h5; not the --out name)")

    p = add_command(sub, "sweep", ROUTES["sweep"][1])
    _add_config(p)
    add_output(p, "output dataset (.h5)", resumable=True)
    p.add_argument("--retry-failed", action="store_true", help="with --resume: rerun failed simulations")
    p.add_argument("--shard", default="0/1", help="run shard i of n (0 <= i < n), e.g. 3/16")
    p.add_argument("--ranks-per-sim", type=int, default=1, help="MPI ranks per simulation")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = add_command(sub, "merge", ROUTES["merge"][1])
    p.add_argument("shards", type=Path, nargs="+", help="shard datasets (.h5)")
    add_output(p, "merged dataset (.h5)")

    p = add_command(sub, "info", ROUTES["info"][1])
    p.add_argument("data", type=Path, help="dataset (.h5)")
    return parser


def cmd_mesh(args, comm) -> int:
    from skinfem.mesh import build_mesh, mesh_path
    from skinfem.outputs import check_writable

    config = load_config(args.config)
    path = mesh_path(config, args.mesh_dir)
    if comm.rank == 0:
        if args.force or not path.exists():
            info = build_mesh(config, check_writable(path))
            print(
                f"wrote {info.path}: {info.n_cells} hexahedra ({info.n_skin_cells} in the skin), {info.n_nodes} nodes"
            )
        else:
            print(f"{path} exists (use --force to regenerate)")
    return 0


def check_simulate_outputs(args) -> None:
    """``--out`` and the two ``--fields`` files: new (or ``--force``), writable, not the same file."""
    from skinfem.io import field_files
    from skinfem.outputs import check_output

    if args.out.suffix not in (".h5", ".hdf5"):
        raise ValueError(f"--out must end in .h5, got '{args.out}'")
    check_output(args.out, args.force)
    if args.fields is None:
        return
    for path in field_files(args.fields):
        if path.resolve() == args.out.resolve():
            raise ValueError(
                f"--fields {args.fields} writes its data to {path}, the --out file; give --fields another name"
            )
        check_output(path, args.force)


def cmd_simulate(args, comm) -> int:
    from contextlib import nullcontext

    from skinfem.io import STATUS_OK, FieldWriter, create_dataset, write_simulation
    from skinfem.model import SkinModel
    from skinfem.outputs import write_atomically
    from skinfem.params import Design, SkinParams

    config = load_config(args.config)
    params = SkinParams(*(getattr(args, n) for n in PARAM_NAMES))
    design = Design(*args.alpha)
    check_simulate_outputs(args)
    model = SkinModel(config, comm, mesh_dir=args.mesh_dir)
    with FieldWriter(model, args.fields) if args.fields else nullcontext() as writer:
        frames = model.simulate(params, design, on_frame=writer.write if writer else None)
    if comm.rank != 0:
        return 0

    def write(tmp: Path) -> None:
        create_dataset(
            tmp,
            config,
            params.as_array()[None],
            design.as_array()[None],
            frames.t,
            frames.xy,
            frames.volume,
            split=np.zeros(1),
            mesh_sha256=model.mesh_sha256,
        )
        write_simulation(tmp, 0, 0, frames.strain, STATUS_OK, "", sum(frames.newton_iterations), frames.seconds)

    write_atomically(args.out, write)
    last = frames.strain[-1]
    print(
        f"simulated {params} with {design} in {frames.seconds:.1f} s "
        f"({comm.size} rank{'s' if comm.size > 1 else ''}; Newton iterations per increment "
        f"{frames.newton_iterations}, cut-backs {frames.cutbacks})\n"
        f"max |E_xx| = {np.abs(last[:, 0]).max():.4f}, max |E_yy| = {np.abs(last[:, 1]).max():.4f} "
        f"over {len(last)} skin cells\nwrote {args.out}" + (f" and {writer.path}" if writer else "")
    )
    return 0


def cmd_sweep(args, comm) -> int:
    from skinfem.sweep import parse_shard, run_sweep

    config = load_config(args.config)
    report = run_sweep(
        config,
        args.out,
        resume=args.resume,
        retry_failed=args.retry_failed,
        shard=parse_shard(args.shard),
        ranks_per_sim=args.ranks_per_sim,
        mesh_dir=args.mesh_dir,
        comm=comm,
        progress=not args.quiet,
        force=args.force,
    )
    if report is not None:
        print(report)
    return 0


def cmd_merge(args, comm) -> int:
    from skinfem.outputs import check_output
    from skinfem.sweep import merge_datasets

    check_output(args.out, args.force)
    if comm.rank == 0:
        data = merge_datasets(args.shards, args.out)
        done = np.count_nonzero(data.status)
        print(f"merged {len(args.shards)} shards: {done} of {data.status.size} simulations\nwrote {args.out}")
    return 0


def cmd_info(args, comm) -> int:
    from skinfem.io import StrainDataset, dataset_summary

    if comm.rank == 0:
        print(dataset_summary(StrainDataset.open(args.data)))
    return 0


COMMANDS = {
    "mesh": cmd_mesh,
    "simulate": cmd_simulate,
    "sweep": cmd_sweep,
    "merge": cmd_merge,
    "info": cmd_info,
}


def main(argv: list[str] | None = None) -> int:
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args, comm)
    except (ConfigError, ValueError, FileNotFoundError, RuntimeError) as exc:
        return refuse(f"skinid {args.command}", exc, show=comm.rank == 0)


if __name__ == "__main__":
    sys.exit(main())
