"""The command line: simulate end to end (serial and under mpirun), and clear input errors."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skinfem.io import StrainDataset
from tests.cli_helpers import MPIRUN, skinid, skinid_env

MATERIAL = ["--mu", "0.0012", "--k1", "0.017", "--k2", "12", "--kappa", "0.28", "--theta", "30"]
DESIGN = ["--alpha", "0.05", "-0.05"]


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory, mesh_dir):
    out = tmp_path_factory.mktemp("cli") / "serial.h5"
    res = skinid(
        "simulate",
        "--config",
        "small",
        "--mesh-dir",
        str(mesh_dir),
        *MATERIAL,
        *DESIGN,
        "--out",
        str(out),
        "--fields",
        str(out.with_name("fields.xdmf")),
    )
    assert res.returncode == 0, res.stderr
    return out, res


def test_simulate_writes_the_dataset_contract(serial_run):
    out, res = serial_run
    assert "wrote" in res.stdout
    ds = StrainDataset.open(out)
    assert ds.params.shape == (1, 5) and ds.designs.shape == (1, 2)
    np.testing.assert_allclose(ds.params[0], [0.0012, 0.017, 12, 0.28, 30])
    assert ds.status.tolist() == [[1]]
    strain = ds.strain()
    assert strain.shape == (1, 1, 10, len(ds.xy), 3) and strain.dtype == np.float32
    assert np.all(np.isfinite(strain))
    assert ds.config.name == "small" and len(ds.mesh_sha256) == 64 and "numpy" in ds.versions
    fields = out.with_name("fields.xdmf")  # with its fields.h5, moved into place when complete
    assert sorted(p.name for p in out.parent.iterdir()) == ["fields.h5", "fields.xdmf", "serial.h5"]
    assert "fields.h5:/" in fields.read_text()


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="mpirun not found")
def test_two_ranks_equal_serial(serial_run, mesh_dir, tmp_path):
    out = tmp_path / "mpi.h5"
    res = skinid(
        "simulate", "--config", "small", "--mesh-dir", str(mesh_dir), *MATERIAL, *DESIGN, "--out", str(out), ranks=2
    )
    assert res.returncode == 0, res.stderr
    serial = StrainDataset.open(serial_run[0])
    parallel = StrainDataset.open(out)
    np.testing.assert_array_equal(parallel.xy, serial.xy)
    a, b = parallel.strain().astype(float), serial.strain().astype(float)
    assert np.abs(a - b).max() <= 1e-6 * np.abs(b).max()  # float32 storage resolution


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="mpirun not found")
def test_two_ranks_equal_serial_in_float64(small_model, mesh_dir, tmp_path):
    from skinfem.params import Design, SkinParams

    out = tmp_path / "mpi.npy"
    script = Path(__file__).with_name("mpi_simulate.py")
    res = subprocess.run(
        [MPIRUN, "-n", "2", sys.executable, str(script), str(mesh_dir), str(out)],
        capture_output=True,
        text=True,
        env=skinid_env(),
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    frames = small_model.simulate(SkinParams(1.2e-3, 0.017, 12.0, 0.28, 30.0), Design(0.05, -0.05))
    serial = np.concatenate([frames.xy.ravel(), frames.strain.ravel()])
    parallel = np.load(out)
    np.testing.assert_allclose(parallel, serial, rtol=0, atol=1e-8 * np.abs(frames.strain).max())


@pytest.mark.parametrize(
    "change, message",
    [
        ({"--mu": ["-0.001"]}, "mu must be > 0"),
        ({"--kappa": ["0.5"]}, "kappa must be in [0, 1/3]"),
        ({"--alpha": ["0.6", "-0.05"]}, "|alpha11| must be < 0.5"),
        ({"--config": ["nope"]}, "no such file and no such preset"),
    ],
)
def test_bad_input_is_one_clear_line(tmp_path, change, message):
    options = {
        "--config": ["small"],
        **{k: [v] for k, v in zip(MATERIAL[::2], MATERIAL[1::2])},
        "--alpha": DESIGN[1:],
    } | change
    flat = [x for key, values in options.items() for x in (key, *values)]
    out = tmp_path / "x.h5"
    res = skinid("simulate", *flat, "--out", str(out))
    assert res.returncode == 2
    assert message in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert "WARNING! There are options" not in res.stdout  # PETSc lists no options of the run that did not happen
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_unknown_config_key_is_named(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[mesh]\nh_membrane = 2.0\nh_farr = 6.0\n")
    res = skinid("mesh", "--config", str(cfg), "--mesh-dir", str(tmp_path / "m"))
    assert res.returncode == 2 and "'mesh.h_farr'" in res.stderr


def test_missing_mesh_dir_file_is_reported(tmp_path):
    from mpi4py import MPI

    from skinfem.mesh import read_mesh

    with pytest.raises(FileNotFoundError, match="skinid mesh"):
        read_mesh(tmp_path / "none.msh", MPI.COMM_WORLD)


def test_an_existing_output_is_refused_before_any_computing(serial_run, mesh_dir, tmp_path):
    """simulate and merge never replace a dataset silently; --force does; an output folder that
    cannot be made is refused before the simulation, not after it."""
    out, _ = serial_run
    existing = tmp_path / "existing.h5"
    existing.write_bytes(b"an 80-simulation dataset")
    common = ["--config", "small", "--mesh-dir", str(mesh_dir), *MATERIAL, *DESIGN]
    res = skinid("simulate", *common, "--out", existing)
    assert res.returncode == 2 and "exists" in res.stderr and "--force" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and existing.read_bytes() == b"an 80-simulation dataset"
    res = skinid("merge", str(out), "--out", existing)
    assert res.returncode == 2 and "--force" in res.stderr and existing.read_bytes() == b"an 80-simulation dataset"
    res = skinid("merge", str(out), "--out", existing, "--force")
    assert res.returncode == 0, res.stderr
    assert StrainDataset.open(existing).status.size == StrainDataset.open(out).status.size == 1

    res = skinid("simulate", *common, "--out", existing / "x.h5")  # a folder that cannot be made
    assert res.returncode == 2 and "is a file, not a folder" in res.stderr and "simulated" not in res.stdout
