"""The strain dataset (HDF5) and ParaView field output.

Dataset layout (one file per sweep or simulation; see README "File formats"):

- ``/params`` (n_mat, 5) float64; attrs ``names``, ``units``, ``lower``, ``upper``
- ``/designs`` (n_des, 2) float64 (alpha11, alpha22); ``/t`` (n_frames,) load fractions
- ``/cells/xy`` (n_cells, 2) skin-cell centroids [mm]; ``/cells/volume`` (n_cells,) [mm^3]
- ``/strain`` (n_mat, n_des, n_frames, n_cells, 3) float32 log strain (xx, yy, xy) of the
  observable named by the root attribute ``observable`` (``surface`` or ``top_cell_average``,
  :mod:`skinfem.strain`; files without it hold ``top_cell_average``); one
  simulation is one contiguous block. Valid only where ``status == 1`` (NaN for failed
  simulations, undefined for those not run: read through :meth:`StrainDataset.strain`)
- ``/status`` (n_mat, n_des) int8: 0 not run, 1 converged, -1 failed; ``/messages`` likewise
- ``/newton_iterations`` (n_mat, n_des) int32 total Newton iterations of the simulation
- ``/seconds`` (n_mat, n_des) float32 wall time of the simulation
- ``/split`` (n_mat,) int8: 0 train, 1 test
- root attrs: ``config`` (TOML), ``versions`` (JSON), ``mesh_sha256``, ``created``, ``seed``,
  ``observable``

Kill safety: every dataset is allocated in full when the file is created (contiguous layout,
early allocation), so recording a simulation only overwrites bytes at fixed offsets and never
touches HDF5 metadata. The strain block is written and flushed before the status byte, and the
file is closed between simulations: a process killed at any moment leaves a readable file in
which every simulation with ``status != 0`` is complete.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path

import h5py
import numpy as np

from skinfem.config import PARAM_NAMES, PARAM_UNITS, Config, config_from_toml
from skinfem.outputs import remove_output

STATUS_NOT_RUN, STATUS_OK, STATUS_FAILED = 0, 1, -1
FORMAT_VERSION = 1
COMPONENTS = ("xx", "yy", "xy")  # the order of the strain components in every array and file
MESSAGE_BYTES = 240  # fixed-length messages keep the file layout static
DATASET_MEMBERS = (
    "params",
    "designs",
    "t",
    "cells/xy",
    "cells/volume",
    "strain",
    "status",
    "messages",
    "newton_iterations",
    "seconds",
    "split",
)
DATASET_ATTRIBUTES = ("config", "versions", "mesh_sha256", "created")


def package_versions() -> dict[str, str]:
    """Versions of skinid and the packages that decide its numbers."""
    versions = {}
    for name in ("skinid", "fenics-dolfinx", "dolfinx-solver-real", "numpy", "h5py", "gmsh"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    # conda and apt installs of DOLFINx have no pip metadata: its module's version, if this process
    # loaded it (importing it only to read the version would start PETSc for nothing)
    dolfinx = sys.modules.get("dolfinx")
    if dolfinx is not None:
        versions.setdefault("dolfinx", dolfinx.__version__)
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
    versions: dict[str, str] | None = None,
    added_noise: AddedNoise | None = None,
) -> None:
    """Create an empty dataset (every simulation 'not run') with all metadata.

    Args:
        params: (n_mat, 5) skin parameters, theta in degrees.
        designs: (n_des, 2) eigen-strains (alpha11, alpha22).
        t: (n_frames,) load fractions.
        xy, volume: (n_cells, 2) centroids [mm] and (n_cells,) volumes [mm^3].
        split: (n_mat,) 0 train / 1 test.
        bounds: (5, 2) parameter box of the design (default: min/max of ``params``).
        versions: the packages that made the simulations (default: this process's,
            :func:`package_versions`).
        added_noise: the measurement noise the strains will carry (the ``noise`` attribute);
            None: simulated strains.
    """
    params = np.asarray(params, dtype=float)
    bounds = np.stack([params.min(0), params.max(0)], 1) if bounds is None else np.asarray(bounds)
    n_mat, n_des, n_frames, n_cells = len(params), len(designs), len(t), len(xy)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "skinid-dataset"
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["config"] = config.to_toml()
        f.attrs["versions"] = json.dumps(package_versions() if versions is None else versions)
        f.attrs["mesh_sha256"] = mesh_sha256
        f.attrs["created"] = datetime.now(UTC).isoformat(timespec="seconds")
        f.attrs["seed"] = config.sweep.seed
        f.attrs["observable"] = config.observable.kind
        if added_noise is not None:
            f.attrs["noise"] = json.dumps(added_noise.to_json())
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
            dcpl=_early_allocation(),
            fill_time="never",  # unwritten blocks stay sparse on disk; status says what is valid
        )
        f.create_dataset("status", data=np.zeros((n_mat, n_des), dtype=np.int8))
        f.create_dataset("messages", data=np.zeros((n_mat, n_des), dtype=f"S{MESSAGE_BYTES}"))
        f.create_dataset("newton_iterations", data=np.zeros((n_mat, n_des), dtype=np.int32))
        f.create_dataset("seconds", data=np.zeros((n_mat, n_des), dtype=np.float32))
        f.create_dataset("split", data=np.asarray(split, dtype=np.int8))


def create_dataset_like(path: Path | str, data: StrainDataset) -> None:
    """Create an empty dataset with the metadata (config, design, cells, split, mesh, the versions
    that made its simulations, the noise it carries) of ``data``."""
    create_dataset(
        path,
        data.config,
        data.params,
        data.designs,
        data.t,
        data.xy,
        data.volume,
        data.split,
        data.mesh_sha256,
        bounds=np.stack([data.lower, data.upper], 1),
        versions=data.versions,
        added_noise=data.added_noise,
    )


def _early_allocation():
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
    return dcpl


def _encode_message(message: str) -> bytes:
    return message.encode("utf-8")[:MESSAGE_BYTES]


def write_simulation(
    path: Path | str,
    i_mat: int,
    i_des: int,
    strain: np.ndarray | None,
    status: int,
    message: str = "",
    newton_iterations: int = 0,
    seconds: float = 0.0,
) -> None:
    """Record one simulation: frames (n_frames, n_cells, 3) first, then its status.

    A failed simulation (``status = -1``) stores NaN strains and its message. Non-finite
    strains of a converged simulation are refused (``ValueError``).
    """
    # No HDF5 file lock: the sweep's rank 0 is the only writer, and a reader (``skinid info``
    # while the sweep runs) must not make the write fail. Readers see complete entries only,
    # because the status byte is written last.
    with h5py.File(path, "r+", locking=False) as f:
        block = f["strain"]
        if status == STATUS_OK:
            if strain is None or not np.all(np.isfinite(strain)):
                raise ValueError(f"simulation ({i_mat}, {i_des}) produced non-finite strains")
            block[i_mat, i_des] = np.asarray(strain, dtype=np.float32)
        else:
            block[i_mat, i_des] = np.full(block.shape[2:], np.nan, dtype=np.float32)
        f.flush()
        f["messages"][i_mat, i_des] = _encode_message(message)
        f["newton_iterations"][i_mat, i_des] = newton_iterations
        f["seconds"][i_mat, i_des] = seconds
        f.flush()
        f["status"][i_mat, i_des] = status


def copy_simulations(data: StrainDataset, path: Path | str, strain_of) -> None:
    """Record every finished simulation of ``data`` in the dataset at ``path`` (same materials and
    designs, created beforehand): a converged one with ``strain_of(i_mat)`` (n_des, n_frames,
    n_cells, 3) for its design, with its Newton iterations and seconds; a failed one as failed,
    with its message. ``strain_of`` is called once per material, in order."""
    n_mat, n_des = data.status.shape
    for i in range(n_mat):
        block = strain_of(i)
        for j in range(n_des):
            status = int(data.status[i, j])
            if status == STATUS_OK:
                write_simulation(
                    path, i, j, block[j], status, "", int(data.newton_iterations[i, j]), float(data.seconds[i, j])
                )
            elif status != STATUS_NOT_RUN:
                write_simulation(path, i, j, None, status, data.messages[i, j])


@dataclass(frozen=True)
class AddedNoise:
    """The measurement noise ``skinid noise`` added to a dataset's strains (RBF-correlated Gaussian).

    Attributes:
        length_mm: correlation length of the noise [mm].
        level: its amplitude as a share of the clean training data's max |strain| per component [-].
        amplitude: (3,) its standard deviation per strain component (xx, yy, xy) [-].
    """

    length_mm: float
    level: float
    amplitude: tuple[float, ...]

    @classmethod
    def from_json(cls, entry: dict) -> AddedNoise:
        return cls(float(entry["length_mm"]), float(entry["level"]), tuple(float(a) for a in entry["amplitude"]))

    def to_json(self) -> dict:
        return {"length_mm": self.length_mm, "level": self.level, "amplitude": list(self.amplitude)}


def _added_noise(path: Path, text: str) -> AddedNoise:
    """The dataset's ``noise`` attribute (JSON); ValueError naming the file if it is not one."""
    try:
        return AddedNoise.from_json(json.loads(text))
    except (KeyError, TypeError, ValueError) as exc:  # ValueError includes JSONDecodeError
        problem = f"no entry {exc}" if isinstance(exc, KeyError) else exc
        raise ValueError(f"'{path}' has a corrupt 'noise' attribute ({problem}): add the noise again") from None


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
    newton_iterations: np.ndarray
    seconds: np.ndarray
    split: np.ndarray
    mesh_sha256: str
    versions: dict
    created: str
    added_noise: AddedNoise | None = None  # the noise `skinid noise` added; None: simulated strains

    @property
    def observable(self) -> str:
        """What ``/strain`` holds per cell: ``surface`` or ``top_cell_average`` (:mod:`skinfem.strain`)."""
        return self.config.observable.kind

    @classmethod
    def open(cls, path: Path | str) -> StrainDataset:
        """Read the metadata of a dataset file.

        Raises:
            FileNotFoundError / ValueError: missing file or not a skinid dataset.
        """
        path = Path(path)
        if path.is_dir():
            raise ValueError(f"'{path}' is a folder, not a dataset (.h5)")
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
            missing = [f"/{k}" for k in DATASET_MEMBERS if k not in f] + [
                f"attribute '{k}'" for k in DATASET_ATTRIBUTES if k not in f.attrs
            ]
            if missing:
                raise ValueError(f"'{path}' is not a complete skinid dataset: it has no {missing[0]}")
            p = f["params"]
            observable = str(f.attrs.get("observable", "top_cell_average"))  # older files: the cell average
            noise = f.attrs.get("noise")
            return cls(
                path=path,
                config=config_from_toml(f.attrs["config"]).with_changes(observable={"kind": observable}),
                params=p[...],
                lower=np.asarray(p.attrs["lower"]),
                upper=np.asarray(p.attrs["upper"]),
                designs=f["designs"][...],
                t=f["t"][...],
                xy=f["cells/xy"][...],
                volume=f["cells/volume"][...],
                status=f["status"][...],
                messages=np.char.decode(f["messages"][...], "utf-8"),
                newton_iterations=f["newton_iterations"][...],
                seconds=f["seconds"][...],
                split=f["split"][...],
                mesh_sha256=str(f.attrs["mesh_sha256"]),
                versions=json.loads(f.attrs["versions"]),
                created=str(f.attrs["created"]),
                added_noise=None if noise is None else _added_noise(path, noise),
            )

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(n_mat, n_des, n_frames, n_cells)."""
        return len(self.params), len(self.designs), len(self.t), len(self.xy)

    def strain(self, i_mat=slice(None), i_des=slice(None), i_frame=slice(None)) -> np.ndarray:
        """Read a slice of ``/strain`` (float32), NaN wherever the simulation did not converge.

        Indices are ints or slices (at most one of them a list, as in h5py).
        """
        with h5py.File(self.path, "r") as f:
            data = f["strain"][i_mat, i_des, i_frame]
        ok = self.status[i_mat, i_des] == STATUS_OK
        if np.ndim(ok) == 0:
            if not ok:
                data[...] = np.nan
        else:
            data[~ok] = np.nan
        return data


ALPHA_TOLERANCE = 1e-3  # |alpha given - alpha of a design| that still names it [-]


def design_index(designs: np.ndarray, alpha: tuple[float, float] | np.ndarray, dataset: Path | str) -> int:
    """The index of the design with eigen-strains ``alpha`` = (alpha11, alpha22) [-], each
    matched within ``ALPHA_TOLERANCE`` (e.g. the "mixed" design (0.05, -0.05)).

    Args:
        designs: (n_des, 2) a dataset's eigen-strains (:attr:`StrainDataset.designs`).
        dataset: the dataset's path, named in the error.
    Raises:
        ValueError: no design has these eigen-strains (the message lists the dataset's).
    """
    distance = np.abs(np.asarray(designs) - np.asarray(alpha, dtype=float)).max(1)
    j = int(np.argmin(distance))
    if distance[j] > ALPHA_TOLERANCE:
        known = ", ".join(f"{a:g},{b:g}" for a, b in designs)
        raise ValueError(f"{dataset} has no design alpha = {alpha[0]:g},{alpha[1]:g} (its designs: {known})")
    return j


def dataset_summary(data: StrainDataset) -> str:
    """Human-readable summary: sizes, status counts, split, strain ranges, configuration."""
    n_mat, n_des, n_frames, n_cells = data.shape
    counts = {
        name: int(np.count_nonzero(data.status == code))
        for name, code in (("converged", STATUS_OK), ("failed", STATUS_FAILED), ("not run", STATUS_NOT_RUN))
    }
    lines = [
        f"{data.path}: skinid dataset, config '{data.config.name}', created {data.created}, "
        f"observable: {data.observable}",
        f"  {n_mat} materials x {n_des} designs x {n_frames} frames x {n_cells} skin cells "
        f"({data.path.stat().st_size / 1e6:.1f} MB on disk)",
        "  simulations: " + ", ".join(f"{v} {k}" for k, v in counts.items()),
        f"  split: {int(np.sum(data.split == 0))} train, {int(np.sum(data.split == 1))} test "
        f"materials (test: {', '.join(map(str, np.flatnonzero(data.split)))})",
        "  parameter box: "
        + ", ".join(
            f"{n} [{lo:.4g}, {hi:.4g}] {u}" for n, u, lo, hi in zip(PARAM_NAMES, PARAM_UNITS, data.lower, data.upper)
        ),
        "  designs (alpha11, alpha22): " + ", ".join(f"({a:+.3g}, {b:+.3g})" for a, b in data.designs),
    ]
    ok = data.status == STATUS_OK
    if ok.any():
        low, high = np.full(3, np.inf), np.full(3, -np.inf)
        for i in np.flatnonzero(ok.any(1)):  # one material at a time: bounded memory
            block = data.strain(i)[ok[i]]
            low = np.minimum(low, np.nanmin(block, axis=(0, 1, 2)))
            high = np.maximum(high, np.nanmax(block, axis=(0, 1, 2)))
        lines.append(
            "  log strain range: "
            + ", ".join(f"E_{c} [{lo:+.4f}, {hi:+.4f}]" for c, lo, hi in zip(COMPONENTS, low, high))
        )
        secs = data.seconds[ok]
        its = data.newton_iterations[ok]
        lines.append(
            f"  per simulation: {secs.mean():.2f} s (max {secs.max():.2f} s), {its.mean():.1f} Newton iterations"
        )
    failed = np.argwhere(data.status == STATUS_FAILED)
    for i, j in failed[:5]:
        lines.append(f"  failed ({i}, {j}): {data.messages[i, j]}")
    if len(failed) > 5:
        lines.append(f"  ... and {len(failed) - 5} more failures")
    lines.append(
        f"  mesh sha256 {data.mesh_sha256[:16]}..., versions: "
        + ", ".join(f"{k} {v}" for k, v in data.versions.items())
    )
    return "\n".join(lines)


def field_files(path: Path | str) -> tuple[Path, Path]:
    """The two files of a ParaView output named ``path``: the .xdmf and the .h5 it refers to."""
    path = Path(path)
    return path.with_suffix(".xdmf"), path.with_suffix(".h5")


class FieldWriter:
    """ParaView output (XDMF + HDF5): displacement and cell-wise log strain per frame.

    The pair is written into a hidden folder next to ``path`` and moved into place (the .xdmf
    last) when it is closed with ``keep=True``, so that a failed or killed simulation leaves no
    half-written fields under the given name. As a context manager it keeps the files if the
    block ends normally and discards them otherwise.

    Collective: create and call on all ranks of the model's communicator.
    """

    def __init__(self, model, path: Path | str):
        from skinfem.fenics import dolfinx
        from skinfem.strain import SkinStrainSampler

        mesh = model.mesh
        self.model = model
        self.path, _ = field_files(path)
        self._partial = self.path.with_name(f".{self.path.stem}.partial")
        self._partial.mkdir(parents=True, exist_ok=True)
        self.file = dolfinx.io.XDMFFile(mesh.comm, str(self._partial / self.path.name), "w")
        self.file.write_mesh(mesh)
        self.file.write_meshtags(model.cell_tags, mesh.geometry)
        V1 = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
        self.u1 = dolfinx.fem.Function(V1, name="displacement_mm")
        W = dolfinx.fem.functionspace(mesh, ("DG", 0, (3,)))
        self.strain = dolfinx.fem.Function(W, name="log_strain_xx_yy_xy")
        n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
        self._cells = np.arange(n_owned, dtype=np.int32)
        self._sampler = SkinStrainSampler(model.u, self._cells, model.config.solver.quadrature_degree)

    def __enter__(self) -> FieldWriter:
        return self

    def __exit__(self, kind, exc, traceback) -> None:
        self.close(keep=kind is None)

    def write(self, t: float) -> None:
        self.u1.interpolate(self.model.u)
        local = self._sampler.local_strain()
        dofs = self.strain.function_space.dofmap.list[self._cells, 0]
        values = self.strain.x.array.reshape(-1, 3)
        values[dofs] = local
        self.strain.x.scatter_forward()
        self.file.write_function(self.u1, t)
        self.file.write_function(self.strain, t)

    def close(self, keep: bool = True) -> None:
        """Close the files; move them into place if ``keep``, else delete them."""
        self.file.close()
        comm = self.model.mesh.comm
        comm.barrier()
        if comm.rank == 0:
            if keep:
                for name in reversed(field_files(self.path)):  # the .h5 first: an .xdmf means a complete pair
                    (self._partial / name.name).replace(name)
            remove_output(self._partial)
        comm.barrier()
