"""The conventions every ``skinid`` command shares (fast: no FE simulation, no MPI).

- ``skinid --version`` prints the installed package's version;
- every option's help shows its default, and an option has one spelling in every command;
- an existing output is refused before any computing (exit 2, one line, its bytes unchanged)
  unless ``--force`` (or ``--resume``, where the output keeps finished work) is given, and so
  is an output whose folder cannot be written; ``--force`` replaces it whole;
- a sweep holds ``<out>.lock`` while it runs: a second sweep is refused, a stale lock is
  named with the command that removes it, and the lock is gone when the sweep ends;
- a refused command does not print PETSc's list of unused options.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from skinfem.outputs import write_atomically
from tests.cli_helpers import skinid

DIC = Path(__file__).parent / "data" / "dic" / "vic9_extract.csv"
MATERIAL = ["--mu", "0.0012", "--k1", "0.017", "--k2", "12", "--kappa", "0.28", "--theta", "30"]
SIMULATE = ["simulate", "--config", "small", *MATERIAL, "--alpha", "0.05", "-0.05"]
OLD_BYTES = b"an output that took hours"
PETSC_WARNING = "There are options you set that were not used"

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
    import inference.__main__ as inference_cli
    import skinfem.__main__ as skinfem_cli
    import surrogate.__main__ as surrogate_cli
    from skinfem.cli import ROUTES

    roots = {"": skinfem_cli.build_parser(), "surrogate": surrogate_cli.build_parser()}
    roots |= {name: inference_cli.build_parser(f"skinid {name}") for name, (module, _) in ROUTES.items()
              if module == "inference.__main__"}
    parsers = {}
    for prefix, parser in roots.items():
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        children = subs[0].choices if subs else {"": parser}
        parsers |= {f"{prefix} {name}".strip(): p for name, p in children.items()}
    return parsers


PARSERS = command_parsers()


def visible_options(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in parser._actions if a.option_strings and a.help is not argparse.SUPPRESS
            and not isinstance(a, argparse._HelpAction)]


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


def assert_refused(res: subprocess.CompletedProcess, message: str) -> None:
    """Exit status 2, one line on stderr containing ``message``, no traceback or PETSc list."""
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2, res.stderr
    assert len(lines) == 1 and message in lines[0], res.stderr
    assert PETSC_WARNING not in res.stdout + res.stderr


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
    from skinfem.config import PARAM_NAMES, load_config
    from skinfem.io import STATUS_OK, create_dataset, write_simulation

    config = load_config("small")
    bounds = np.array([config.sweep.bounds[n] for n in PARAM_NAMES])
    rng = np.random.default_rng(0)
    unit = rng.uniform(size=(12, 5))
    params = bounds[:, 0] + unit * np.ptp(bounds, axis=1)
    designs, t = np.array([[0.05, -0.05], [0.05, 0.05]]), np.array([0.5, 1.0])
    g = np.linspace(-15, 15, 6)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    create_dataset(path, config, params, designs, t, xy, np.ones(len(xy)), np.r_[np.zeros(10), np.ones(2)],
                   "fake", bounds)
    shape = np.exp(-(xy**2).sum(1) / 200)
    for i, u in enumerate(unit):
        for j, (a11, a22) in enumerate(designs):
            frames = [np.column_stack([(1 + u[0]) * a11 * s * shape, (1 + u[1]) * a22 * s * shape,
                                       0.1 * u[4] * a11 * s * shape]) for s in t]
            write_simulation(path, i, j, np.array(frames), STATUS_OK)
    return path


# ---------------------------------------------------------------- version, help, spellings


def test_version_is_the_installed_packages():
    res = skinid("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"skinid {metadata.version('skinid')}"
    assert len(res.stdout.splitlines()) == 1


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
    import inference.__main__ as inference_cli

    parser = inference_cli.build_parser("skinid study")
    args = parser.parse_args(["noise", "--data", "d.h5", "--design", "7", "--out", "o"])
    assert args.designs == 7
    assert "--design is deprecated; use --designs" in capsys.readouterr().err
    assert not re.search(r"--design\b(?!s)", PARSERS["study noise"].format_help())
    with pytest.raises(SystemExit):  # one of the two is still required
        parser.parse_args(["noise", "--data", "d.h5", "--out", "o"])
    assert "--designs is required" in capsys.readouterr().err


# ---------------------------------------------------------------- existing outputs

REFUSALS = {  # command -> (its arguments before --out, the output's name)
    "simulate": (SIMULATE, "run.h5"),
    "sweep": (["sweep", "--config", "small", "--quiet"], "data.h5"),
    "merge": (["merge", "shard0.h5", "shard1.h5"], "data.h5"),
    "noise": (["noise", "--data", "data.h5", "--length", "1", "--level", "0.05"], "noisy.h5"),
    "surrogate fit": (["surrogate", "fit", "--data", "data.h5"], "emu"),
    "infer": (["infer", "--emulator", "emu", "--data", "data.h5", "--material", "0"], "post"),
    "study test-set": (["study", "test-set", "--emulator", "emu", "--data", "data.h5", "--designs", "2"], "study"),
    "study setups": (["study", "setups", "--emulator", "emu", "--data", "data.h5", "--designs", "2"], "study"),
    "study noise": (["study", "noise", "--data", "data.h5", "--designs", "2"], "study"),
    "check": (["check", "--config", "small", "--measurement", "m.csv", "--noise-sd", "1e-4", "1e-4", "1e-4"],
              "report"),
    "measurement import": (["measurement", "import", DIC, "--alpha", "0.05", "-0.02", "--t", "0.8"], "m.csv"),
    "measurement show": (["measurement", "show", DIC], "m.png"),
}


@pytest.mark.parametrize("command", list(REFUSALS))
def test_an_existing_output_is_refused_before_any_computing(command, tmp_path):
    args, name = REFUSALS[command]
    out = tmp_path / name
    kept = old_output(out)
    res = skinid(*args, "--out", out, cwd=tmp_path)
    assert_refused(res, f"error: {out} exists; pass --force to replace it")
    assert kept.read_bytes() == OLD_BYTES
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no lock, temporary or partial file left


def test_simulate_refuses_existing_fields_and_fields_that_would_overwrite_out(tmp_path):
    kept = old_output(tmp_path / "fields.h5")  # the data file of fields.xdmf
    res = skinid(*SIMULATE, "--out", tmp_path / "run.h5", "--fields", tmp_path / "fields.xdmf")
    assert_refused(res, f"error: {kept} exists; pass --force to replace it")
    res = skinid(*SIMULATE, "--out", tmp_path / "run.h5", "--fields", tmp_path / "run.xdmf")
    assert_refused(res, "writes its data to")
    assert kept.read_bytes() == OLD_BYTES and not (tmp_path / "run.h5").exists()


def test_surrogate_validate_refuses_to_replace_a_validation(tmp_path):
    kept = old_output(tmp_path / "emu")
    (tmp_path / "emu" / "validation.json").write_bytes(OLD_BYTES)
    res = skinid("surrogate", "validate", "--emulator", tmp_path / "emu")
    assert_refused(res, f"error: {tmp_path / 'emu' / 'validation.json'} exists; pass --force to replace it")
    assert (tmp_path / "emu" / "validation.json").read_bytes() == kept.read_bytes() == OLD_BYTES


@pytest.mark.parametrize("command", ["sweep", "study test-set", "check"])
def test_force_and_resume_exclude_each_other(command, tmp_path):
    args, name = REFUSALS[command]
    res = skinid(*args, "--out", tmp_path / name, "--force", "--resume", cwd=tmp_path)
    assert_refused(res, "--resume completes an existing output and --force replaces it")


def test_merge_and_noise_force_replace_a_file(tmp_path):
    from skinfem.io import StrainDataset

    shard = fake_dataset(tmp_path / "shard.h5")
    for args, out in [(["merge", shard], tmp_path / "merged.h5"),
                      (["noise", "--data", shard, "--length", "5", "--level", "0.05"], tmp_path / "noisy.h5")]:
        old_output(out)
        res = skinid(*args, "--out", out, "--force")
        assert res.returncode == 0, res.stderr
        assert StrainDataset.open(out).status.tolist() == StrainDataset.open(shard).status.tolist()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["merged.h5", "noisy.h5", "shard.h5"]


# ---------------------------------------------------------------- folders that cannot be written


@pytest.mark.parametrize("command", ["simulate", "sweep", "surrogate fit", "infer", "noise"])
def test_an_output_in_a_file_is_refused_before_any_computing(command, tmp_path):
    args, name = REFUSALS[command]
    (tmp_path / "file").write_bytes(OLD_BYTES)
    res = skinid(*args, "--out", tmp_path / "file" / name, cwd=tmp_path)
    assert_refused(res, f"'{tmp_path / 'file'}' is a file, not a folder")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only folder: chmod cannot refuse it")
@pytest.mark.parametrize("command", ["simulate", "sweep", "surrogate fit", "study noise", "measurement import"])
def test_an_unwritable_folder_is_refused_before_any_computing(command, tmp_path):
    args, name = REFUSALS[command]
    folder = tmp_path / "read_only"
    folder.mkdir(mode=0o500)
    try:
        res = skinid(*args, "--out", folder / "sub" / name, cwd=tmp_path)
    finally:
        folder.chmod(0o700)
    assert_refused(res, f"'{folder}' is not writable")
    assert list(folder.iterdir()) == []


def test_check_output_asks_the_folder_for_write_permission(tmp_path, monkeypatch):
    """The check the test above makes through the commands, where root cannot make it."""
    from skinfem import outputs

    asked = []
    monkeypatch.setattr(outputs.os, "access", lambda path, mode: asked.append((Path(path), mode)) and False)
    with pytest.raises(ValueError, match=f"'{tmp_path}' is not writable"):
        outputs.check_output(tmp_path / "new" / "data.h5")
    assert asked == [(tmp_path, os.W_OK | os.X_OK)]


# ---------------------------------------------------------------- the sweep lock


def dead_pid() -> int:
    """The id of a process that has ended."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_a_second_sweep_to_the_same_output_is_refused(tmp_path):
    out, lock = tmp_path / "data.h5", tmp_path / "data.h5.lock"
    lock.write_text(f"{os.getpid()}\n")  # a sweep that runs: this process
    res = skinid("sweep", "--config", "small", "--out", out, "--resume", "--quiet")
    assert_refused(res, f"{out} is being written by another sweep (PID {os.getpid()}")
    assert lock.read_text() == f"{os.getpid()}\n" and not out.exists()


def test_a_stale_lock_is_reported_with_its_removal(tmp_path):
    out, lock = tmp_path / "data.h5", tmp_path / "data.h5.lock"
    pid = dead_pid()
    lock.write_text(f"{pid}\n")
    res = skinid("sweep", "--config", "small", "--out", out, "--quiet")
    assert_refused(res, f"stale lock {lock} (PID {pid} is not running)")
    assert f"rm '{lock}'" in res.stderr and lock.exists()


def test_the_lock_is_removed_when_the_sweep_ends_on_an_error(tmp_path):
    out = tmp_path / "data.h5"
    old_output(out)  # refused after the lock is taken
    res = skinid("sweep", "--config", "small", "--out", out, "--quiet")
    assert_refused(res, "exists; pass --force to replace it or --resume to complete it")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.h5"]


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
