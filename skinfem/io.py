"""The strain dataset (HDF5) and ParaView field output.

Dataset layout (one file per sweep or simulation; see README "File formats"):

- ``/params`` (n_mat, 5) float64; attrs ``names``, ``units``, ``lower``, ``upper``
- ``/designs`` (n_des, 2) float64 (alpha11, alpha22); ``/t`` (n_frames,) load fractions
- ``/cells/xy`` (n_cells, 2) skin-cell centroids [mm]; ``/cells/volume`` (n_cells,) [mm^3]
- ``/strain`` (n_mat, n_des, n_frames, n_cells, 3) float32 log strain (xx, yy, xy), chunked
  per simulation; NaN where not (successfully) run
- ``/status`` (n_mat, n_des) int8: 0 not run, 1 converged, -1 failed; ``/messages`` likewise
- ``/newton_iterations`` (n_mat, n_des) int32 total Newton iterations of the simulation
- ``/split`` (n_mat,) int8: 0 train, 1 test
- root attrs: ``config`` (TOML), ``versions`` (JSON), ``mesh_sha256``, ``created``, ``seed``
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

import h5py
import numpy as np

from skinfem.config import PARAM_NAMES, PARAM_UNITS, Config, config_from_toml

STATUS_NOT_RUN, STATUS_OK, STATUS_FAILED = 0, 1, -1
FORMAT_VERSION = 1


def package_versions() -> dict[str, str]:
    """Versions of skinid and the packages that decide its numbers."""
    versions = {}
    for name in ("skinid", "fenics-dolfinx", "dolfinx-solver-real", "numpy", "h5py", "gmsh"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    try:
        from skinfem.fenics import dolfinx

        versions.setdefault("dolfinx", dolfinx.__version__)
    except ImportError:
        pass
    return versions


def create_dataset(
    path: Path | str,
    config: Config,
    params: np.ndarray,
    designs: np.ndarray,
    t: np.ndarray,
    xy: np.ndarray,
    volume: np.ndarray,
    split: np.ndarray,
    mesh_sha256: str,
    bounds: np.ndarray | None = None,
) -> None:
    """Create an empty dataset (every simulation 'not run') with all metadata.

    Args:
        params: (n_mat, 5) skin parameters, theta in degrees.
        designs: (n_des, 2) eigen-strains (alpha11, alpha22).
        t: (n_frames,) load fractions.
        xy, volume: (n_cells, 2) centroids [mm] and (n_cells,) volumes [mm^3].
        split: (n_mat,) 0 train / 1 test.
        bounds: (5, 2) parameter box of the design (default: min/max of ``params``).
    """
    params = np.asarray(params, dtype=float)
    bounds = np.stack([params.min(0), params.max(0)], 1) if bounds is None else np.asarray(bounds)
    n_mat, n_des, n_frames, n_cells = len(params), len(designs), len(t), len(xy)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "skinid-dataset"
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["config"] = config.to_toml()
        f.attrs["versions"] = json.dumps(package_versions())
        f.attrs["mesh_sha256"] = mesh_sha256
        f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        f.attrs["seed"] = config.sweep.seed
        d = f.create_dataset("params", data=params)
        d.attrs["names"] = list(PARAM_NAMES)
        d.attrs["units"] = list(PARAM_UNITS)
        d.attrs["lower"] = bounds[:, 0]
        d.attrs["upper"] = bounds[:, 1]
        f.create_dataset("designs", data=np.asarray(designs, dtype=float))
        f.create_dataset("t", data=np.asarray(t, dtype=float))
        f.create_dataset("cells/xy", data=np.asarray(xy, dtype=float))
        f.create_dataset("cells/volume", data=np.asarray(volume, dtype=float))
        f.create_dataset(
            "strain",
            shape=(n_mat, n_des, n_frames, n_cells, 3),
            dtype=np.float32,
            chunks=(1, 1, n_frames, n_cells, 3),
            fillvalue=np.nan,
        )
        f.create_dataset("status", data=np.zeros((n_mat, n_des), dtype=np.int8))
        f.create_dataset("messages", shape=(n_mat, n_des), dtype=h5py.string_dtype())
        f.create_dataset("newton_iterations", data=np.zeros((n_mat, n_des), dtype=np.int32))
        f.create_dataset("split", data=np.asarray(split, dtype=np.int8))


def write_simulation(
    f: h5py.File,
    i_mat: int,
    i_des: int,
    strain: np.ndarray | None,
    status: int,
    message: str = "",
    newton_iterations: int = 0,
) -> None:
    """Store one simulation's frames (n_frames, n_cells, 3) and its status, then flush."""
    if strain is not None:
        if not np.all(np.isfinite(strain)):
            raise ValueError(f"simulation ({i_mat}, {i_des}) produced non-finite strains")
        f["strain"][i_mat, i_des] = strain.astype(np.float32)
    f["messages"][i_mat, i_des] = message
    f["newton_iterations"][i_mat, i_des] = newton_iterations
    f["status"][i_mat, i_des] = status
    f.flush()


