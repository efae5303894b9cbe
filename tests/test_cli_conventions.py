"""The conventions every ``skinid`` command shares (fast: no FE simulation, no MPI).

- ``skinid --version`` prints the installed package's version;
- every option's help shows its default, and an option has one spelling in every command;
- ``--force`` replaces an existing output whole, and outputs are written under a temporary
  name (nothing half-written is left when a write fails);
- a sweep's lock file ``<out>.lock`` is exclusive, and an output whose folder cannot be written
  is found by asking the folder.

The refusals (an existing output without ``--force``, an output in a file or an unwritable
folder, ``--force`` with ``--resume``, a second sweep to a locked file, a stale lock, PETSc's
list of unused options after a refusal) are in the bad-input corpus, tests/test_bad_inputs.py.
"""

from __future__ import annotations

import argparse
import os
import re
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from skinfem.outputs import write_atomically
from tests.cli_helpers import skinid

OLD_BYTES = b"an output that took hours"

# one spelling per meaning: no command may use the spellings on the right
CANONICAL = {
    "--out": ("--output", "--output-dir", "--out-dir", "--outdir", "-o"),
    "--force": ("--overwrite", "--replace", "-f"),
    "--resume": ("--continue", "--restart"),
    "--config": ("--cfg", "--preset", "--configuration"),
    "--mesh-dir": ("--mesh-directory", "--meshes", "--mesh_dir", "--meshdir"),
    "--seed": ("--seeds", "--random-seed", "--rng-seed"),
    "--designs": ("--design",),
    "--alpha": ("--alpha11", "--alpha22"),
    "--data": ("--dataset",),
    "--emulator": ("--emu", "--surrogate"),
    "--measurement": ("--measurements",),
    "--quiet": ("--silent", "--no-progress"),
}


def command_parsers() -> dict[str, argparse.ArgumentParser]:
    """Every (sub)command's parser, by the words that call it (``"study noise"``)."""
    import inference.cli_parsers as inference_cli
    import skinfem.__main__ as skinfem_cli
    import surrogate.__main__ as surrogate_cli
    from skinfem.cli import ROUTES

    roots = {"": skinfem_cli.build_parser(), "surrogate": surrogate_cli.build_parser()}
    roots |= {
        name: inference_cli.build_parser(f"skinid {name}")
        for name, (module, _) in ROUTES.items()
        if module == "inference.__main__"
    }
    parsers = {}
    for prefix, parser in roots.items():
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        children = subs[0].choices if subs else {"": parser}
        parsers |= {f"{prefix} {name}".strip(): p for name, p in children.items()}
    return parsers


PARSERS = command_parsers()


def visible_options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [
        a
        for a in parser._actions
        if a.option_strings and a.help is not argparse.SUPPRESS and not isinstance(a, argparse._HelpAction)
    ]


def help_blocks(text: str) -> dict[str, str]:
    """The help of each option of a ``--help`` text, by its first option string."""
    blocks: dict[str, str] = {}
    current = None
    for line in text.splitlines():
        if re.match(r"^ {2}-", line):
            current = line.split()[0].rstrip(",")
            blocks[current] = line
        elif current and line.startswith("   "):
            blocks[current] += " " + line.strip()
        else:
            current = None
    return blocks


def old_output(path: Path) -> Path:
    """An existing output at ``path`` (a file, or a folder if it has no suffix) holding OLD_BYTES;
    returns the file whose bytes must survive."""
    if path.suffix:
        path.write_bytes(OLD_BYTES)
        return path
    path.mkdir()
    (path / "keep.bin").write_bytes(OLD_BYTES)
    return path / "keep.bin"


