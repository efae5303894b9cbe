"""Verification of the finite-element forward model on small meshes."""

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.config import MembraneConfig
from skinfem.fenics import dolfinx, ufl
from skinfem.materials import LaminaStiffness, hgo_energy, membrane_energy
from skinfem.model import SkinModel, extrapolate
from skinfem.params import Design, SkinParams
from skinfem.solver_work import SolverWork, WorkMeter
from tests.helpers import at_point, component_bc, solve_energy

PARAMS = SkinParams(mu=1.2e-3, k1=0.017, k2=12.0, kappa=0.28, theta=30.0)


def centre_cells(xy, radius):
    return np.linalg.norm(xy, axis=1) < radius


def test_zero_eigenstrain_gives_zero_displacement(small_model):
    frames = small_model.simulate(PARAMS, Design(0.0, 0.0))
    assert np.abs(small_model.u.x.array).max() == 0.0
    assert np.abs(frames.strain).max() == 0.0


def test_frames_are_finite_monotone_and_in_fixed_order(small_model):
    frames = small_model.simulate(PARAMS, Design(0.05, -0.05))
    assert frames.strain.shape == (10, len(frames.xy), 3)
    np.testing.assert_allclose(frames.t, np.arange(1, 11) / 10)
    assert np.all(np.isfinite(frames.strain))
    # canonical order: by y, then x
    order = np.lexsort((frames.xy[:, 0], frames.xy[:, 1]))
    np.testing.assert_array_equal(order, np.arange(len(order)))
    # the centre strain grows with the load
    c = np.argmin(np.linalg.norm(frames.xy, axis=1))
    assert np.all(np.diff(frames.strain[:, c, 0]) > 0)
    assert np.all(np.diff(frames.strain[:, c, 1]) < 0)


def test_reused_factorization_gives_the_newton_lu_fields(small_model, small_config, mesh_dir):
    """GMRES preconditioned by a stale LU (the default) and a factorization at every Newton
    step converge to the same fields, with the same Newton iterations and fewer factorizations.
    GMRES stops once its residual is below a tenth of the Newton tolerance, so the fields agree
    to that tolerance (~1e-9 of the largest strain), not to round-off."""
    design = Design(0.05, -0.05)
    reused = small_model.simulate(PARAMS, design)
    factorizations = small_model.factorizations
    plain_model = SkinModel(small_config.with_changes(solver={"refactor_krylov": 0}), mesh_dir=mesh_dir)
    plain = plain_model.simulate(PARAMS, design)
    np.testing.assert_allclose(reused.strain, plain.strain, rtol=0, atol=1e-8 * np.abs(plain.strain).max())
    assert reused.newton_iterations == plain.newton_iterations
    assert plain_model.factorizations == sum(plain.newton_iterations)
    assert 1 <= factorizations < sum(reused.newton_iterations) / 2


def test_a_released_factorisation_is_freed_and_made_again_for_the_same_fields(small_model):
    """A check holds its own mesh's model while the refined mesh's runs: releasing the kept LU
    factors leaves the solver an empty factor (made, with its memory limit, but not factorised),
    and the next simulation factorises again and finds the same fields to round-off."""
    design = Design(0.05, -0.05)
    before = small_model.simulate(PARAMS, design)
    pc = small_model.problem.solver.getKSP().getPC()
    assert pc.getFactorMatrix().getType() == "mumps" and pc.getFactorMatrix().assembled
    small_model.release_factorisation()
    assert not pc.getFactorMatrix().assembled
    meter = WorkMeter(MPI.COMM_SELF)
    after = small_model.simulate(PARAMS, design)
    assert meter.lap().factorisations == small_model.factorizations >= 1
    np.testing.assert_allclose(after.strain, before.strain, rtol=0, atol=1e-12)