@dataclass
class StrainDataset:
    """A dataset read into memory (strain lazily: use :meth:`strain` to slice it)."""

    path: Path
    config: Config
    params: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    designs: np.ndarray
    t: np.ndarray
    xy: np.ndarray
    volume: np.ndarray
    status: np.ndarray
    messages: np.ndarray
    split: np.ndarray
    mesh_sha256: str
    versions: dict

    @classmethod
    def open(cls, path: Path | str) -> "StrainDataset":
        """Read the metadata of a dataset file.

        Raises:
            FileNotFoundError / ValueError: missing file or not a skinid dataset.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"dataset '{path}' does not exist")
        try:
            f = h5py.File(path, "r")
        except OSError as exc:
            raise ValueError(f"'{path}' is not a readable HDF5 file ({exc})") from None
        with f:
            if f.attrs.get("format") != "skinid-dataset":
                raise ValueError(f"'{path}' is not a skinid dataset (no format attribute)")
            if int(f.attrs["format_version"]) != FORMAT_VERSION:
                raise ValueError(
                    f"'{path}' has dataset format {f.attrs['format_version']}, "
                    f"this skinid reads format {FORMAT_VERSION}"
                )
            p = f["params"]
            return cls(
                path=path,
                config=config_from_toml(f.attrs["config"]),
                params=p[...],
                lower=np.asarray(p.attrs["lower"]),
                upper=np.asarray(p.attrs["upper"]),
                designs=f["designs"][...],
                t=f["t"][...],
                xy=f["cells/xy"][...],
                volume=f["cells/volume"][...],
                status=f["status"][...],
                messages=f["messages"].asstr()[...],
                split=f["split"][...],
                mesh_sha256=str(f.attrs["mesh_sha256"]),
                versions=json.loads(f.attrs["versions"]),
            )

    def strain(self, i_mat=slice(None), i_des=slice(None), i_frame=slice(None)) -> np.ndarray:
        """Read a slice of ``/strain`` (float32, NaN where not run)."""
        with h5py.File(self.path, "r") as f:
            return f["strain"][i_mat, i_des, i_frame]


def write_atomically(path: Path | str, write) -> Path:
    """Call ``write(tmp_path)`` and move the result to ``path`` only if it succeeded."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        tmp.replace(path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


class FieldWriter:
    """ParaView output (XDMF + HDF5): displacement and cell-wise log strain per frame.

    Collective: create and call on all ranks of the model's communicator.
    """

    def __init__(self, model, path: Path | str):
        from skinfem.fenics import dolfinx
        from skinfem.strain import SkinStrainSampler

        mesh = model.mesh
        self.model = model
        self.path = Path(path).with_suffix(".xdmf")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.file = dolfinx.io.XDMFFile(mesh.comm, str(self.path), "w")
        self.file.write_mesh(mesh)
        self.file.write_meshtags(model.cell_tags, mesh.geometry)
        V1 = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
        self.u1 = dolfinx.fem.Function(V1, name="displacement_mm")
        W = dolfinx.fem.functionspace(mesh, ("DG", 0, (3,)))
        self.strain = dolfinx.fem.Function(W, name="log_strain_xx_yy_xy")
        n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
        self._cells = np.arange(n_owned, dtype=np.int32)
        self._sampler = SkinStrainSampler(model.u, self._cells, model.config.solver.quadrature_degree)

    def write(self, t: float) -> None:
        self.u1.interpolate(self.model.u)
        local = self._sampler.local_strain()
        dofs = self.strain.function_space.dofmap.list[self._cells, 0]
        values = self.strain.x.array.reshape(-1, 3)
        values[dofs] = local
        self.strain.x.scatter_forward()
        self.file.write_function(self.u1, t)
        self.file.write_function(self.strain, t)

    def close(self) -> None:
        self.file.close()
