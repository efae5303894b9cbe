"""Candidate physical effects the baseline model leaves out, as switchable UFL modifications.

The baseline (the paper's model) assumes a stress-free skin of nominal thickness on a muscle of
fixed stiffness, a nearly incompressible skin with K = 20 mu, and a perfectly bonded membrane.
Each :class:`Effect` relaxes one of these assumptions. It declares its parameters (name, unit,
prior range and the *null* value at which the model equals the baseline) and edits the
:class:`ModelTerms` the :class:`~skinfem.model.SkinModel` assembles its energy from. Effect
parameters are DOLFINx Constants, so one compiled model evaluates any parameter value.

Writing a new effect: subclass :class:`Effect`, set ``name``, ``description`` and
``parameters``, implement ``apply(terms, p)`` (``p`` maps your parameter names to UFL
constants), and add the class to :data:`EFFECTS`. At the null values ``apply`` must leave the
terms unchanged (tests check that the field then equals the baseline's).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import ufl
from ufl.core.expr import Expr

from skinfem.materials import LaminaStiffness


@dataclass(frozen=True)
class EffectParameter:
    """One parameter of an effect: prior range [low, high] and its null (baseline) value."""

    name: str
    unit: str
    low: float
    high: float
    null: float
    description: str


@dataclass
class ModelTerms:
    """The UFL pieces of the energy that effects may modify.

    Attributes:
        skin_map: G (3x3), the gradient of the map from the mesh's skin layer to the physical
            reference skin: the skin deformation gradient is F = I + grad(u) G^-1 and its
            energy is weighted by det G.
        skin_prestretch: F0 (3x3), the deformation from the skin's stress-free state to the
            reference (in vivo) configuration; the skin energy is Psi(F F0) / det F0.
        skin_bulk_ratio: K/mu of the skin's volumetric term.
        muscle_mu: neo-Hookean shear modulus of the muscle [MPa].
        lamina: membrane stiffness (its G13, G23 are the membrane-skin shear coupling); None
            for a rigid membrane.
        skin_stiffness: factor [-] on the skin's whole energy density (1 in the baseline); a
            function of ``x`` makes the skin heterogeneous (a scar, an inclusion).
        x: the reference coordinates (UFL SpatialCoordinate) [mm]; z = 0 is the skin surface.
    """

    skin_map: Expr
    skin_prestretch: Expr
    skin_bulk_ratio: Expr | float
    muscle_mu: Expr | float
    lamina: LaminaStiffness | None
    skin_stiffness: Expr | float = 1.0
    x: Expr | None = None


class Effect:
    """Base class: a named physical effect with declared parameters (see module doc)."""

    name: ClassVar[str]
    description: ClassVar[str]
    parameters: ClassVar[tuple[EffectParameter, ...]]
    #: True if the reference configuration is stressed (the model then first solves the
    #: unloaded equilibrium and measures strain from it, as DIC does).
    prestressed: ClassVar[bool] = False

    def apply(self, terms: ModelTerms, p: dict[str, object]) -> None:
        raise NotImplementedError

    @classmethod
    def describe(cls, values: dict[str, float]) -> str:
        """A sentence on estimated parameter values (keys: parameter names), for reports."""
        units = {q.name: "" if q.unit == "-" else f" {q.unit}" for q in cls.parameters}
        return ", ".join(f"{q.name} = {values[q.name]:.3g}{units[q.name]}" for q in cls.parameters) + "."

    @classmethod
    def qualified_names(cls) -> list[str]:
        """Parameter names as used in files and on the command line: ``effect.parameter``."""
        return [f"{cls.name}.{q.name}" for q in cls.parameters]


class PreStretch(Effect):
    name = "pre_stretch"
    description = (
        "in-vivo skin pre-stretch (the paper assumes a stress-free skin): the skin's stress-free "
        "state is stretched in plane by exp(eps) into the reference configuration"
    )
    parameters = (
        EffectParameter("eps_xx", "-", -0.15, 0.15, 0.0, "log pre-strain along x"),
        EffectParameter("eps_yy", "-", -0.15, 0.15, 0.0, "log pre-strain along y"),
        EffectParameter("eps_xy", "-", -0.10, 0.10, 0.0, "log pre-strain, tensor shear"),
    )
    prestressed = True

    @classmethod
    def describe(cls, values: dict[str, float]) -> str:
        l1, l2, ang = principal_prestretch(values["eps_xx"], values["eps_yy"], values["eps_xy"])
        return f"pre-stretch {l1:.3f} x {l2:.3f}, major axis at {ang:.0f} deg."

    def apply(self, terms: ModelTerms, p: dict[str, object]) -> None:
        terms.skin_prestretch = prestretch_gradient(p["eps_xx"], p["eps_yy"], p["eps_xy"])


def prestretch_gradient(exx, eyy, exy):
    """F0 = exp(eps) in plane (closed form for a symmetric 2x2), 1/det through the thickness.

    With eigenvalues e_mean +- r of eps, exp(eps) = exp(e_mean) (cosh r I + sinh(r)/r dev eps);
    sinh(r)/r is evaluated by its series below r = 1e-4 so that the null value is smooth.
    The isochoric choice det F0 = 1 keeps the skin volume of the reference configuration.
    """
    mean = 0.5 * (exx + eyy)
    dxx = 0.5 * (exx - eyy)
    r2 = dxx**2 + exy**2
    r = ufl.sqrt(r2 + 1e-30)
    sinhc = ufl.conditional(ufl.lt(r2, 1e-8), 1 + r2 / 6, ufl.sinh(r) / r)
    cosh = ufl.cosh(r)
    scale = ufl.exp(mean)
    u11 = scale * (cosh + sinhc * dxx)
    u22 = scale * (cosh - sinhc * dxx)
    u12 = scale * sinhc * exy
    u33 = ufl.exp(-2 * mean)  # det of the in-plane block is exp(2 mean)
    return ufl.as_matrix([[u11, u12, 0], [u12, u22, 0], [0, 0, u33]])


def principal_prestretch(exx: float, eyy: float, exy: float) -> tuple[float, float, float]:
    """(lambda1, lambda2, direction [deg]) of a log pre-strain; lambda1 >= lambda2."""
    w, v = np.linalg.eigh(np.array([[exx, exy], [exy, eyy]]))
    angle = math.degrees(math.atan2(v[1, 1], v[0, 1])) % 180.0
    return math.exp(w[1]), math.exp(w[0]), angle


def prestretch_log_strain(lambda1: float, lambda2: float, direction_deg: float) -> dict[str, float]:
    """The (eps_xx, eps_yy, eps_xy) of principal stretches lambda1 along ``direction_deg``."""
    e1, e2, a = math.log(lambda1), math.log(lambda2), math.radians(direction_deg)
    c, s = math.cos(a), math.sin(a)
    return {"eps_xx": e1 * c * c + e2 * s * s, "eps_yy": e1 * s * s + e2 * c * c, "eps_xy": (e1 - e2) * c * s}


class LogFactor(Effect):
    """An effect with one parameter, log_factor: the log of the factor on an assumed quantity."""

    quantity: ClassVar[str]  # what the factor multiplies, for reports

    @classmethod
    def describe(cls, values: dict[str, float]) -> str:
        return f"{cls.quantity} {math.exp(values['log_factor']):.2f} times the assumed one."


class ScaledTerm(LogFactor):
    """An effect that multiplies one scalar of :class:`ModelTerms` by exp(log_factor)."""

    term: ClassVar[str]

    def apply(self, terms: ModelTerms, p: dict[str, object]) -> None:
        setattr(terms, self.term, getattr(terms, self.term) * ufl.exp(p["log_factor"]))


class MuscleStiffness(ScaledTerm):
    name = "muscle_stiffness"
    description = "muscle shear modulus differs from the assumed one: mu_m = mu_m,config exp(p)"
    parameters = (EffectParameter("log_factor", "-", -1.6, 1.6, 0.0, "ln(mu_m / mu_m,config)"),)
    term = "muscle_mu"
    quantity = "muscle shear modulus"


class SkinThickness(LogFactor):
    name = "skin_thickness"
    description = (
        "skin thickness differs from the nominal 0.6 mm: h = h_config exp(p) (the skin layer of "
        "the mesh is mapped affinely through its thickness)"
    )
    parameters = (EffectParameter("log_factor", "-", math.log(0.5), math.log(2.0), 0.0, "ln(h / h_config)"),)
    quantity = "skin thickness"

    def apply(self, terms: ModelTerms, p: dict[str, object]) -> None:
        s = ufl.exp(p["log_factor"])
        terms.skin_map = ufl.dot(terms.skin_map, ufl.as_matrix([[1, 0, 0], [0, 1, 0], [0, 0, s]]))


class Compressibility(ScaledTerm):
    name = "compressibility"
    description = "skin compressibility differs from K/mu = 20: K/mu = bulk_ratio exp(p)"
    parameters = (EffectParameter("log_factor", "-", -1.6, 3.0, 0.0, "ln(K/mu / bulk_ratio)"),)
    term = "skin_bulk_ratio"
    quantity = "skin bulk-to-shear modulus ratio K/mu"


class Bonding(Effect):
    name = "bonding"
    description = (
        "imperfect membrane bonding: a compliant adhesive adds c to the membrane's transverse "
        "shear compliance, G13 -> 1/(1/G13 + c)"
    )
    parameters = (EffectParameter("compliance", "1/MPa", 0.0, 100.0, 0.0, "adhesive shear compliance c"),)

    def apply(self, terms: ModelTerms, p: dict[str, object]) -> None:
        q = terms.lamina
        if q is None:
            raise ValueError("the bonding effect needs an elastic membrane (membrane.model = 'elastic')")
        terms.lamina = dataclasses.replace(
            q, G13=1 / (1 / q.G13 + p["compliance"]), G23=1 / (1 / q.G23 + p["compliance"])
        )


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls for cls in (PreStretch, MuscleStiffness, SkinThickness, Compressibility, Bonding)
}


def get_effect(name: str) -> type[Effect]:
    """The effect class called ``name``; ValueError listing the known ones otherwise."""
    if name not in EFFECTS:
        raise ValueError(f"unknown effect '{name}'; known effects: {', '.join(EFFECTS)}")
    return EFFECTS[name]


def effect_parameters(names: list[str]) -> list[tuple[str, EffectParameter]]:
    """(qualified name, parameter) of every parameter of the named effects, in order."""
    out = []
    for name in names:
        cls = get_effect(name)
        out += [(f"{cls.name}.{q.name}", q) for q in cls.parameters]
    return out