def test_the_work_meter_counts_what_the_model_counts(small_model):
    """PETSc's event log (a check's cost per phase) against the model's own counters: one
    tangent per Newton iteration, the factorisations the model made, and at least one
    preconditioned GMRES iteration (a triangular solve) per Newton step; nothing between laps."""
    meter = WorkMeter(MPI.COMM_SELF)
    frames = small_model.simulate(PARAMS, Design(0.05, -0.05))
    work = meter.lap()
    assert work.newton_steps == sum(frames.newton_iterations) > 0
    assert work.factorisations == small_model.factorizations >= 1
    assert work.triangular_solves >= work.newton_steps
    assert meter.lap() == SolverWork()


def test_predictor_is_exact_for_polynomial_load_paths():
    """The increment predictor reproduces a quadratic path from three states (unequal steps,
    as after a cut-back) and a linear one from two; one state is kept as is."""
    a, b, c = np.array([1.0, -2.0]), np.array([0.5, 3.0]), np.array([-4.0, 0.25])
    path = lambda t: a + b * t + c * t**2  # noqa: E731
    np.testing.assert_allclose(extrapolate(0.45, [(t, path(t)) for t in (0.4, 0.3, 0.1)]), path(0.45), rtol=1e-13)
    line = lambda t: a + b * t  # noqa: E731
    np.testing.assert_allclose(extrapolate(0.2, [(0.1, line(0.1)), (0.0, line(0.0))]), line(0.2), rtol=1e-13)
    np.testing.assert_array_equal(extrapolate(0.1, [(0.0, a)]), a)


def test_a_simulation_does_not_depend_on_the_one_before(small_model, small_config, mesh_dir):
    """A model that solved another material first returns the same bits as a fresh one
    (datasets are reproducible across shards and resumed runs; needs PETSc's deterministic
    vector kernels, see skinfem.fenics)."""
    config = small_config.with_changes(solver={"increments": 3})
    other = SkinParams(mu=2e-3, k1=0.022, k2=15.0, kappa=0.27, theta=80.0)
    design = Design(-0.05, 0.05)
    used = SkinModel(config, mesh_dir=mesh_dir)
    used.simulate(other, Design(0.05, -0.05))
    after = used.simulate(PARAMS, design)
    fresh = SkinModel(config, mesh_dir=mesh_dir).simulate(PARAMS, design)
    assert after.newton_iterations == fresh.newton_iterations
    np.testing.assert_array_equal(after.strain, fresh.strain)


def test_membrane_reaches_its_eigenstrain(small_model):
    """The stiff membrane's own strain at its centre is ln(1 + alpha) within 0.5 %."""
    from skinfem.mesh import TAGS
    from skinfem.strain import SkinStrainSampler

    design = Design(0.05, -0.03)
    small_model.simulate(PARAMS, design)
    cells = small_model.cell_tags.find(TAGS["membrane"])
    sampler = SkinStrainSampler(small_model.u, cells, 2)
    strain = sampler()
    c = centre_cells(sampler.xy, 2.0)
    np.testing.assert_allclose(strain[c, 0], np.log1p(design.alpha11), rtol=5e-3)
    np.testing.assert_allclose(strain[c, 1], np.log1p(design.alpha22), rtol=5e-3)


def test_skin_follows_membrane_on_soft_substrate(small_config, mesh_dir):
    """On a very soft muscle the skin under the membrane centre is stretched to ln(1+alpha).

    With the paper's muscle (mu_m = 3.5e-3 MPa, stiffer than the skin) the cell-averaged
    (mid-thickness) skin strain is lower, because the muscle restrains the skin underside.
    """
    cfg = small_config.with_changes(muscle={"mu": 1e-6})
    model = SkinModel(cfg, mesh_dir=mesh_dir)
    design = Design(0.05, 0.05)
    frames = model.simulate(PARAMS, design)
    c = centre_cells(frames.xy, 2.0)
    np.testing.assert_allclose(frames.strain[-1, c, :2], np.log1p(0.05), rtol=0.02)


