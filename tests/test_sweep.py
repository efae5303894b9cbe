"""Sweeps: stratified design, kill-safe resume, shards + merge, recorded failures, MPI groups."""

import signal
import subprocess
import time

import h5py
import numpy as np
import pytest

from skinfem.config import load_config
from skinfem.io import STATUS_FAILED, STATUS_OK, StrainDataset
from skinfem.sweep import (
    SimulationResult,
    latin_hypercube,
    merge_datasets,
    parse_shard,
    pending_simulations,
    run_sweep,
    spool_folder,
    test_split,
)
from tests.cli_helpers import MPIRUN, skinid, skinid_command, skinid_env


def tiny_config(**sweep):
    """Small mesh, 3 increments, a few materials and two designs (~1 s per simulation)."""
    return load_config("small").with_changes(
        solver={"increments": 3},
        sweep={"n_materials": 4, "n_test": 1, "designs": [[0.05, -0.05], [-0.05, 0.05]], **sweep},
    )


@pytest.fixture(scope="module")
def tiny_toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("sweep") / "tiny.toml"
    path.write_text(tiny_config().to_toml())
    return path


@pytest.fixture(scope="module")
def reference(tmp_path_factory, tiny_toml, mesh_dir):
    """An uninterrupted serial sweep of the tiny configuration."""
    out = tmp_path_factory.mktemp("sweep") / "reference.h5"
    res = skinid("sweep", "--config", tiny_toml, "--mesh-dir", mesh_dir, "--out", out, "--quiet")
    assert res.returncode == 0, res.stderr
    assert "ran 8 simulations (0 failed)" in res.stdout
    return out


def assert_same_dataset(a_path, b_path):
    """Every dataset and attribute equal, except wall times and the creation stamp."""
    with h5py.File(a_path) as a, h5py.File(b_path) as b:
        assert set(a.attrs) == set(b.attrs)
        for key in a.attrs:
            if key != "created":
                assert np.array_equal(a.attrs[key], b.attrs[key]), key
        names = []
        a.visit(lambda name: names.append(name) if isinstance(a[name], h5py.Dataset) else None)
        assert names and all(name in b for name in names)
        for name in names:
            if name != "seconds":
                x, y = a[name][...], b[name][...]
                assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name


# -- design --------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [7, 120])
def test_latin_hypercube_has_one_sample_per_stratum(n):
    bounds = np.array([[1.0, 2.0], [0.0, 90.0], [-3.0, -1.0]])
    x = latin_hypercube(bounds, n, seed=122)
    assert x.shape == (n, 3)
    for d, (low, high) in enumerate(bounds):
        stratum = np.floor((x[:, d] - low) / (high - low) * n).astype(int)
        assert sorted(stratum) == list(range(n))
    assert np.array_equal(x, latin_hypercube(bounds, n, seed=122))
    assert not np.array_equal(x, latin_hypercube(bounds, n, seed=123))


def test_split_is_seeded_and_sized():
    split = test_split(120, 20, seed=122)
    assert split.sum() == 20 and split.dtype == np.int8
    assert np.array_equal(split, test_split(120, 20, seed=122))
    assert not np.array_equal(split, test_split(120, 20, seed=1))


def test_pending_and_shards_partition_the_work():
    status = np.array([[1, 0, -1], [0, 0, 0]], dtype=np.int8)
    assert pending_simulations(status) == [(0, 1), (1, 0), (1, 1), (1, 2)]
    assert pending_simulations(status, retry_failed=True)[1] == (0, 2)
    shards = [pending_simulations(np.zeros((3, 4)), (i, 3)) for i in range(3)]
    flat = sorted(p for shard in shards for p in shard)
    assert flat == [(i, j) for i in range(3) for j in range(4)]
    assert parse_shard("3/16") == (3, 16)
    for bad in ("16/16", "a/b", "3"):
        with pytest.raises(ValueError, match="shard"):
            parse_shard(bad)


