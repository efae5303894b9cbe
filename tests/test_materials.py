"""The UFL energies against an independent numpy implementation (complex-step derivatives).

The first Piola–Kirchhoff stress P = dPsi/dF of each UFL energy is evaluated with a DOLFINx
Expression for a homogeneous F and compared, entry by entry, with the complex-step
derivative of the energy written again here in numpy from the formulas of the paper.
"""

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.config import MembraneConfig
from skinfem.fenics import dolfinx, ufl
from skinfem.materials import (
    LaminaStiffness,
    hgo_energy,
    membrane_energy,
    neo_hookean_energy,
)

MU, K1, K2, KAPPA, BULK = 1.2e-3, 0.017, 12.0, 0.28, 20 * 1.2e-3


def hgo_numpy(F, theta_deg, kappa=KAPPA, k1=K1, fiber="isochoric"):
    a0 = np.array([np.cos(np.radians(theta_deg)), np.sin(np.radians(theta_deg)), 0.0])
    J = np.linalg.det(F)
    C = F.T @ F
    I1b = J ** (-2 / 3) * np.trace(C)
    I4 = a0 @ C @ a0
    I4x = J ** (-2 / 3) * I4 if fiber == "isochoric" else I4
    E = kappa * (I1b - 3) + (1 - 3 * kappa) * (I4x - 1)
    Ep = np.where(E.real > 0, E, 0)
    vol = BULK / 2 * ((J**2 - 1) / 2 - np.log(J))
    return MU / 2 * (I1b - 3) + k1 / (2 * K2) * (np.exp(K2 * Ep**2) - 1) + vol


def complex_step_pk1(energy, F):
    P = np.zeros((3, 3))
    h = 1e-30
    for i in range(3):
        for j in range(3):
            Fc = F.astype(complex)
            Fc[i, j] += 1j * h
            P[i, j] = energy(Fc).imag / h
    return P


@pytest.fixture(scope="module")
def one_cell():
    return dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1, dolfinx.mesh.CellType.hexahedron)


def ufl_pk1(mesh, energy_of_F, F_value):
    """Evaluate P = dPsi/dF of a UFL energy at a constant F on a one-cell mesh."""
    Fc = dolfinx.fem.Constant(mesh, np.asarray(F_value, dtype=float))
    F = ufl.variable(Fc)
    P = ufl.diff(energy_of_F(F), F)
    expr = dolfinx.fem.Expression(P, np.array([[0.5, 0.5, 0.5]]))
    return expr.eval(mesh, np.array([0], dtype=np.int32)).reshape(3, 3)


def deformations():
    lam = 1.1
    uniaxial = np.diag([lam, lam**-0.5, lam**-0.5])
    equibiaxial = np.diag([1.08, 1.08, 1.08**-2])
    compression = np.diag([0.9, 0.9**-0.5, 0.9**-0.5])
    sheared = np.array([[1.05, 0.08, 0.01], [0.02, 0.97, -0.03], [0.0, 0.04, 1.01]])
    return {"uniaxial": uniaxial, "equibiaxial": equibiaxial, "compression": compression, "general": sheared}


@pytest.mark.parametrize("fiber", ["isochoric", "full"])
@pytest.mark.parametrize("theta", [0.0, 30.0, 60.0, 90.0])
@pytest.mark.parametrize("name", ["uniaxial", "equibiaxial", "compression", "general"])
def test_hgo_stress_matches_independent_derivation(one_cell, fiber, theta, name):
    F = deformations()[name]
    a0 = np.array([np.cos(np.radians(theta)), np.sin(np.radians(theta)), 0.0])

    def energy(Fu):
        return hgo_energy(Fu, MU, K1, K2, KAPPA, ufl.as_vector(a0), BULK, fiber)

    P_ufl = ufl_pk1(one_cell, energy, F)
    P_ref = complex_step_pk1(lambda Fc: hgo_numpy(Fc, theta, fiber=fiber), F)
    scale = np.abs(P_ref).max()
    assert scale > 1e-5  # a non-trivial stress state
    np.testing.assert_allclose(P_ufl, P_ref, rtol=0, atol=1e-6 * scale)


def test_fibers_do_not_act_in_compression(one_cell):
    """With kappa = 0, compression along a0 gives the same stress for k1 = 0 and k1 > 0."""
    F = deformations()["compression"]
    a0 = ufl.as_vector([1.0, 0.0, 0.0])
    P = [ufl_pk1(one_cell, lambda Fu, k1=k1: hgo_energy(Fu, MU, k1, K2, 0.0, a0, BULK), F) for k1 in (0.0, 0.05)]
    np.testing.assert_allclose(P[0], P[1], rtol=1e-12, atol=1e-15)
    Ft = np.diag([1.1, 1.1**-0.5, 1.1**-0.5])  # tension: fibers must act
    Pt = [ufl_pk1(one_cell, lambda Fu, k1=k1: hgo_energy(Fu, MU, k1, K2, 0.0, a0, BULK), Ft) for k1 in (0.0, 0.05)]
    assert abs(Pt[1][0, 0] - Pt[0][0, 0]) > 1e-3


def test_neo_hookean_stress(one_cell):
    F = deformations()["general"]
    mu, K = 3.5e-3, 0.07

    def numpy_energy(Fc):
        J = np.linalg.det(Fc)
        return mu / 2 * (J ** (-2 / 3) * np.trace(Fc.T @ Fc) - 3) + K / 2 * (J - 1) ** 2

    P_ufl = ufl_pk1(one_cell, lambda Fu: neo_hookean_energy(Fu, mu, K), F)
    P_ref = complex_step_pk1(numpy_energy, F)
    np.testing.assert_allclose(P_ufl, P_ref, rtol=0, atol=1e-9 * np.abs(P_ref).max())


def test_membrane_is_stress_free_at_its_eigenstrain(one_cell):
    lamina = LaminaStiffness.from_config(MembraneConfig())
    a11, a22 = 0.05, -0.03
    Fg = np.diag([1 + a11, 1 + a22, 1.0])
    P = ufl_pk1(one_cell, lambda Fu: membrane_energy(Fu, a11, a22, lamina), Fg)
    np.testing.assert_allclose(P, 0.0, atol=1e-9)
    # and stressed (E1-scale) when held at F = I
    P0 = ufl_pk1(one_cell, lambda Fu: membrane_energy(Fu, a11, a22, lamina), np.eye(3))
    assert abs(P0[0, 0]) > 100.0


def test_lamina_stiffness_is_plane_stress():
    m = MembraneConfig()
    q = LaminaStiffness.from_config(m)
    compliance = np.array([[1 / m.E1, -m.nu12 / m.E1, 0], [-m.nu12 / m.E1, 1 / m.E2, 0], [0, 0, 1 / m.G12]])
    Q = np.array([[q.Q11, q.Q12, 0], [q.Q12, q.Q22, 0], [0, 0, q.Q66]])
    np.testing.assert_allclose(Q @ compliance, np.eye(3), atol=1e-12)
