"""The umbrella console script ``skinid``: dispatches to the packages' command lines.

Only the package that owns a command is imported, so ``skinid surrogate ...`` and
``skinid infer ...`` work without FEniCSx. The conventions every command shares live here:
:class:`CommandParser` (each option's help shows its default), :func:`add_output` (``--out``,
``--force`` and ``--resume``, spelled and explained alike), :func:`add_renamed_option` (a
renamed option keeps its old spelling as a hidden deprecated alias) and :func:`refuse` (a
refused input is one line on stderr and exit status 2).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

ROUTES: dict[str, tuple[str, str]] = {
    "mesh": ("skinfem.__main__", "generate the gmsh mesh of a configuration"),
    "simulate": ("skinfem.__main__", "one forward simulation -> dataset (.h5)"),
    "sweep": ("skinfem.__main__", "Latin-hypercube sweep -> dataset (.h5), resumable, sharded"),
    "merge": ("skinfem.__main__", "join sweep shards into one dataset"),
    "info": ("skinfem.__main__", "summary of a dataset"),
    "surrogate": ("surrogate.__main__", "fit | validate the PCA + GP emulator"),
    "infer": ("inference.__main__", "NUTS posterior of the skin parameters"),
    "noise": ("inference.__main__", "add spatially correlated noise to a dataset"),
    "study": ("inference.__main__", "test-set | setups | coverage | noise: many posteriors, accuracy and calibration"),
    "check": ("inference.__main__", "model criticism: residuals, where the model fails, the missing effect"),
    "measurement": ("inference.__main__", "import | show DIC exports (VIC, DaVis, DICe, tables) as measurements"),
}


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends "(default: ...)" to the help of every option that has a default (not ``None``)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default is None or action.default is argparse.SUPPRESS or "%(default)" in text:
            return text
        value = action.default
        if isinstance(value, list | tuple):
            value = " ".join(map(str, value)) or "none"
        return f"{text} (default: {str(value).replace('%', '%%')})"


class CommandParser(argparse.ArgumentParser):
    """The parser of every skinid command; its sub-parsers are of the same class, so all of
    them format help the same way (:class:`HelpFormatter`)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


class _DeprecatedSpelling(argparse.Action):
    """The old spelling of a renamed option: hidden from the help; stores like the new one
    and says on stderr that it is deprecated."""

    def __init__(self, option_strings, dest, new: str, **kwargs):
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kwargs)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog}: warning: {option_string} is deprecated; use {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_command(sub: argparse._SubParsersAction, name: str, help: str) -> argparse.ArgumentParser:
    """The parser of a (sub)command: its ``--help`` opens with the line that lists it among its siblings."""
    return sub.add_parser(name, help=help, description=help.replace("%%", "%"))


def add_design(parser: argparse.ArgumentParser, help: str, *, required: bool = False) -> None:
    """``--alpha A11 A22``: a membrane design's eigen-strains along x and y [-]."""
    parser.add_argument(
        "--alpha", type=float, nargs=2, required=required, metavar=("A11", "A22"), help=f"{help} [-], e.g. 0.05 -0.05"
    )


def add_pca_scaling(parser: argparse.ArgumentParser) -> None:
    """``--pca-scaling cell|none``: the PCA's per-cell scaling (:mod:`surrogate.pca`)."""
    parser.add_argument(
        "--pca-scaling",
        choices=["cell", "none"],
        default="cell",
        help="per-cell standardisation before the PCA (cell: the paper's) or none (strain units: "
        "noise keeps its size in the weights, and the field's information survives noise; docs/surrogate.md)",
    )


def add_output(parser: argparse.ArgumentParser, what: str, *, resumable: bool = False, replaces: str = "--out") -> None:
    """``--out`` (``what`` it is) and ``--force``; also ``--resume`` for an output that keeps
    finished work (see :mod:`skinfem.outputs`)."""
    parser.add_argument("--out", type=Path, required=True, help=what)
    parser.add_argument(
        "--force", action="store_true", help=f"replace an existing {replaces}" + (" (start over)" if resumable else "")
    )
    if resumable:
        parser.add_argument(
            "--resume", action="store_true", help="complete an existing --out, reusing its finished work"
        )


def add_renamed_option(
    parser: argparse.ArgumentParser, name: str, *, old: str, required: bool = False, **kwargs
) -> None:
    """Add the option ``name`` and its former spelling ``old`` as a hidden deprecated alias.

    ``required`` applies to the pair: either spelling satisfies it.
    """
    group = parser.add_mutually_exclusive_group(required=required)
    action = group.add_argument(name, **kwargs)
    group.add_argument(
        old, dest=action.dest, type=action.type, nargs=action.nargs, action=_DeprecatedSpelling, new=name
    )


def refuse(prog: str, exc: BaseException, show: bool = True) -> int:
    """A command refused its input: print ``<prog>: error: <exc>`` (if ``show``; one rank of
    several says it once) and return the exit status 2.

    PETSc, if loaded, would list at exit the options set for a run that never happened
    ("WARNING! There are options you set that were not used!"); ``options_left`` false
    silences that list.
    """
    if show:
        print(f"{prog}: error: {exc}", file=sys.stderr)
    petsc = sys.modules.get("petsc4py.PETSc")
    if petsc is not None:
        petsc.Options()["options_left"] = False
    return 2


def usage() -> str:
    lines = ["usage: skinid <command> [options]   (skinid <command> --help for details; skinid --version)", ""]
    lines += [f"  {name:<10} {help_}" for name, (_, help_) in ROUTES.items()]
    return "\n".join(lines)


def version() -> str:
    """The installed skinid's version ("unknown" when run from a source tree not installed)."""
    from importlib import metadata

    try:
        return metadata.version("skinid")
    except metadata.PackageNotFoundError:
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    if not argv:
        print(f"skinid: a command is needed\n\n{usage()}", file=sys.stderr)
        return 2
    if argv[0] == "--version":
        print(f"skinid {version()}")
        return 0
    if argv[0] not in ROUTES:
        print(f"skinid: unknown command '{argv[0]}'\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(ROUTES[argv[0]][0])
    return module.main(argv)


if __name__ == "__main__":
    sys.exit(main())
