"""Layered hexahedral block: skin on muscle, with the membrane as a bonded layer on top.

Built with the gmsh Python API by extrusion, so every cell is a hexahedron and the in-plane
grid is a tensor product, mirror-symmetric about x = 0 and y = 0:

- in plane: uniform cells of ``h_membrane`` under the membrane footprint |x|, |y| <= a,
  geometrically graded outwards to about ``h_far`` at the block edge |x| or |y| = L/2; with
  ``h_edge`` > 0, cells of ``h_edge`` on both sides of the membrane edge |x| or |y| = a,
  graded to ``h_membrane`` at the centre and to ``h_far`` at the block edge (one progression
  per side, or with ``edge_growth`` > 1 growing by that factor until they reach those sizes);
- through the thickness: ``skin_layers`` cells in the skin (z in [-h_s, 0]),
  ``muscle_layers`` in the muscle (z in [-h_s - h_m, -h_s]) and ``membrane_layers`` in the
  membrane (z in [0, t_mem] over the footprint; absent for ``membrane.model = "rigid"``).

Units: mm. Physical groups (cell and facet tags) are listed in :data:`TAGS`.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skinfem.config import Config, MeshConfig

TAGS = {
    # volumes
    "skin": 1,
    "muscle": 2,
    "membrane": 3,
    # facets
    "bottom": 11,
    "sides": 12,
    "top": 13,
    "footprint": 14,
    "membrane_top": 15,
}

DEFAULT_MESH_DIR = Path("meshes")
EDGE_GROWTH = 1.3  # largest size ratio of neighbouring cells graded away from a refined membrane edge


def graded_sizes(length: float, h_start: float, h_end: float, max_ratio: float = np.inf) -> np.ndarray:
    """Cell sizes of a geometric progression from ``h_start`` that fill ``length`` exactly.

    The number of cells is chosen so that the last cell is as close as possible to
    ``h_end``, then raised until the growth ratio is at most ``max_ratio`` (the last cell is
    then smaller than ``h_end``). Returns a (n,) array of sizes in mm summing to ``length``.
    """
    sizes = _closest_progression(length, h_start, h_end)
    n = len(sizes)
    while len(sizes) > 1 and sizes[1] / sizes[0] > max_ratio:
        n += 1
        sizes = h_start * _progression_ratio(length, h_start, n) ** np.arange(n)
        sizes *= length / sizes.sum()
    return sizes


def capped_sizes(length: float, h_start: float, h_max: float, growth: float) -> np.ndarray:
    """Cell sizes that start at ``h_start``, grow by ``growth`` while below ``h_max``, then fill
    the rest of ``length`` with equal cells of at most ``h_max``: (n,) sizes in mm summing to
    ``length``. A geometric grading towards the first cell: neighbours within ``growth`` of each
    other in the graded part, within max(``growth``, 2) where it meets the equal cells (graded
    cells are given up to the equal ones until the first equal cell is at least the last graded
    one / ``growth``). Without room to reach ``h_max``, :func:`graded_sizes`."""
    graded = [h_start]
    while graded[-1] * growth < h_max:
        graded.append(graded[-1] * growth)
    if sum(graded) >= length:  # h_max is not reached: one progression of ratio <= growth
        return graded_sizes(length, h_start, h_max, growth)
    for k in range(len(graded), 0, -1):  # drop graded cells until the fill matches its neighbour
        rest = length - sum(graded[:k])
        n_fill = int(np.ceil(rest / h_max - 1e-9))
        fill = [rest / n_fill] * n_fill if n_fill else []
        if not fill or fill[0] * growth >= graded[k - 1] * (1 - 1e-9):
            break
    sizes = np.array(graded[:k] + fill)
    return sizes * (length / sizes.sum())


def _closest_progression(length: float, h_start: float, h_end: float) -> np.ndarray:
    if h_end <= h_start * (1 + 1e-12):
        n = max(1, round(length / h_start))
        return np.full(n, length / n)
    best = None
    for n in range(1, 10_000):
        ratio = _progression_ratio(length, h_start, n)
        sizes = h_start * ratio ** np.arange(n)
        sizes *= length / sizes.sum()
        misfit = abs(np.log(sizes[-1] / h_end))
        if best is None or misfit < best[0]:
            best = (misfit, sizes)
        if sizes[-1] < h_end:
            break
    return best[1]


def _progression_ratio(length: float, h0: float, n: int) -> float:
    """Ratio r with h0 (1 + r + ... + r^(n-1)) = length (bisection; r >= 0)."""
    if n * h0 >= length:
        lo, hi = 0.0, 1.0
    else:
        lo, hi = 1.0, 2.0
        while h0 * (hi**n - 1) / (hi - 1) < length:
            hi *= 2
    total = lambda r: h0 * n if abs(r - 1) < 1e-14 else h0 * (r**n - 1) / (r - 1)  # noqa: E731
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if total(mid) < length:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def edge_cell_size(mesh_cfg: MeshConfig) -> float:
    """In-plane cell size [mm] at the membrane edge, where the strain concentrates."""
    if mesh_cfg.edge_refined:
        return mesh_cfg.h_edge
    return mesh_cfg.membrane_size / _centre_cells(mesh_cfg)


def _centre_cells(mesh_cfg: MeshConfig) -> int:
    """Cells across the membrane without edge refinement (uniform, about ``h_membrane``)."""
    return max(2, round(mesh_cfg.membrane_size / mesh_cfg.h_membrane))


def inplane_coordinates(mesh_cfg: MeshConfig) -> np.ndarray:
    """Node coordinates (mm) along x (and y): symmetric about 0, refined under the membrane."""
    half = mesh_cfg.length / 2
    a = mesh_cfg.membrane_size / 2
    if mesh_cfg.edge_refined:
        inner = _sizes_from_edge(mesh_cfg, a, mesh_cfg.h_membrane)[::-1]  # centre -> edge
        center = np.concatenate([[0.0], np.cumsum(inner)])
        center = np.concatenate([-center[::-1], center[1:]]) * (a / center[-1])
    else:
        center = np.linspace(-a, a, _centre_cells(mesh_cfg) + 1)
    outer = _sizes_from_edge(mesh_cfg, half - a, mesh_cfg.h_far)
    right = a + np.concatenate([[0.0], np.cumsum(outer)])
    right[-1] = half
    return np.concatenate([-right[::-1], center[1:-1], right])


def _sizes_from_edge(mesh_cfg: MeshConfig, length: float, h_end: float) -> np.ndarray:
    """Cell sizes (mm) from the membrane edge over ``length`` towards cells of ``h_end``: grown by
    ``edge_growth`` then uniform, or one progression (neighbours within :data:`EDGE_GROWTH` when
    the edge is refined)."""
    h_edge = edge_cell_size(mesh_cfg)
    if mesh_cfg.edge_refined and mesh_cfg.edge_growth > 1:
        return capped_sizes(length, h_edge, h_end, mesh_cfg.edge_growth)
    return graded_sizes(length, h_edge, h_end, EDGE_GROWTH if mesh_cfg.edge_refined else np.inf)


@dataclass(frozen=True)
class MeshInfo:
    """Summary of a generated mesh."""

    path: Path
    n_cells: int
    n_skin_cells: int
    n_nodes: int
    sha256: str


def mesh_path(config: Config, directory: Path | str = DEFAULT_MESH_DIR) -> Path:
    """The file a configuration's mesh lives in: ``<dir>/<config name>-<mesh hash>.msh``."""
    return Path(directory) / f"{config.name}-{config.mesh_key}.msh"


