"""Skin material parameters and membrane designs, validated on construction.

Units: mu, k1 in MPa; k2, kappa dimensionless; theta in degrees (fiber angle from the x /
alpha11 axis in the skin plane). Eigen-strains alpha11, alpha22 are dimensionless.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass

import numpy as np

from skinfem.config import PARAM_NAMES

MAX_ALPHA = 0.5
MAX_THETA = 180.0  # deg: a fiber direction repeats every 180 deg


@dataclass(frozen=True)
class SkinParams:
    """Holzapfel–Gasser–Ogden skin parameters (mu, k1 [MPa], k2, kappa [-], theta [deg])."""

    mu: float
    k1: float
    k2: float
    kappa: float
    theta: float

    def __post_init__(self) -> None:
        for name in PARAM_NAMES:
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if self.mu <= 0:
            raise ValueError(f"mu must be > 0 MPa, got {self.mu}")
        if self.k1 < 0:
            raise ValueError(f"k1 must be >= 0 MPa, got {self.k1}")
        if self.k2 <= 0:
            raise ValueError(f"k2 must be > 0, got {self.k2}")
        if not 0.0 <= self.kappa <= 1.0 / 3.0:
            raise ValueError(f"kappa must be in [0, 1/3], got {self.kappa}")
        if not -MAX_THETA <= self.theta <= MAX_THETA:
            raise ValueError(f"theta must be in [-{MAX_THETA:g}, {MAX_THETA:g}] deg, got {self.theta}")

    @property
    def theta_rad(self) -> float:
        return math.radians(self.theta)

    def as_array(self) -> np.ndarray:
        """(5,) float64 in the order mu, k1, k2, kappa, theta [deg]."""
        return np.array(astuple(self), dtype=float)

    @classmethod
    def from_array(cls, values) -> SkinParams:
        """From the five values (mu, k1, k2, kappa, theta) in this order and these units (theta in degrees)."""
        return cls(*(float(v) for v in values))


@dataclass(frozen=True)
class Design:
    """Membrane eigen-strains alpha11 (along x) and alpha22 (along y); |alpha| < 0.5."""

    alpha11: float
    alpha22: float

    def __post_init__(self) -> None:
        for name in ("alpha11", "alpha22"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
            if abs(value) >= MAX_ALPHA:
                raise ValueError(f"|{name}| must be < {MAX_ALPHA}, got {value}")

    def as_array(self) -> np.ndarray:
        return np.array(astuple(self), dtype=float)
