"""The umbrella console script ``skinid``: dispatches to the packages' command lines.

Only the package that owns a command is imported, so ``skinid surrogate ...`` and
``skinid infer ...`` work without FEniCSx.
"""

from __future__ import annotations

import importlib
import sys

ROUTES: dict[str, tuple[str, str]] = {
    "mesh": ("skinfem.__main__", "generate the gmsh mesh of a configuration"),
    "simulate": ("skinfem.__main__", "one forward simulation -> dataset (.h5)"),
    "sweep": ("skinfem.__main__", "Latin-hypercube sweep -> dataset (.h5), resumable, sharded"),
    "merge": ("skinfem.__main__", "join sweep shards into one dataset"),
    "info": ("skinfem.__main__", "summary of a dataset"),
    "surrogate": ("surrogate.__main__", "fit | validate the PCA + GP emulator"),
    "infer": ("inference.__main__", "NUTS posterior of the skin parameters"),
    "noise": ("inference.__main__", "add spatially correlated noise to a dataset"),
    "study": ("inference.__main__", "test-set | setups | noise: many posteriors, accuracy and coverage"),
    "check": ("inference.__main__", "model criticism: residuals, where the model fails, the missing effect"),
    "measurement": ("inference.__main__", "import | show DIC exports (VIC, DaVis, DICe, tables) as measurements"),
}


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
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
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