def file_sha256(path: Path | str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _extrude_layers(gmsh, dim_tags, dx, dy, dz, sizes):
    """Extrude entities with one layer per entry of ``sizes`` (relative heights)."""
    heights = np.cumsum(sizes) / np.sum(sizes)
    heights[-1] = 1.0
    return gmsh.model.geo.extrude(
        dim_tags, dx, dy, dz, numElements=[1] * len(sizes), heights=list(heights), recombine=True
    )


def build_mesh(config: Config, path: Path | str) -> MeshInfo:
    """Generate the layered hexahedral mesh with gmsh and write it to ``path`` (.msh 4.1).

    Runs on one process (call it on rank 0 only). Overwrites ``path`` atomically.
    """
    import gmsh

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.msh")  # processes that build the same mesh do not collide
    initialized_here = not gmsh.isInitialized()
    if initialized_here:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("skinid-block")
        surfaces = _top_surfaces(gmsh, config.mesh)
        volumes = _extrude_layers_down(gmsh, config, surfaces)
        gmsh.model.geo.synchronize()
        _tag_groups(gmsh, config, surfaces, volumes)
        n_cells, n_skin, n_nodes = _generate(gmsh, tmp, volumes["skin"])
        gmsh.model.remove()
    finally:
        if initialized_here:
            gmsh.finalize()
    tmp.replace(path)
    return MeshInfo(path, n_cells, n_skin, n_nodes, file_sha256(path))


def _top_surfaces(gmsh, m) -> dict[tuple[int, int], int]:
    """The z = 0 plane as 3 x 3 structured surfaces (i, j) -> tag, split at the membrane's edges
    x, y = -a, +a; the node coordinates are :func:`inplane_coordinates`."""
    coords = inplane_coordinates(m)
    half, a = m.length / 2, m.membrane_size / 2
    i_lo = int(np.argmin(np.abs(coords + a)))
    i_hi = int(np.argmin(np.abs(coords - a)))
    segments = [coords[: i_lo + 1], coords[i_lo : i_hi + 1], coords[i_hi:]]
    # x-lines along y = -L/2 (one per segment), extruded point by point
    p = gmsh.model.geo.addPoint(-half, -half, 0.0)
    x_lines = []
    for seg in segments:
        out = _extrude_layers(gmsh, [(0, p)], seg[-1] - seg[0], 0, 0, np.diff(seg))
        p = out[0][1]
        x_lines.append(out[1][1])
    # rows of surfaces along y; for each extruded line: [top line, surface, lateral lines...]
    surfaces = {}
    bottom_lines = [(1, t) for t in x_lines]
    for j, seg in enumerate(segments):
        out = _extrude_layers(gmsh, bottom_lines, 0, seg[-1] - seg[0], 0, np.diff(seg))
        bottom_lines = [out[4 * i] for i in range(3)]
        for i in range(3):
            surfaces[(i, j)] = out[4 * i + 1][1]
    return surfaces


def _extrude_layers_down(gmsh, config: Config, surfaces: dict[tuple[int, int], int]) -> dict[str, list[int]]:
    """Skin and muscle volumes extruded down from z = 0, the membrane up from its footprint
    (the centre surface); returns the volume tags per part."""
    m = config.mesh
    top_surfaces = [(2, surfaces[(i, j)]) for j in range(3) for i in range(3)]
    skin_out = _extrude_layers(gmsh, top_surfaces, 0, 0, -m.skin_thickness, np.full(m.skin_layers, 1.0))
    skin_bottoms = [skin_out[6 * k] for k in range(9)]
    muscle_out = _extrude_layers(gmsh, skin_bottoms, 0, 0, -m.muscle_thickness, np.full(m.muscle_layers, 1.0))
    volumes = {
        "skin": [skin_out[6 * k + 1][1] for k in range(9)],
        "muscle": [muscle_out[6 * k + 1][1] for k in range(9)],
        "membrane": [],
    }
    if config.membrane.model == "elastic":
        mem_out = _extrude_layers(
            gmsh, [(2, surfaces[(1, 1)])], 0, 0, m.membrane_thickness, np.full(m.membrane_layers, 1.0)
        )
        volumes["membrane"] = [mem_out[1][1]]
    return volumes


def _tag_groups(gmsh, config: Config, surfaces: dict[tuple[int, int], int], volumes: dict[str, list[int]]) -> None:
    """Physical groups (``TAGS``): the three volumes and the boundary surfaces."""
    m = config.mesh
    half, a = m.length / 2, m.membrane_size / 2
    tol = 1e-6 * m.length
    z_bottom = -m.skin_thickness - m.muscle_thickness

    def surfaces_in(xmin, ymin, zmin, xmax, ymax, zmax):
        found = gmsh.model.getEntitiesInBoundingBox(
            xmin - tol, ymin - tol, zmin - tol, xmax + tol, ymax + tol, zmax + tol, 2
        )
        return [t for _, t in found]

    bottom = surfaces_in(-half, -half, z_bottom, half, half, z_bottom)
    sides = sorted(
        set(surfaces_in(-half, -half, z_bottom, -half, half, 0))
        | set(surfaces_in(half, -half, z_bottom, half, half, 0))
        | set(surfaces_in(-half, -half, z_bottom, half, -half, 0))
        | set(surfaces_in(-half, half, z_bottom, half, half, 0))
    )
    footprint = [surfaces[(1, 1)]]
    top = [surfaces[(i, j)] for j in range(3) for i in range(3) if surfaces[(i, j)] not in footprint]
    gmsh.model.addPhysicalGroup(3, volumes["skin"], TAGS["skin"], name="skin")
    gmsh.model.addPhysicalGroup(3, volumes["muscle"], TAGS["muscle"], name="muscle")
    if volumes["membrane"]:
        gmsh.model.addPhysicalGroup(3, volumes["membrane"], TAGS["membrane"], name="membrane")
        z_top = m.membrane_thickness
        membrane_top = surfaces_in(-a, -a, z_top, a, a, z_top)
        gmsh.model.addPhysicalGroup(2, membrane_top, TAGS["membrane_top"], name="membrane_top")
    gmsh.model.addPhysicalGroup(2, bottom, TAGS["bottom"], name="bottom")
    gmsh.model.addPhysicalGroup(2, sides, TAGS["sides"], name="sides")
    gmsh.model.addPhysicalGroup(2, top, TAGS["top"], name="top")
    gmsh.model.addPhysicalGroup(2, footprint, TAGS["footprint"], name="footprint")


def _generate(gmsh, tmp: Path, skin_volumes: list[int]) -> tuple[int, int, int]:
    """Mesh (all hexahedra), write binary .msh 4.1 to ``tmp``; (cells, skin cells, nodes)."""
    gmsh.option.setNumber("Mesh.RecombineAll", 1)
    gmsh.model.mesh.generate(3)
    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("Mesh.Binary", 1)
    gmsh.write(str(tmp))
    _, tags, _ = gmsh.model.mesh.getElements(3)
    n_skin = sum(len(t) for vol in skin_volumes for t in gmsh.model.mesh.getElements(3, vol)[1])
    node_tags, _, _ = gmsh.model.mesh.getNodes()
    return sum(len(t) for t in tags), n_skin, len(node_tags)


def ensure_mesh(config: Config, directory: Path | str = DEFAULT_MESH_DIR, comm=None) -> Path:
    """Return the mesh file for ``config``, generating it (on rank 0) if it does not exist.

    Raises:
        ValueError: the mesh cannot be written there (with ``comm``: CollectiveError on every rank).
    """
    path = mesh_path(config, directory)

    def build() -> Path:
        if not path.exists():
            try:
                build_mesh(config, path)
            except OSError as exc:  # a --mesh-dir that is a file, an unwritable folder
                folder = Path(directory)
                reason = f"'{folder}' is a file, not a folder" if folder.is_file() else exc.strerror or str(exc)
                raise ValueError(f"cannot write the mesh '{path}' ({reason})") from None
        return path

    if comm is None:
        return build()
    from skinfem.parallel import on_root

    return on_root(comm, build)


def read_mesh(path: Path | str, comm):
    """Read a mesh written by :func:`build_mesh` into DOLFINx.

    Returns ``dolfinx.io.gmsh.MeshData`` (mesh, cell_tags, facet_tags, ...).

    Raises:
        FileNotFoundError: with the path and how to create the mesh.
        CollectiveError: on every rank, when rank 0 cannot read the file.
    """
    import gmsh

    from skinfem.fenics import dolfinx  # imports dolfinx.io.gmsh after the wheel's PETSc/MPICH
    from skinfem.parallel import on_root

    path = Path(path)
    exists = comm.bcast(path.is_file() if comm.rank == 0 else None, root=0)
    if not exists:
        raise FileNotFoundError(f"mesh file '{path}' does not exist; create it with `skinid mesh --config <config>`")
    if comm.rank == 0:
        gmsh.initialize(interruptible=False)
    try:
        on_root(comm, lambda: _load(gmsh, path))  # every rank refuses together: none waits in the read
        return dolfinx.io.gmsh.model_to_mesh(gmsh.model, comm, 0, gdim=3)
    finally:
        if comm.rank == 0:
            gmsh.finalize()


def _load(gmsh, path: Path) -> None:
    """Read ``path`` into gmsh's model (rank 0).

    Raises:
        ValueError: gmsh cannot read it, or it holds no volume.
    """
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("skinid-read")
    try:
        gmsh.merge(str(path))
    except Exception as exc:  # gmsh raises a bare Exception carrying its last error
        reason = str(exc) or "gmsh could not read it"
    else:
        reason = None if gmsh.model.getEntities(3) else "it holds no volume"
    if reason is not None:
        raise ValueError(f"mesh file '{path}' cannot be read ({reason}); delete it and run `skinid mesh`")
