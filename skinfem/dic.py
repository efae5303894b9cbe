"""The measurement operator: what a DIC system reports of a model's displacement field.

A camera sees the skin's top surface (z = 0; under the membrane, the bonded skin-membrane
interface), and a DIC system reports at each of its points the strain of a *virtual strain
gauge*: the least-squares affine fit of the surface displacement over a square window of
side ``window`` [mm] centred on the point (the "strain window" / VSG of Vic, DICe, MatchID).
:class:`SurfaceStrainGauge` does exactly that with the model's displacement:

1. the displacement u (3 components) at a ``samples`` x ``samples`` grid of points spanning
   the window, on z = 0 (:func:`window_offsets`);
2. the in-plane gradient H = d u / d(X, Y) (3 x 2) of the least-squares affine fit
   (:func:`fit_gradient`; exact for an affine field, and for a quadratic one at the centre);
3. the surface's Lagrangian log strain ln(C) / 2 with C = F_s^T F_s, F_s = [I; 0] + H
   (:func:`surface_log_strain`); components (xx, yy, xy), tensor shear, reference axes.

With a pre-stressed reference (a DIC reference image of the unloaded, pre-stretched skin) the
strain is measured from the unloaded equilibrium u_ref: F_s is taken relative to the in-plane
gradient of the reference state, F_s (I + H_ref,in-plane)^-1. The out-of-plane slope of
u_ref and the shift of the points by u_ref are neglected (second order in the pre-strain).

Window and sampling are user-set: the window is the DIC system's VSG size (strain window x
step size); a window smaller than a mesh cell measures the cell's own gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StrainGauge:
    """A DIC system's strain computation: square window side [mm] and samples per side."""

    window: float = 1.0
    samples: int = 5

    def __post_init__(self):
        if not (np.isfinite(self.window) and self.window > 0):
            raise ValueError(f"the DIC strain window must be > 0 mm, got {self.window}")
        if self.samples < 2:
            raise ValueError(f"the DIC strain window needs at least 2 samples per side, got {self.samples}")


def window_offsets(gauge: StrainGauge) -> np.ndarray:
    """(samples^2, 2) offsets [mm] of a uniform grid spanning the square window."""
    s = np.linspace(-gauge.window / 2, gauge.window / 2, gauge.samples)
    return np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)


