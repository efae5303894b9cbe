"""The observable a simulation reports per skin cell: the surface strain converges, the top-cell
average does not (skinfem.strain, ``observable.kind``)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.dic import surface_log_strain
from skinfem.fenics import dolfinx
from skinfem.io import StrainDataset
from skinfem.model import SkinModel
from skinfem.params import Design, SkinParams
from skinfem.strain import SkinStrainSampler, SurfaceStrainSampler
from tests.cli_helpers import MPIRUN, skinid, skinid_env

PARAMS = SkinParams(1.2e-3, 0.017, 12.0, 0.28, 30.0)
DESIGN = Design(0.05, -0.05)


def top_cells_of_box(degree: int):
    """A displacement space on a 2-layer hexahedral box [-3, 3]^2 x [-1, 0] and its top cells."""
    mesh = dolfinx.mesh.create_box(
        MPI.COMM_SELF, [[-3, -3, -1], [3, 3, 0]], [4, 3, 2], dolfinx.mesh.CellType.hexahedron
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (3,)))
    n = mesh.topology.index_map(3).size_local
    centroids = mesh.geometry.x[mesh.geometry.dofmaps[0][:n]].mean(axis=1)
    return dolfinx.fem.Function(V), np.flatnonzero(centroids[:, 2] > -0.5).astype(np.int32)


@pytest.mark.parametrize("degree", [1, 2])
def test_an_affine_field_is_measured_exactly_and_differs_from_the_cell_average(degree):
    """u = A X: the surface strain is that of the 3 x 2 surface gradient A[:, :2] (closed form),
    whatever the out-of-plane column; the cell average of ln V includes it."""
    A = np.array([[0.04, 0.01, 0.05], [-0.02, -0.03, 0.02], [0.01, 0.02, 0.06]])
    u, cells = top_cells_of_box(degree)
    u.interpolate(lambda x: A @ x)
    surface = SurfaceStrainSampler(u, cells, 2)()
    expected = surface_log_strain(A[None, :, :2])[0]
    np.testing.assert_allclose(surface, np.broadcast_to(expected, surface.shape), atol=1e-12)
    average = SkinStrainSampler(u, cells, 2)()
    assert np.abs(average - surface).max() > 1e-3


def test_a_quadratic_element_s_surface_gradient_is_the_point_gradient_within_the_window_bias():
    """u_x = c X^2 Y on Q2 (exactly representable): the fitted slope in x at a face centre is
    exact (2 c X0 Y0); the slope in y is c (X0^2 + mean(dx^2)), the O(window^2) bias of the fit,
    with sample offsets dx = w s, s in {0, +-1/4, +-1/2}: mean(dx^2) = w^2 / 8."""
    c = 0.01
    u, cells = top_cells_of_box(2)
    u.interpolate(lambda x: np.stack([c * x[0] ** 2 * x[1], 0 * x[0], 0 * x[0]]))
    sampler = SurfaceStrainSampler(u, cells, 2)
    H = sampler._gradient(u)
    x = u.function_space.mesh.geometry.x[u.function_space.mesh.geometry.dofmaps[0][cells]]
    X0, Y0 = x[:, :, 0].mean(axis=1), x[:, :, 1].mean(axis=1)
    w = SurfaceStrainSampler.WINDOW_FRACTION * np.min(np.ptp(x[:, :, :2], axis=1), axis=1)
    np.testing.assert_allclose(H[:, 0, 0], 2 * c * X0 * Y0, atol=1e-12)
    np.testing.assert_allclose(H[:, 0, 1], c * (X0**2 + w**2 / 8), atol=1e-12)


@pytest.fixture(scope="module")
def layer_series(small_config, mesh_dir):
    """Last-frame strain (n_cells, 3) and centroids for each observable and 1 or 2 skin layers."""
    out = {}
    for kind in ("surface", "top_cell_average"):
        for layers in (1, 2):
            config = small_config.with_changes(
                mesh={"skin_layers": layers}, observable={"kind": kind}, solver={"increments": 2}
            )
            frames = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir).simulate(PARAMS, DESIGN)
            out[kind, layers] = frames.strain[-1], frames.xy
    return out


def test_the_surface_under_the_membrane_carries_its_eigenstrain(layer_series):
    """The skin surface is bonded to the stiff membrane: at its centre the surface strain is
    ln(1 + alpha) (1e-4) for any number of skin layers, while the cell average lies below it
    (the muscle restrains the skin's underside) and moves towards it as layers are added."""
    target = np.log1p([DESIGN.alpha11, DESIGN.alpha22])
    means = {}
    for (kind, layers), (strain, xy) in layer_series.items():
        means[kind, layers] = strain[np.linalg.norm(xy, axis=1) < 3, :2].mean(axis=0)
    for layers in (1, 2):
        np.testing.assert_allclose(means["surface", layers], target, rtol=1e-4)
    gap1 = target - means["top_cell_average", 1]
    gap2 = target - means["top_cell_average", 2]
    assert np.all(np.abs(gap1) > 0.1 * np.abs(target))
    assert np.all(np.abs(gap2) < 0.7 * np.abs(gap1))


def plausibility_of(dataset: Path):
    """(ratio, cosine) of :func:`assess_plausibility` for every simulation, design and frame of a
    sweep whose design imposes a measurable strain: the model's own fields as measurements."""
    from inference.dic_import import assess_plausibility

    data = StrainDataset.open(dataset)
    half = data.config.mesh.membrane_size / 2
    checks = [
        assess_plausibility(data.xy, data.strain(i)[j, k], alpha, t, half)
        for i in range(len(data.params))
        for j, alpha in enumerate(data.designs)
        for k, t in enumerate(data.t)
    ]
    return np.array([(c.ratio, c.cosine) for c in checks if np.isfinite(c.ratio)])


def test_the_model_s_own_fields_pass_the_import_plausibility_check_with_margin(
    small_dataset, small_cell_average_dataset
):
    """``skinid measurement import`` compares the mean strain under the membrane with the design's
    ln(1 + t alpha) (docs/measurements.md). The surface, which the bonded membrane carries, is at
    ratio 1 and cosine 1 in every design and frame of the ``small`` sweep; the mid-thickness cell
    average, which the muscle restrains, lies lower but a factor > 4 inside the ratio bounds and
    inside the direction cone."""
    from inference.dic_import import COS_MIN, RATIO_RANGE

    surface = plausibility_of(small_dataset)
    assert len(surface) == 16 * 5 * 10
    np.testing.assert_allclose(surface, 1.0, atol=1e-3)
    cells = plausibility_of(small_cell_average_dataset)
    ratio, cosine = cells[:, 0], cells[:, 1]
    assert np.median(ratio) < 1.0
    assert 4 * RATIO_RANGE[0] < ratio.min() and ratio.max() < RATIO_RANGE[1] / 4
    assert cosine.min() > COS_MIN


def test_the_surface_strain_moves_less_than_the_cell_average_through_the_thickness(layer_series):
    """Doubling the skin layers (1 -> 2, Q1 `small`) moves the surface field a quarter as much
    as the top-cell average (measured: 6 % vs 23 %, relative RMS)."""

    def change(kind):
        a, b = layer_series[kind, 1][0], layer_series[kind, 2][0]
        return np.sqrt(np.mean((b - a) ** 2) / np.mean(a**2))

    assert change("surface") < 0.4 * change("top_cell_average")


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="mpirun not found")
def test_the_surface_observable_on_two_ranks_equals_serial(small_config, mesh_dir, tmp_path):
    out = tmp_path / "mpi.npy"
    script = Path(__file__).with_name("mpi_simulate.py")
    res = subprocess.run(
        [MPIRUN, "-n", "2", sys.executable, str(script), str(mesh_dir), str(out), "surface"],
        capture_output=True,
        text=True,
        env=skinid_env(),
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    config = small_config.with_changes(observable={"kind": "surface"})
    frames = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir).simulate(PARAMS, DESIGN)
    serial = np.concatenate([frames.xy.ravel(), frames.strain.ravel()])
    np.testing.assert_allclose(np.load(out), serial, rtol=0, atol=1e-8 * np.abs(frames.strain).max())


