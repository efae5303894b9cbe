"""Logarithmic (Hencky) strain per skin cell, in the global frame.

The observed cells are the top layer of skin cells (what a camera sees; with one skin layer,
as in the paper, all skin cells). Each cell's strain is the volume-weighted average over its
quadrature points of ln V = ln(F F^T)/2, components (xx, yy, xy) with tensor (not
engineering) shear. Cells are returned on rank 0 in a fixed order independent of the number
of MPI ranks: by centroid y, then x.
"""

from __future__ import annotations

import numpy as np

from skinfem.fenics import dolfinx, ufl

COMPONENTS = ("xx", "yy", "xy")


def log_strain(F: np.ndarray) -> np.ndarray:
    """Hencky strain ln V = ln(F F^T) / 2.

    Args:
        F: (..., 3, 3) deformation gradients.

    Returns:
        (..., 3, 3) symmetric log strains (dimensionless).
    """
    B = F @ np.swapaxes(F, -1, -2)
    eigval, eigvec = np.linalg.eigh(B)
    return (eigvec * (0.5 * np.log(eigval))[..., None, :]) @ np.swapaxes(eigvec, -1, -2)


def top_skin_cells(mesh, cell_tags, skin_tag: int, skin_top_layer_depth: float) -> np.ndarray:
    """Owned cells tagged ``skin_tag`` whose centroid lies within the top layer (z > -depth)."""
    n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
    cells = cell_tags.find(skin_tag)
    cells = cells[cells < n_owned]
    centroids = cell_centroids(mesh, cells)
    return cells[centroids[:, 2] > -skin_top_layer_depth].astype(np.int32)


def cell_centroids(mesh, cells: np.ndarray) -> np.ndarray:
    """(n, 3) vertex averages of the given cells' geometry nodes (reference configuration)."""
    x = mesh.geometry.x
    dofs = mesh.geometry.dofmaps[0][cells]
    return x[dofs].mean(axis=1)


class SkinStrainSampler:
    """Cell-averaged log strain of the top skin cells, gathered on rank 0 in canonical order.

    Args:
        u: displacement Function (mm).
        cells: local owned cell indices to observe.
        quadrature_degree: degree of the quadrature rule used for the cell average.
        F: UFL deformation gradient to measure (default I + grad u), e.g. relative to a
            pre-stressed reference.
    """

    def __init__(self, u, cells: np.ndarray, quadrature_degree: int, F=None):
        import basix

        mesh = u.function_space.mesh
        self.comm = mesh.comm
        self.mesh = mesh
        self.cells = np.asarray(cells, dtype=np.int32)
        cell_type = basix.CellType[mesh.topology.cell_name()]
        points, weights = basix.make_quadrature(cell_type, max(quadrature_degree, 1))
        F = ufl.Identity(3) + ufl.grad(u) if F is None else F
        self._F_expr = dolfinx.fem.Expression(F, points)
        detJ = abs(ufl.JacobianDeterminant(mesh))
        dV = dolfinx.fem.Expression(detJ, points).eval(mesh, self.cells) * weights[None, :]
        self._weights = dV / dV.sum(axis=1, keepdims=True)  # (n_cells, n_qp)
        local_xy = cell_centroids(mesh, self.cells)[:, :2]
        local_volume = dV.sum(axis=1)
        xy = self._gather(local_xy)
        volume = self._gather(local_volume)
        if self.comm.rank == 0:
            self.order = np.lexsort((np.round(xy[:, 0], 9), np.round(xy[:, 1], 9)))
            self.xy = xy[self.order]
            self.volume = volume[self.order]
        else:
            self.order = self.xy = self.volume = None

    def _gather(self, local: np.ndarray) -> np.ndarray | None:
        parts = self.comm.gather(np.ascontiguousarray(local), root=0)
        return np.concatenate(parts, axis=0) if self.comm.rank == 0 else None

    def local_strain(self) -> np.ndarray:
        """(n_local_cells, 3) cell-averaged (xx, yy, xy) log strain of this rank's cells."""
        n_cells, n_qp = self._weights.shape
        F = self._F_expr.eval(self.mesh, self.cells).reshape(n_cells, n_qp, 3, 3)
        E = log_strain(F)
        Ebar = np.einsum("cq,cqij->cij", self._weights, E)
        return np.stack([Ebar[:, 0, 0], Ebar[:, 1, 1], Ebar[:, 0, 1]], axis=1)

    def __call__(self) -> np.ndarray | None:
        """(n_cells, 3) strain on rank 0 (canonical order); None on other ranks."""
        strain = self._gather(self.local_strain())
        return strain[self.order] if self.comm.rank == 0 else None