def fake_dataset(path: Path) -> Path:
    """A finished 12-material dataset (2 held out) of smooth fields on 36 cells: no FE."""
    from skinfem.config import load_config
    from skinfem.io import STATUS_OK, create_dataset, write_simulation

    config = load_config("small")
    bounds = config.sweep.box
    rng = np.random.default_rng(0)
    unit = rng.uniform(size=(12, 5))
    params = bounds[:, 0] + unit * np.ptp(bounds, axis=1)
    designs, t = np.array([[0.05, -0.05], [0.05, 0.05]]), np.array([0.5, 1.0])
    g = np.linspace(-15, 15, 6)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    create_dataset(
        path, config, params, designs, t, xy, np.ones(len(xy)), np.r_[np.zeros(10), np.ones(2)], "fake", bounds
    )
    shape = np.exp(-(xy**2).sum(1) / 200)
    for i, u in enumerate(unit):
        for j, (a11, a22) in enumerate(designs):
            frames = [
                np.column_stack(
                    [(1 + u[0]) * a11 * s * shape, (1 + u[1]) * a22 * s * shape, 0.1 * u[4] * a11 * s * shape]
                )
                for s in t
            ]
            write_simulation(path, i, j, np.array(frames), STATUS_OK)
    return path


# ---------------------------------------------------------------- version, help, spellings