def test_free_membrane_reaches_eigenstrain_without_stress():
    """A membrane block with no skin attached deforms to F = F_g and carries no stress."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [4, 3, 1]], [4, 3, 1], dolfinx.mesh.CellType.hexahedron)
    a11, a22 = 0.04, -0.05
    lamina = LaminaStiffness.from_config(MembraneConfig())

    def energy(F):
        return membrane_energy(F, a11, a22, lamina)

    def rigid_motion_constraints(V):  # pin a corner, two components of a second, one of a third
        pins = (((0, 0, 0), (0, 1, 2)), ((4, 0, 0), (1, 2)), ((0, 3, 0), (2,)))
        return [component_bc(V, i, at_point(p), 0.0) for p, comps in pins for i in comps]

    u, V = solve_energy(mesh, energy, rigid_motion_constraints, "free_membrane_")
    X = V.tabulate_dof_coordinates()
    expected = np.stack([a11 * X[:, 0], a22 * X[:, 1], 0 * X[:, 2]], axis=1)
    np.testing.assert_allclose(u.x.array.reshape(-1, 3), expected, atol=1e-9)
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    P = dolfinx.fem.Expression(ufl.diff(energy(F), F), np.array([[0.5, 0.5, 0.5]]))
    stress = P.eval(mesh, np.arange(mesh.topology.index_map(3).size_local, dtype=np.int32))
    assert np.abs(stress).max() < 1e-6  # MPa, against moduli ~ 1e4 MPa


@pytest.mark.parametrize("design", [Design(0.05, -0.05), Design(-0.05, 0.0)])
def test_mirror_symmetry_for_axis_aligned_fibers(small_model, design):
    """theta = 0: E_xx, E_yy even and E_xy odd under x -> -x and under y -> -y."""
    params = SkinParams(mu=1.2e-3, k1=0.017, k2=12.0, kappa=0.28, theta=0.0)
    frames = small_model.simulate(params, design)
    xy, E = frames.xy, frames.strain[-1]
    key = {tuple(np.round(p, 6)): i for i, p in enumerate(xy)}
    mirror_x = np.array([key[tuple(np.round((-p[0], p[1]), 6))] for p in xy])
    mirror_y = np.array([key[tuple(np.round((p[0], -p[1]), 6))] for p in xy])
    scale = np.abs(E).max()
    for mirror in (mirror_x, mirror_y):
        np.testing.assert_allclose(E[mirror, :2], E[:, :2], atol=1e-8 * scale)
        np.testing.assert_allclose(E[mirror, 2], -E[:, 2], atol=1e-8 * scale)
    # and a fiber angle breaks it (so the check can fail)
    tilted = small_model.simulate(PARAMS, design).strain[-1]
    assert np.abs(tilted[mirror_x, 0] - tilted[:, 0]).max() > 1e-3 * scale


@pytest.mark.parametrize("theta", [0.0, 20.0])
def test_fibers_carry_no_load_in_compression(theta):
    """Uniaxial stress on a skin block along a0 (kappa = 0): under compression the field is
    the same for k1 = 0 and k1 > 0; under tension it is not."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 3, 3, 3, dolfinx.mesh.CellType.hexahedron)
    a0 = ufl.as_vector([np.cos(np.radians(theta)), np.sin(np.radians(theta)), 0.0])
    mu = 1.2e-3

    def solve(k1, stretch):
        def energy(F):
            return hgo_energy(F, mu, k1, 12.0, 0.0, a0, 20 * mu)

        def bcs(V):
            return [
                component_bc(V, 0, lambda x: np.isclose(x[0], 0), 0.0),
                component_bc(V, 1, at_point((0, 0, 0)), 0.0),
                component_bc(V, 2, lambda x: np.isclose(x[2], 0), 0.0),
                component_bc(V, 1, at_point((0, 0, 1)), 0.0),
                component_bc(V, 0, lambda x: np.isclose(x[0], 1), stretch - 1),
            ]

        u, _ = solve_energy(mesh, energy, bcs, f"fiber_{k1}_{stretch}_{theta}_".replace(".", "p"))
        return u.x.array.copy()

    for stretch, same in ((0.9, True), (1.1, False)):
        soft, stiff = solve(1e-14, stretch), solve(0.02, stretch)
        scale = np.abs(soft).max()
        if same:
            np.testing.assert_allclose(stiff, soft, atol=1e-9 * scale)
        else:
            assert np.abs(stiff - soft).max() > 1e-2 * scale
