"""Shared fixtures: small models are built once per test session (JIT and mesh cached)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")


@pytest.fixture(scope="session")
def mesh_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("meshes")


@pytest.fixture(scope="session")
def small_config():
    from skinfem.config import load_config

    return load_config("small")


@pytest.fixture(scope="session")
def small_model(small_config, mesh_dir):
    from skinfem.model import SkinModel

    return SkinModel(small_config, mesh_dir=mesh_dir)


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory, mesh_dir):
    """The ``small`` preset sweep (80 simulations), run on 2 MPI groups when mpirun exists."""
    from tests.cli_helpers import MPIRUN, skinid

    out = tmp_path_factory.mktemp("small") / "small.h5"
    ranks = 2 if MPIRUN else 1
    res = skinid("sweep", "--config", "small", "--mesh-dir", mesh_dir, "--out", out, "--quiet", ranks=ranks)
    assert res.returncode == 0, res.stderr
    return out


@pytest.fixture(scope="session")
def small_cell_average_dataset(tmp_path_factory, mesh_dir):
    """The ``small`` sweep with the paper's observable, the top skin cell's average strain, for
    the paper's "mixed" design and its mirror only (32 simulations instead of 80)."""
    import re

    from skinfem.config import PRESET_DIR
    from tests.cli_helpers import MPIRUN, skinid

    folder = tmp_path_factory.mktemp("small_cells")
    config = folder / "small_cells.toml"
    text = (PRESET_DIR / "small.toml").read_text().replace('name = "small"', 'name = "small_cells"')
    text = re.sub(r"(?m)^designs = .*$", "designs = [[0.05, -0.05], [-0.05, 0.05]]", text)
    config.write_text(text + '\n[observable]\nkind = "top_cell_average"\n')
    out = folder / "small_cells.h5"
    res = skinid("sweep", "--config", config, "--mesh-dir", mesh_dir, "--out", out, "--quiet", ranks=2 if MPIRUN else 1)
    assert res.returncode == 0, res.stderr
    return out


def _emulator_of(dataset, folder):
    """An emulator of a sweep (GPs on half of the training rows), saved; returns its folder."""
    from skinfem.io import StrainDataset
    from surrogate.emulator import fit_emulator

    emulator = fit_emulator(StrainDataset.open(dataset), gp_fraction=0.5, restarts=1, seed=0)
    return emulator.save(folder / "emu")


@pytest.fixture(scope="session")
def small_emulator(small_dataset, tmp_path_factory):
    """An emulator of the small sweep, saved (tests reload it)."""
    return _emulator_of(small_dataset, tmp_path_factory.mktemp("emulator"))


@pytest.fixture(scope="session")
def small_cell_average_emulator(small_cell_average_dataset, tmp_path_factory):
    """An emulator of the small sweep with the top-cell-average observable, saved."""
    return _emulator_of(small_cell_average_dataset, tmp_path_factory.mktemp("emulator_cells"))
