"""The DIC measurement operator against closed forms: homogeneous deformations are measured
exactly by any window, and a quadratic displacement by its slope at the window centre."""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.dic import (
    StrainGauge,
    SurfaceStrainGauge,
    fit_gradient,
    surface_log_strain,
    surface_log_strain_derivative,
    window_offsets,
)


def homogeneous_log_strain(F: np.ndarray) -> np.ndarray:
    """ln(C)/2 of the in-plane surface of a homogeneous 3x3 deformation gradient, via scipy."""
    from scipy.linalg import logm

    Fs = F[:, :2]
    E = 0.5 * np.real(logm(Fs.T @ Fs))
    return np.array([E[0, 0], E[1, 1], E[0, 1]])


@pytest.fixture(scope="module")
def box_space():
    """Q2 vector space on a box [-10, 10]^2 x [-2, 0] mm (top surface at z = 0)."""
    from skinfem.fenics import dolfinx

    mesh = dolfinx.mesh.create_box(
        MPI.COMM_SELF, [[-10, -10, -2], [10, 10, 0]], [5, 5, 2], dolfinx.mesh.CellType.hexahedron
    )
    return dolfinx.fem.functionspace(mesh, ("Lagrange", 2, (3,)))


POINTS = np.array([[0.0, 0.0], [3.3, -1.7], [-7.9, 8.1], [4.0, 4.0]])  # incl. element edges / corners


def test_homogeneous_deformation_is_measured_exactly(box_space):
    from skinfem.fenics import dolfinx

    F = np.array([[1.08, 0.03, 0.0], [-0.02, 0.95, 0.0], [0.01, -0.04, 0.97]])
    u = dolfinx.fem.Function(box_space)
    u.interpolate(lambda x: (F - np.eye(3)) @ x)
    expected = homogeneous_log_strain(F)
    for window in (0.2, 1.0, 3.0):
        measured = SurfaceStrainGauge(u, POINTS, StrainGauge(window, 4))()
        np.testing.assert_allclose(measured, np.tile(expected, (len(POINTS), 1)), atol=1e-12)


def test_quadratic_displacement_gives_the_centre_slope(box_space):
    """u_x = c X^2, u_y = c' X Y: a symmetric window's affine fit has the exact centre slope."""
    from skinfem.fenics import dolfinx

    c, c2 = 2e-3, -1e-3
    u = dolfinx.fem.Function(box_space)
    u.interpolate(lambda x: np.stack([c * x[0] ** 2, c2 * x[0] * x[1], 0 * x[0]]))
    measured = SurfaceStrainGauge(u, POINTS, StrainGauge(2.0, 5))()
    for p, e in zip(POINTS, measured):
        F = np.eye(3)
        F[0, 0] += 2 * c * p[0]
        F[1, 0] += c2 * p[1]
        F[1, 1] += c2 * p[0]
        np.testing.assert_allclose(e, homogeneous_log_strain(F), atol=1e-12)


def test_reference_state_is_divided_out(box_space):
    """Strain from a pre-deformed in-plane reference: F_rel = F F_ref^-1."""
    from skinfem.fenics import dolfinx

    F_ref = np.diag([1.05, 0.98, 1.0])
    F_rel = np.array([[1.02, 0.01, 0], [0.0, 1.04, 0], [0, 0, 1.0]])
    F = F_rel @ F_ref
    u, u_ref = dolfinx.fem.Function(box_space), dolfinx.fem.Function(box_space)
    u.interpolate(lambda x: (F - np.eye(3)) @ x)
    u_ref.interpolate(lambda x: (F_ref - np.eye(3)) @ x)
    measured = SurfaceStrainGauge(u, POINTS[:1], StrainGauge(1.0, 3), u_ref=u_ref)()
    np.testing.assert_allclose(measured[0], homogeneous_log_strain(F_rel), atol=1e-12)


def test_window_leaving_the_mesh_is_refused(box_space):
    from skinfem.fenics import dolfinx

    u = dolfinx.fem.Function(box_space)
    with pytest.raises(ValueError, match=r"window \(2.0 mm\) of point \(9.5, 0\) mm leaves"):
        SurfaceStrainGauge(u, np.array([[0.0, 0.0], [9.5, 0.0]]), StrainGauge(2.0, 3))


def test_fit_and_log_strain_closed_forms():
    offsets = window_offsets(StrainGauge(1.5, 3))
    H = np.array([[0.1, -0.2], [0.05, 0.3], [0.0, 0.01]])
    u = offsets @ H.T + np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(fit_gradient(u[None], offsets)[0], H, atol=1e-14)
    # small strain limit: ln(C)/2 -> symmetric gradient
    h = 1e-7 * np.array([[[1.0, 2.0], [0.5, -1.0], [3.0, 0.0]]])
    np.testing.assert_allclose(surface_log_strain(h)[0], 1e-7 * np.array([1.0, -1.0, 1.25]), rtol=1e-6)
    with pytest.raises(ValueError, match="window must be > 0"):
        StrainGauge(0.0)


@pytest.mark.parametrize("with_reference", [False, True])
def test_log_strain_derivative_equals_central_differences(with_reference):
    """Daleckii-Krein derivative against central differences of the closed form (step 1e-6),
    including a repeated eigenvalue (equibiaxial C)."""
    rng = np.random.default_rng(3)
    H = 0.1 * rng.normal(size=(6, 3, 2))
    H[0] = [[0.05, 0], [0, 0.05], [0, 0]]  # C = (1.05)^2 I: equal eigenvalues
    dH = rng.normal(size=H.shape)
    H_ref = 0.05 * rng.normal(size=H.shape) if with_reference else None
    dH_ref = rng.normal(size=H.shape) if with_reference else None
    h = 1e-6

    def at(s):
        return surface_log_strain(H + s * dH, None if H_ref is None else H_ref + s * dH_ref)

    expected = (at(h) - at(-h)) / (2 * h)
    np.testing.assert_allclose(surface_log_strain_derivative(H, dH, H_ref, dH_ref), expected, atol=1e-8)
