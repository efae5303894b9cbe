"""Strain energies (UFL) of skin, muscle and the active membrane.

Every function takes the deformation gradient ``F`` (a UFL 3x3 expression) and material
constants (UFL expressions or numbers) and returns a strain-energy density in MPa
(= mJ/mm^3) per unit reference volume. Stresses and tangents follow from
``ufl.diff``/``ufl.derivative``; nothing here is linearised by hand.
"""

from __future__ import annotations

from dataclasses import dataclass

import ufl

from skinfem.config import MembraneConfig


def isochoric_invariants(F, a0):
    """(J, I1bar, I4bar, I4) of F for the unit fiber direction a0.

    I1bar = tr(Cbar), I4bar = a0 . Cbar a0 with Cbar = J^(-2/3) C, C = F^T F; I4 = a0 . C a0.
    """
    J = ufl.det(F)
    C = F.T * F
    scale = J ** (-2.0 / 3.0)
    I4 = ufl.dot(a0, C * a0)
    return J, scale * ufl.tr(C), scale * I4, I4


def abaqus_hgo_volumetric(J, bulk_modulus):
    """Psi_vol = K/2 ((J^2 - 1)/2 - ln J): Abaqus' HGO volumetric term, K = 2/D [MPa]."""
    return 0.5 * bulk_modulus * (0.5 * (J**2 - 1) - ufl.ln(J))


# The stress-free skin sits exactly at the fibers' switch (Ebar = 0), where the rounding of
# a0 . a0 (+-2e-16) picked the tangent's side by the last bit of the fiber angle: at zero
# pre-stretch its derivative was the tensile side's at theta = 25.2, 26.01 or 30.34 deg and the
# compressive side's at 25.31 or 30 deg (10-15 % apart). Ebar up to FIBER_SLACK counts as slack
# (always the compressive side); the energy this drops is below k1 1e-24 MPa.
FIBER_SLACK = 1e-12


def macaulay(x):
    """<x> = max(x, 0) (0 up to FIBER_SLACK): fibers carry load in tension only."""
    return ufl.conditional(ufl.gt(x, FIBER_SLACK), x, 0)


def hgo_energy(F, mu, k1, k2, kappa, a0, bulk_modulus, fiber_invariant: str = "isochoric"):
    """Holzapfel–Gasser–Ogden energy with one dispersed fiber family.

    Psi = mu/2 (I1bar - 3) + k1/(2 k2) [exp(k2 <Ebar>^2) - 1] + Psi_vol(J),
    Ebar = kappa (I1bar - 3) + (1 - 3 kappa)(I4x - 1),
    with I4x = I4bar ("isochoric", the paper and Abaqus) or the full I4 ("full").

    Args:
        F: deformation gradient (3x3).
        mu, k1: MPa. k2, kappa: dimensionless, 0 <= kappa <= 1/3.
        a0: unit fiber direction in the reference configuration (3-vector).
        bulk_modulus: K [MPa] of the volumetric term.
        fiber_invariant: "isochoric" or "full".
    """
    J, I1bar, I4bar, I4 = isochoric_invariants(F, a0)
    I4x = {"isochoric": I4bar, "full": I4}[fiber_invariant]
    Ebar = kappa * (I1bar - 3) + (1 - 3 * kappa) * (I4x - 1)
    psi_iso = 0.5 * mu * (I1bar - 3)
    psi_fiber = k1 / (2 * k2) * (ufl.exp(k2 * macaulay(Ebar) ** 2) - 1)
    return psi_iso + psi_fiber + abaqus_hgo_volumetric(J, bulk_modulus)


def neo_hookean_energy(F, mu, bulk_modulus):
    """Compressible neo-Hookean (Abaqus form): mu/2 (I1bar - 3) + K/2 (J - 1)^2 [MPa]."""
    J = ufl.det(F)
    I1bar = J ** (-2.0 / 3.0) * ufl.tr(F.T * F)
    return 0.5 * mu * (I1bar - 3) + 0.5 * bulk_modulus * (J - 1) ** 2


@dataclass(frozen=True)
class LaminaStiffness:
    """Plane-stress reduced stiffness of an orthotropic lamina (MPa), axis 1 = x."""

    Q11: float
    Q22: float
    Q12: float
    Q66: float
    G13: float
    G23: float
    E3: float

    @classmethod
    def from_config(cls, m: MembraneConfig) -> LaminaStiffness:
        nu21 = m.nu12 * m.E2 / m.E1
        d = 1 - m.nu12 * nu21
        return cls(m.E1 / d, m.E2 / d, m.nu12 * m.E2 / d, m.G12, m.G13, m.G23, m.E3)


def eigenstrain_gradient(alpha11, alpha22):
    """F_g = diag(1 + alpha11, 1 + alpha22, 1): the membrane's stress-free growth."""
    return ufl.as_matrix([[1 + alpha11, 0, 0], [0, 1 + alpha22, 0], [0, 0, 1]])


def membrane_energy(F, alpha11, alpha22, lamina: LaminaStiffness):
    """Orthotropic St Venant–Kirchhoff energy of the membrane with an imposed eigen-strain.

    F_e = F F_g^-1, E_e = (F_e^T F_e - I)/2; in-plane the plane-stress lamina energy
    (Q11 E11^2 + 2 Q12 E11 E22 + Q22 E22^2 + Q66 (2 E12)^2)/2, plus transverse shear
    2 (G13 E13^2 + G23 E23^2) and a decoupled normal term E3 E33^2 / 2. Returned per unit
    reference volume (the intermediate-configuration energy times det F_g).
    """
    Fg = eigenstrain_gradient(alpha11, alpha22)
    Fe = F * ufl.inv(Fg)
    E = 0.5 * (Fe.T * Fe - ufl.Identity(3))
    q = lamina
    w = 0.5 * (q.Q11 * E[0, 0] ** 2 + 2 * q.Q12 * E[0, 0] * E[1, 1] + q.Q22 * E[1, 1] ** 2)
    w += 0.5 * q.Q66 * (2 * E[0, 1]) ** 2
    w += 2 * (q.G13 * E[0, 2] ** 2 + q.G23 * E[1, 2] ** 2)
    w += 0.5 * q.E3 * E[2, 2] ** 2
    return ufl.det(Fg) * w