def simulate_one(config, out: Path, mesh_dir) -> None:
    """`skinid simulate` of PARAMS, DESIGN with ``config`` (preset or TOML path) into ``out``."""
    material = [f"--{name}={value}" for name, value in zip(("mu", "k1", "k2", "kappa", "theta"), PARAMS.as_array())]
    res = skinid(
        "simulate",
        "--config",
        str(config),
        "--mesh-dir",
        str(mesh_dir),
        *material,
        "--alpha",
        str(DESIGN.alpha11),
        str(DESIGN.alpha22),
        "--out",
        str(out),
    )
    assert res.returncode == 0, res.stderr


def test_a_dataset_records_its_observable(tmp_path, mesh_dir):
    config = tmp_path / "surface.toml"
    config.write_text(
        'name = "small_surface"\n[mesh]\nh_membrane = 2.0\nh_far = 6.0\nmuscle_layers = 2\n'
        '[observable]\nkind = "surface"\n[solver]\nincrements = 2\n'
    )
    out = tmp_path / "one.h5"
    simulate_one(config, out, mesh_dir)
    ds = StrainDataset.open(out)
    assert ds.observable == "surface"
    import h5py

    with h5py.File(out) as f:
        assert f.attrs["observable"] == "surface"
    centre = np.linalg.norm(ds.xy, axis=1) < 3
    np.testing.assert_allclose(ds.strain()[0, 0, -1][centre, 0], np.log1p(0.05), rtol=1e-4)


def test_a_dataset_without_the_attribute_holds_the_cell_average(tmp_path, mesh_dir):
    """Files written before datasets recorded their observable hold the top-cell average."""
    import h5py

    out = tmp_path / "old.h5"
    simulate_one("small", out, mesh_dir)
    assert StrainDataset.open(out).observable == "surface"
    with h5py.File(out, "r+") as f:
        del f.attrs["observable"]
    assert StrainDataset.open(out).observable == "top_cell_average"
