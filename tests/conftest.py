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