def fit_gradient(u: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Slope of the least-squares affine fit u ~ a + H d over the window.

    Args:
        u: (n, m, c) values at the m window samples of n points.
        offsets: (m, 2) sample offsets d [mm] (centred: their mean is 0).

    Returns:
        (n, c, 2) gradient H [per mm].
    """
    d = offsets - offsets.mean(axis=0)
    pinv = np.linalg.solve(d.T @ d, d.T)  # (2, m): H^T = pinv @ (u - mean u)
    return np.einsum("km,nmc->nck", pinv, u - u.mean(axis=1, keepdims=True))


def surface_log_strain(H: np.ndarray, H_ref: np.ndarray | None = None) -> np.ndarray:
    """Lagrangian log strain (xx, yy, xy) of surfaces with displacement gradients H.

    Args:
        H: (n, 3, 2) d u / d(X, Y) of the surface.
        H_ref: (n, 3, 2) or None: gradient of the reference state the strain is measured
            from (its in-plane part is used, see module doc).

    Returns:
        (n, 3) ln(C)/2 components, C = F_s^T F_s (2 x 2).
    """
    F = H + np.eye(3, 2)
    if H_ref is not None:
        F = F @ np.linalg.inv(np.eye(2) + H_ref[:, :2, :])
    C = np.swapaxes(F, -1, -2) @ F
    w, v = np.linalg.eigh(C)
    if np.any(w <= 0):
        raise ValueError("a surface stretch is not positive (inverted element?)")
    E = (v * (0.5 * np.log(w))[:, None, :]) @ np.swapaxes(v, -1, -2)
    return np.stack([E[:, 0, 0], E[:, 1, 1], E[:, 0, 1]], axis=1)


def surface_log_strain_derivative(
    H: np.ndarray, dH: np.ndarray, H_ref: np.ndarray | None = None, dH_ref: np.ndarray | None = None
) -> np.ndarray:
    """Directional derivative (n, 3) of :func:`surface_log_strain` along dH (and dH_ref).

    Exact: dF = dH A^-1 - F dA A^-1 with A = I + H_ref (in plane), dC = dF^T F + F^T dF, and the
    derivative of the matrix logarithm by the Daleckii-Krein formula
    d ln C = V [(V^T dC V) o L] V^T, L_ij = (ln w_i - ln w_j)/(w_i - w_j) (1/w_i if equal).
    """
    A_inv = np.broadcast_to(np.eye(2), (len(H), 2, 2))
    if H_ref is not None:
        A_inv = np.linalg.inv(np.eye(2) + H_ref[:, :2, :])
    F = (H + np.eye(3, 2)) @ A_inv
    dF = dH @ A_inv
    if dH_ref is not None:
        dF = dF - F @ dH_ref[:, :2, :] @ A_inv
    C = np.swapaxes(F, -1, -2) @ F
    dC = np.swapaxes(dF, -1, -2) @ F + np.swapaxes(F, -1, -2) @ dF
    w, v = np.linalg.eigh(C)
    lw = np.log(w)
    gap = w[:, :, None] - w[:, None, :]
    close = np.abs(gap) <= 1e-12 * w[:, :, None]
    L = np.where(close, 1 / w[:, :, None], (lw[:, :, None] - lw[:, None, :]) / np.where(close, 1.0, gap))
    dE = 0.5 * v @ ((np.swapaxes(v, -1, -2) @ dC @ v) * L) @ np.swapaxes(v, -1, -2)
    return np.stack([dE[:, 0, 0], dE[:, 1, 1], dE[:, 0, 1]], axis=1)


class SurfaceStrainGauge:
    """DIC strain at fixed surface points from a displacement Function (serial meshes).

    Args:
        u: displacement Function [mm] on a mesh whose top surface is z = 0.
        points: (n, 2) in-plane positions [mm].
        gauge: window and sampling.
        u_ref: Function of the reference state the strain is measured from, or None.

    Raises:
        ValueError: a point's window leaves the mesh (names the first such point).
    """

    def __init__(self, u, points: np.ndarray, gauge: StrainGauge, u_ref=None):
        from skinfem.fenics import dolfinx

        self.u, self.u_ref = u, u_ref
        self.points = np.asarray(points, dtype=float)
        self.offsets = window_offsets(gauge)
        n, m = len(self.points), len(self.offsets)
        xyz = np.zeros((n * m, 3))
        xyz[:, :2] = (self.points[:, None, :] + self.offsets[None, :, :]).reshape(-1, 2)
        mesh = u.function_space.mesh
        tree = dolfinx.geometry.bb_tree(mesh, mesh.topology.dim)
        hits = dolfinx.geometry.compute_colliding_cells(
            mesh, dolfinx.geometry.compute_collisions_points(tree, xyz), xyz
        )
        counts = np.diff(hits.offsets)
        if np.any(counts == 0):
            bad = self.points[np.flatnonzero(counts == 0)[0] // m]
            raise ValueError(
                f"the DIC window ({gauge.window} mm) of point ({bad[0]:.4g}, {bad[1]:.4g}) mm leaves the model's mesh"
            )
        self._xyz = xyz
        self._cells = hits.array[hits.offsets[:-1]].astype(np.int32)

    def _gradient(self, u) -> np.ndarray:
        values = u.eval(self._xyz, self._cells).reshape(len(self.points), len(self.offsets), 3)
        return fit_gradient(values, self.offsets)

    def __call__(self) -> np.ndarray:
        """(n, 3) log strain (xx, yy, xy) at the points."""
        H_ref = None if self.u_ref is None else self._gradient(self.u_ref)
        return surface_log_strain(self._gradient(self.u), H_ref)

    def derivatives(self, dus, du_refs=None) -> list[np.ndarray]:
        """(n, 3) change of the measured strain per unit change du of u (and du_ref of u_ref),
        for each pair, at the current state (Functions on the same space, e.g. displacement
        sensitivities). The state's gradients are computed once for all pairs."""
        H = self._gradient(self.u)
        H_ref = None if self.u_ref is None else self._gradient(self.u_ref)
        du_refs = [None] * len(dus) if du_refs is None else du_refs
        return [
            surface_log_strain_derivative(
                H, self._gradient(du), H_ref, None if du_ref is None else self._gradient(du_ref)
            )
            for du, du_ref in zip(dus, du_refs, strict=True)
        ]
