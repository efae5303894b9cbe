"""Synthetic measurements: FE fields with optional hidden effects and DIC-like noise, as CSV files.

Used to test model criticism on data whose truth is known (README "Model criticism"). The
data are measured like a DIC system would (:mod:`skinfem.dic`) at a scattered point cloud
(:func:`dic_points`), so that they can come from any discretisation, not the checked one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mpi4py import MPI

from inference.criticism import NoiseModel
from inference.observations import write_measurement
from skinfem.config import Config
from skinfem.dic import StrainGauge, SurfaceStrainGauge
from skinfem.params import Design, SkinParams


def dic_points(extent: float, step: float, rng: np.random.Generator, jitter: float = 0.25,
               holes: int = 3, hole_radius: float = 2.5) -> np.ndarray:
    """(n, 2) a DIC-like point cloud [mm]: a grid of ``step`` over |x|, |y| <= extent, each
    point moved by up to ``jitter`` steps, with ``holes`` circular gaps (lost subsets)."""
    g = np.arange(-extent, extent + 1e-9, step)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = np.clip(xy + rng.uniform(-jitter, jitter, xy.shape) * step, -extent, extent)
    for centre in rng.uniform(-0.8 * extent, 0.8 * extent, (holes, 2)):
        xy = xy[np.linalg.norm(xy - centre, axis=1) > hole_radius]
    return xy


def measured_fields(config: Config, params: SkinParams, designs: list[tuple[float, float]], points: np.ndarray,
                    effects: dict[str, float] | None = None, mesh_dir: Path | str = "meshes",
                    increments: int | None = None, gauge: StrainGauge = StrainGauge()) -> list[np.ndarray]:
    """Noise-free DIC strain (n, 3) at ``points`` (n, 2) [mm], last frame, one per design.

    Args:
        effects: hidden effect parameters by qualified name, e.g. {"pre_stretch.eps_xx": 0.06}.
        gauge: the DIC strain window the data are measured with.
    """
    from skinfem.model import SkinModel

    effects = effects or {}
    if increments is not None:
        config = config.with_changes(solver={"increments": int(increments)})
    names = sorted({name.split(".")[0] for name in effects})
    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=names)
    model.set_effects(effects)
    measure = SurfaceStrainGauge(model.u, np.asarray(points, float), gauge, model.u_ref)
    fields = []
    for alpha in designs:
        model.simulate(params, Design(*alpha))
        fields.append(measure())
    return fields


def write_noisy(fields: list[np.ndarray], points: np.ndarray, designs: list[tuple[float, float]], noise: NoiseModel,
                out: Path | str, seed: int) -> list[Path]:
    """Add noise drawn from ``noise`` (seeded) and write ``out/m_<j>.csv`` with sd columns."""
    rng = np.random.default_rng(seed)
    paths = []
    for j, (field, alpha) in enumerate(zip(fields, designs)):
        noisy = field + noise.sample(points, (), rng)
        paths.append(write_measurement(Path(out) / f"m_{j}.csv", points, noisy, alpha, 1.0,
                                       np.broadcast_to(noise.sd, noisy.shape)))
    return paths


def synthetic_measurements(config: Config, params: SkinParams, designs: list[tuple[float, float]], noise: NoiseModel,
                           out: Path | str, effects: dict[str, float] | None = None, seed: int = 0,
                           mesh_dir: Path | str = "meshes", increments: int | None = None,
                           points: np.ndarray | None = None, gauge: StrainGauge = StrainGauge()) -> list[Path]:
    """Write one measurement CSV (last frame, t = 1) per design: ``out/m_<j>.csv``.

    The fields of :func:`measured_fields` plus noise drawn from ``noise`` (its sd is written
    as sd columns) at ``points`` (default: a DIC-like cloud over +-20 mm, 1 mm step).
    """
    rng = np.random.default_rng(seed)
    points = dic_points(20.0, 1.0, rng) if points is None else np.asarray(points, float)
    fields = measured_fields(config, params, designs, points, effects, mesh_dir, increments, gauge)
    return write_noisy(fields, points, designs, noise, out, int(rng.integers(2**31)))