def test_version_is_the_installed_packages():
    res = skinid("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"skinid {metadata.version('skinid')}"
    assert len(res.stdout.splitlines()) == 1


def test_skinid_without_a_command_is_refused_with_the_list_of_commands(capsys):
    from skinfem.cli import ROUTES, main

    assert main([]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("skinid: a command is needed")
    assert all(f"  {name} " in err for name in ROUTES)


@pytest.mark.parametrize("command", list(PARSERS))
def test_help_opens_with_the_line_that_lists_the_command(command):
    from skinfem.cli import ROUTES

    description = PARSERS[command].description
    assert description and "``" not in description and "%%" not in description
    if command in ROUTES:
        assert description == ROUTES[command][1]


def test_the_check_names_every_registered_effect_it_can_add_or_test():
    from skinfem.effects import EFFECTS

    for option in ("--add", "--candidates"):
        text = next(a.help for a in PARSERS["check"]._actions if option in a.option_strings)
        assert text.split(" of ", 1)[1].split(" (")[0].split(", ") == list(EFFECTS), text


@pytest.mark.parametrize("command", list(PARSERS))
def test_help_shows_every_default(command, capsys, monkeypatch):
    from skinfem.cli import main

    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit) as exit_:
        main([*command.split(), "--help"])
    assert exit_.value.code == 0
    blocks = help_blocks(capsys.readouterr().out)
    for action in visible_options(PARSERS[command]):
        text = blocks[action.option_strings[0]]
        if action.default is not None:
            assert "default" in text, f"skinid {command} --help: {text!r} does not show its default"


def test_one_spelling_per_option():
    variants = {old: new for new, olds in CANONICAL.items() for old in olds}
    for command, parser in PARSERS.items():
        for action in visible_options(parser):
            for name in action.option_strings:
                assert name not in variants, f"skinid {command} spells {variants[name]} as {name}"
    used = {name for parser in PARSERS.values() for a in visible_options(parser) for name in a.option_strings}
    assert set(CANONICAL) <= used  # the list names options that exist


def test_the_old_design_spelling_is_a_hidden_deprecated_alias(capsys):
    import inference.cli_parsers as inference_cli

    parser = inference_cli.build_parser("skinid study")
    args = parser.parse_args(["noise", "--data", "d.h5", "--design", "7", "--out", "o"])
    assert args.designs == "7"
    assert "--design is deprecated; use --designs" in capsys.readouterr().err
    assert not re.search(r"--design\b(?!s)", PARSERS["study noise"].format_help())
    with pytest.raises(SystemExit):  # one of the two is still required
        parser.parse_args(["noise", "--data", "d.h5", "--out", "o"])
    assert "--designs is required" in capsys.readouterr().err


def test_designs_are_named_by_index_or_by_their_eigen_strains():
    from inference.cli_inputs import design_indices

    designs = np.array([[-0.05, -0.05], [-0.05, 0.033333333333], [0.05, -0.05], [0.05, 0.05]])
    path = Path("d.h5")
    assert design_indices("2", designs, path) == [2]
    assert design_indices("3,0", designs, path) == [3, 0]
    assert design_indices("0.05,-0.05", designs, path) == [2]
    assert design_indices("0.05,0.05 -0.05,0.0333", designs, path) == [3, 1]  # within 1e-3
    assert design_indices(None, designs, path) is None
    with pytest.raises(ValueError, match=r"has no design alpha = 0.05,0 \(its designs: -0.05,-0.05, "):
        design_indices("0.05,0", designs, path)
    with pytest.raises(ValueError, match="come in pairs"):
        design_indices("0.05,-0.05,0.05", designs, path)
    import inference.cli_parsers as inference_cli

    parser = inference_cli.build_parser("skinid study")
    args = parser.parse_args(["noise", "--data", "d.h5", "--designs=-0.05,0.05", "--out", "o"])
    assert args.designs == "-0.05,0.05"


# ---------------------------------------------------------------- --force


def test_merge_and_noise_force_replace_a_file(tmp_path):
    from skinfem.io import StrainDataset

    shard = fake_dataset(tmp_path / "shard.h5")
    for args, out in [
        (["merge", shard], tmp_path / "merged.h5"),
        (["noise", "--data", shard, "--length", "5", "--level", "0.05"], tmp_path / "noisy.h5"),
    ]:
        old_output(out)
        res = skinid(*args, "--out", out, "--force")
        assert res.returncode == 0, res.stderr
        assert StrainDataset.open(out).status.tolist() == StrainDataset.open(shard).status.tolist()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["merged.h5", "noisy.h5", "shard.h5"]


# ---------------------------------------------------------------- folders that cannot be written


def test_check_output_asks_the_folder_for_write_permission(tmp_path, monkeypatch):
    """The check tests/test_bad_inputs.py::test_an_unwritable_folder_is_refused makes through the
    commands, where root cannot make it."""
    from skinfem import outputs

    asked = []
    monkeypatch.setattr(outputs.os, "access", lambda path, mode: asked.append((Path(path), mode)) and False)
    with pytest.raises(ValueError, match=f"'{tmp_path}' is not writable"):
        outputs.check_output(tmp_path / "new" / "data.h5")
    assert asked == [(tmp_path, os.W_OK | os.X_OK)]


# ---------------------------------------------------------------- the sweep lock


def test_take_lock_is_exclusive(tmp_path):
    from skinfem.outputs import release_lock, take_lock

    lock = take_lock(tmp_path / "d.h5")
    assert lock.read_text().split()[0] == str(os.getpid())
    with pytest.raises(ValueError, match="being written by another sweep"):
        take_lock(tmp_path / "d.h5")
    release_lock(tmp_path / "d.h5")
    assert not lock.exists()


# ---------------------------------------------------------------- writing under a temporary name


def test_write_atomically_replaces_a_folder_whole_and_keeps_it_if_the_write_fails(tmp_path):
    out = tmp_path / "emu"
    old_output(out)

    def fail(tmp: Path) -> None:
        tmp.mkdir()
        (tmp / "half.bin").write_bytes(b"half")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        write_atomically(out, fail)
    assert [p.name for p in tmp_path.iterdir()] == ["emu"] and (out / "keep.bin").read_bytes() == OLD_BYTES

    def write(tmp: Path) -> None:
        tmp.mkdir()
        (tmp / "new.bin").write_bytes(b"new")

    write_atomically(out, write)
    assert [p.name for p in tmp_path.iterdir()] == ["emu"] and [p.name for p in out.iterdir()] == ["new.bin"]


def test_figures_keep_their_format_under_the_temporary_name(tmp_path):
    from inference.plots import pyplot
    from skinfem.outputs import save_figure

    fig, ax = pyplot().subplots()
    ax.plot([0, 1], [0, 1])
    save_figure(fig, tmp_path / "f.png")
    assert (tmp_path / "f.png").read_bytes().startswith(b"\x89PNG") and len(list(tmp_path.iterdir())) == 1
