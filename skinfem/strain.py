"""Logarithmic (Hencky) strain of the observed skin cells, in the global frame.

The observed cells are the top layer of skin cells (what a camera sees; with one skin layer,
as in the paper, all skin cells). Two observables (``observable.kind``):

- ``surface`` (:class:`SurfaceStrainSampler`): the strain of the skin surface z = 0 at the
  centre of each cell's top face, Lagrangian ln(C)/2 of the 3 x 2 surface gradient, as a DIC
  camera measures it (:mod:`skinfem.dic`; without the DIC system's strain window). It
  converges under refinement through the thickness and in plane.
- ``top_cell_average`` (:class:`SkinStrainSampler`): the volume-weighted average over each
  cell's quadrature points of ln V = ln(F F^T)/2 — with one skin layer the mid-thickness
  strain, with n layers the strain around depth (1 - 1/(2n)) of the skin: it moves with the
  number of skin layers.

Components (xx, yy, xy) with tensor (not engineering) shear. Cells are returned on rank 0 in a
fixed order independent of the number of MPI ranks: by centroid y, then x.
"""

from __future__ import annotations

import numpy as np

from skinfem.dic import fit_gradient, surface_log_strain
from skinfem.fenics import dolfinx, ufl


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


class ObservedCells:
    """The observed skin cells: reference centroids and volumes gathered on rank 0 in canonical
    order; subclasses define :meth:`local_strain`, the strain observed on this rank's cells.

    Args:
        mesh: the model's mesh.
        cells: local owned cell indices to observe.
        quadrature_degree: degree of the quadrature rule for the cell volumes (and averages).
    """

    def __init__(self, mesh, cells: np.ndarray, quadrature_degree: int):
        import basix

        self.comm = mesh.comm
        self.mesh = mesh
        self.cells = np.asarray(cells, dtype=np.int32)
        cell_type = basix.CellType[mesh.topology.cell_name()]
        points, weights = basix.make_quadrature(cell_type, max(quadrature_degree, 1))
        self._quadrature_points = points
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
        """(n_local_cells, 3) observed (xx, yy, xy) log strain of this rank's cells."""
        raise NotImplementedError

    def __call__(self) -> np.ndarray | None:
        """(n_cells, 3) strain on rank 0 (canonical order); None on other ranks."""
        strain = self._gather(self.local_strain())
        return strain[self.order] if self.comm.rank == 0 else None


class SkinStrainSampler(ObservedCells):
    """Cell-averaged log strain ln V of the top skin cells (``top_cell_average``).

    Args:
        u: displacement Function (mm).
        cells: local owned cell indices to observe.
        quadrature_degree: degree of the quadrature rule used for the cell average.
        F: UFL deformation gradient to measure (default I + grad u), e.g. relative to a
            pre-stressed reference.
    """

    def __init__(self, u, cells: np.ndarray, quadrature_degree: int, F=None):
        super().__init__(u.function_space.mesh, cells, quadrature_degree)
        F = ufl.Identity(3) + ufl.grad(u) if F is None else F
        self._F_expr = dolfinx.fem.Expression(F, self._quadrature_points)

    def local_strain(self) -> np.ndarray:
        """(n_local_cells, 3) cell-averaged (xx, yy, xy) log strain of this rank's cells."""
        n_cells, n_qp = self._weights.shape
        F = self._F_expr.eval(self.mesh, self.cells).reshape(n_cells, n_qp, 3, 3)
        E = log_strain(F)
        Ebar = np.einsum("cq,cqij->cij", self._weights, E)
        return np.stack([Ebar[:, 0, 0], Ebar[:, 1, 1], Ebar[:, 0, 1]], axis=1)


class SurfaceStrainSampler(ObservedCells):
    """Log strain of the skin surface at the centre of each top cell's top face (``surface``).

    The surface gradient H = d u / d(X, Y) (3 x 2) at the face centre is the slope of the
    least-squares affine fit of u over a 5 x 5 grid on the face spanning ``WINDOW_FRACTION`` of
    the cell's smaller in-plane side (:func:`skinfem.dic.fit_gradient`): exact for Q1 (the
    bilinear term is orthogonal to the slopes on a symmetric grid), within O(window^2) of the
    point gradient for Q2. Each window stays inside its cell, so every rank measures its own
    cells. The strain is that of :func:`skinfem.dic.surface_log_strain`, relative to the
    in-plane gradient of ``u_ref`` when given (a pre-stressed reference).

    Args:
        u: displacement Function (mm).
        cells: local owned top skin cells (their top face is the surface z = 0).
        quadrature_degree: quadrature degree of the cell volumes.
        u_ref: displacement of the reference state the strain is measured from, or None.
    """

    WINDOW_FRACTION = 0.25

    def __init__(self, u, cells: np.ndarray, quadrature_degree: int, u_ref=None):
        from skinfem.dic import StrainGauge, window_offsets

        super().__init__(u.function_space.mesh, cells, quadrature_degree)
        self.u, self.u_ref = u, u_ref
        x = self.mesh.geometry.x[self.mesh.geometry.dofmaps[0][self.cells]]  # (n, nodes, 3)
        low, high = x.min(axis=1), x.max(axis=1)
        self._window = self.WINDOW_FRACTION * np.min(high[:, :2] - low[:, :2], axis=1)  # (n,) mm
        self._unit_offsets = window_offsets(StrainGauge(window=1.0))  # (m, 2)
        n, m = len(self.cells), len(self._unit_offsets)
        xyz = np.empty((n, m, 3))
        xyz[:, :, :2] = (low + high)[:, None, :2] / 2 + self._window[:, None, None] * self._unit_offsets[None]
        xyz[:, :, 2] = high[:, None, 2]
        self._xyz = xyz.reshape(-1, 3)
        self._sample_cells = np.repeat(self.cells, m)

    def _gradient(self, u) -> np.ndarray:
        """(n_local_cells, 3, 2) surface gradient of ``u`` at the face centres [mm/mm]."""
        values = u.eval(self._xyz, self._sample_cells).reshape(len(self.cells), -1, 3)
        return fit_gradient(values, self._unit_offsets) / self._window[:, None, None]

    def local_strain(self) -> np.ndarray:
        """(n_local_cells, 3) surface log strain (xx, yy, xy) at this rank's face centres."""
        H_ref = None if self.u_ref is None else self._gradient(self.u_ref)
        return surface_log_strain(self._gradient(self.u), H_ref)