# -- running ------------------------------------------------------------------------------
def test_sweep_writes_the_plan(reference):
    data = StrainDataset.open(reference)
    config = tiny_config()
    assert data.shape[:3] == (4, 2, 3)
    assert np.all(data.status == STATUS_OK)
    assert data.split.sum() == 1
    sweep = config.sweep
    assert np.array_equal(data.lower, [sweep.bounds[n][0] for n in ("mu", "k1", "k2", "kappa", "theta")])
    strain = data.strain()
    assert np.all(np.isfinite(strain))
    # the design (0.05, -0.05) stretches x and compresses y under the membrane
    centre = np.argmin(np.linalg.norm(data.xy, axis=1))
    assert np.all(strain[:, 0, -1, centre, 0] > 0.03) and np.all(strain[:, 0, -1, centre, 1] < -0.03)
    assert data.config.to_toml() == config.to_toml()


def test_killed_sweep_resumes_to_the_same_file(reference, tiny_toml, mesh_dir, tmp_path):
    out = tmp_path / "killed.h5"
    proc = subprocess.Popen(
        skinid_command("sweep", "--config", tiny_toml, "--mesh-dir", mesh_dir, "--out", out, "--quiet"),
        env=skinid_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 300
    done = 0
    while done < 3 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
        try:
            done = int(np.count_nonzero(StrainDataset.open(out).status))
        except (OSError, ValueError, KeyError):
            continue  # not created yet, or being written at this instant
    time.sleep(0.3)  # land somewhere inside the next simulation or write
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed = StrainDataset.open(out)  # readable after SIGKILL
    assert 3 <= np.count_nonzero(killed.status) < killed.status.size
    ok = killed.status == STATUS_OK
    assert np.all(np.isfinite(killed.strain()[ok]))

    resume = ("sweep", "--config", tiny_toml, "--mesh-dir", mesh_dir, "--out", out, "--resume", "--quiet")
    res = skinid(*resume)  # the killed sweep could not remove its lock: it is named, with its removal
    lock = out.with_name("killed.h5.lock")
    assert res.returncode == 2 and f"stale lock {lock}" in res.stderr and f"rm '{lock}'" in res.stderr
    lock.unlink()
    res = skinid(*resume)
    assert res.returncode == 0, res.stderr
    assert f"{np.count_nonzero(killed.status)} were already done" in res.stdout
    assert_same_dataset(out, reference)
    assert not lock.exists()


def spool_from(reference, i: int, j: int, out, seconds: float) -> None:
    """Leave the reference's simulation (i, j) in ``out``'s spool, marked by its ``seconds``."""
    data = StrainDataset.open(reference)
    strain = data.strain(i, j)
    SimulationResult(i, j, strain, int(data.status[i, j]), "", int(data.newton_iterations[i, j]), seconds).spool(
        spool_folder(out)
    )


def test_a_resumed_sweep_records_what_other_groups_left_in_the_spool(reference, tiny_toml, mesh_dir, tmp_path):
    """A group other than rank 0's spools each finished simulation at once; when the sweep is
    killed before the writer records it, resuming records it instead of running it again."""
    out = tmp_path / "killed.h5"
    out.write_bytes(reference.read_bytes())
    with h5py.File(out, "r+") as f:  # as killed: (2, 0) spooled by another group, (3, 1) not finished
        f["status"][2, 0] = f["status"][3, 1] = 0
    spool_from(reference, 2, 0, out, seconds=1234.5)
    (spool_folder(out) / ".3_1.99.tmp.npz").write_bytes(b"half-written")  # a write in progress when killed
    report = run_sweep(load_config(tiny_toml), out, resume=True, mesh_dir=mesh_dir, progress=False)
    assert report.n_run == 1 and report.n_done_before == 7
    assert StrainDataset.open(out).seconds[2, 0] == 1234.5
    assert not spool_folder(out).exists()
    assert_same_dataset(out, reference)


def test_a_new_sweep_discards_a_stale_spool(reference, tiny_toml, mesh_dir, tmp_path):
    out = tmp_path / "new.h5"
    spool_from(reference, 0, 0, out, seconds=1234.5)
    with np.load(next(spool_folder(out).glob("*.npz"))) as f:
        assert f["strain"].shape == StrainDataset.open(reference).strain(0, 0).shape
    run_sweep(load_config(tiny_toml), out, shard=(0, 8), mesh_dir=mesh_dir, progress=False)
    data = StrainDataset.open(out)
    assert data.status.tolist() == [[STATUS_OK, 0]] + [[0, 0]] * 3 and data.seconds[0, 0] != 1234.5
    assert not spool_folder(out).exists()


def test_existing_output_needs_resume_and_the_same_config(reference, tiny_toml, mesh_dir, tmp_path):
    res = skinid("sweep", "--config", tiny_toml, "--mesh-dir", mesh_dir, "--out", reference)
    assert res.returncode == 2 and "--resume" in res.stderr
    other = tmp_path / "other.toml"
    other.write_text(tiny_config(seed=5).to_toml())
    res = skinid("sweep", "--config", other, "--mesh-dir", mesh_dir, "--out", reference, "--resume")
    assert res.returncode == 2 and "another configuration" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_shards_merged_equal_a_single_run(reference, tiny_toml, mesh_dir, tmp_path):
    shards = []
    for i in range(3):
        shards.append(tmp_path / f"shard{i}.h5")
        res = skinid(
            "sweep", "--config", tiny_toml, "--mesh-dir", mesh_dir, "--out", shards[-1], "--shard", f"{i}/3", "--quiet"
        )
        assert res.returncode == 0, res.stderr
    assert [np.count_nonzero(StrainDataset.open(s).status) for s in shards] == [3, 3, 2]
    res = skinid("merge", *shards, "--out", tmp_path / "merged.h5")
    assert res.returncode == 0, res.stderr
    assert_same_dataset(tmp_path / "merged.h5", reference)


def test_merge_refuses_other_configs(reference, tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(reference) as src, h5py.File(other, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        for name in src:
            src.copy(name, dst)
        dst.attrs["mesh_sha256"] = "0" * 64
    with pytest.raises(ValueError, match="another mesh"):
        merge_datasets([reference, other], tmp_path / "m.h5")
    assert not (tmp_path / "m.h5").exists()


def test_failed_simulation_is_recorded_and_the_sweep_goes_on(mesh_dir, tmp_path):
    """One Newton iteration and no cut-back: the unloaded design converges, the loaded fails."""
    from skinfem.sweep import run_sweep

    config = tiny_config(n_materials=2, designs=[[0.05, -0.05], [0.0, 0.0]]).with_changes(
        solver={"increments": 3, "max_iterations": 1, "max_cutbacks": 0}
    )
    report = run_sweep(config, tmp_path / "fail.h5", mesh_dir=mesh_dir, progress=False)
    data = StrainDataset.open(tmp_path / "fail.h5")
    assert data.status[:, 0].tolist() == [STATUS_FAILED] * 2
    assert data.status[:, 1].tolist() == [STATUS_OK] * 2
    assert "Newton failed" in data.messages[0, 0]
    assert np.all(np.isnan(data.strain(0, 0))) and np.all(data.strain(0, 1) == 0)
    assert report.n_failed == 2 and report.n_run == 4
    assert "(2 failed)" in str(report)


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="mpirun not found")
@pytest.mark.parametrize("ranks_per_sim", [1, 2])
def test_mpi_groups_equal_serial(reference, tiny_toml, mesh_dir, tmp_path, ranks_per_sim):
    out = tmp_path / "mpi.h5"
    res = skinid(
        "sweep",
        "--config",
        tiny_toml,
        "--mesh-dir",
        mesh_dir,
        "--out",
        out,
        "--ranks-per-sim",
        ranks_per_sim,
        "--quiet",
        ranks=2,
    )
    assert res.returncode == 0, res.stderr
    assert not spool_folder(out).exists()
    a, b = StrainDataset.open(out).strain(), StrainDataset.open(reference).strain()
    assert np.abs(a - b).max() <= 1e-6 * np.abs(b).max()
