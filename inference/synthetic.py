"""Synthetic measurements: FE fields with optional hidden effects and DIC-like noise, as CSV files.

Used to test model criticism on data whose truth is known (README "Model criticism"). The
data are measured like a DIC system would (:mod:`skinfem.dic`) at a scattered point cloud
(:func:`dic_points`), so that they can come from any discretisation, not the checked one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import ufl
from mpi4py import MPI

from inference.criticism import NoiseModel
from inference.observations import write_measurement
from skinfem.config import Config
from skinfem.dic import StrainGauge, SurfaceStrainGauge
from skinfem.effects import Effect, ModelTerms
from skinfem.params import Design, SkinParams


@dataclass(frozen=True)
class StiffInclusion(Effect):
    """A defect outside the check's registry, for synthetic data only: a cylinder of skin
    ``ratio`` times stiffer (scar-like) through the skin's thickness, centred at ``centre``
    [mm] with ``radius`` [mm], its edge smoothed over ``edge`` [mm]. No parameters: a check
    cannot fit it, it can only locate it."""

    centre: tuple[float, float]
    radius: float
    ratio: float
    edge: float = 0.25
    name = "stiff_inclusion"
    description = "a stiff circular inclusion in the skin (synthetic data only)"
    parameters = ()

    def apply(self, terms: ModelTerms, p: dict[str, object]) -> None:
        x = terms.x
        r = ufl.sqrt((x[0] - self.centre[0]) ** 2 + (x[1] - self.centre[1]) ** 2)
        inside = (1 - ufl.tanh((r - self.radius) / self.edge)) / 2
        terms.skin_stiffness = terms.skin_stiffness * (1 + (self.ratio - 1) * inside)


def dic_points(
    extent: float, step: float, rng: np.random.Generator, jitter: float = 0.25, holes: int = 3, hole_radius: float = 2.5
) -> np.ndarray:
    """(n, 2) a DIC-like point cloud [mm]: a grid of ``step`` over |x|, |y| <= extent, each
    point moved by up to ``jitter`` steps, with ``holes`` circular gaps (lost subsets)."""
    g = np.arange(-extent, extent + 1e-9, step)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = np.clip(xy + rng.uniform(-jitter, jitter, xy.shape) * step, -extent, extent)
    for centre in rng.uniform(-0.8 * extent, 0.8 * extent, (holes, 2)):
        xy = xy[np.linalg.norm(xy - centre, axis=1) > hole_radius]
    return xy


def measured_fields(
    config: Config,
    params: SkinParams,
    designs: list[tuple[float, float]],
    points: np.ndarray,
    effects: dict[str, float] | None = None,
    mesh_dir: Path | str = "meshes",
    increments: int | None = None,
    gauge: StrainGauge = StrainGauge(),
    defects: Sequence[Effect] = (),
) -> list[np.ndarray]:
    """Noise-free DIC strain (n, 3) at ``points`` (n, 2) [mm], last frame, one per design.

    Args:
        effects: hidden effect parameters by qualified name, e.g. {"pre_stretch.eps_xx": 0.06}.
        gauge: the DIC strain window the data are measured with.
        defects: effects outside the registry (e.g. :class:`StiffInclusion`), hidden too.
    """
    from skinfem.model import SkinModel

    effects = effects or {}
    if increments is not None:
        config = config.with_changes(solver={"increments": int(increments)})
    names = sorted({name.split(".")[0] for name in effects})
    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=[*names, *defects])
    model.set_effects(effects)
    measure = SurfaceStrainGauge(model.u, np.asarray(points, float), gauge, model.u_ref)
    fields = []
    for alpha in designs:
        model.simulate(params, Design(*alpha))
        fields.append(measure())
    return fields


def write_noisy(
    fields: list[np.ndarray],
    points: np.ndarray,
    designs: list[tuple[float, float]],
    noise: NoiseModel,
    out: Path | str,
    seed: int,
    stated_sd: np.ndarray | None = None,
) -> list[Path]:
    """Add noise drawn from ``noise`` (seeded) and write ``out/m_<j>.csv`` with sd columns:
    ``noise.sd``, or ``stated_sd`` (3,) to mis-state it."""
    rng = np.random.default_rng(seed)
    stated = noise.sd if stated_sd is None else np.asarray(stated_sd, float)
    paths = []
    for j, (field, alpha) in enumerate(zip(fields, designs)):
        noisy = field + noise.sample(points, (), rng)
        paths.append(
            write_measurement(Path(out) / f"m_{j}.csv", points, noisy, alpha, 1.0, np.broadcast_to(stated, noisy.shape))
        )
    return paths


def synthetic_measurements(
    config: Config,
    params: SkinParams,
    designs: list[tuple[float, float]],
    noise: NoiseModel,
    out: Path | str,
    effects: dict[str, float] | None = None,
    seed: int = 0,
    mesh_dir: Path | str = "meshes",
    increments: int | None = None,
    points: np.ndarray | None = None,
    gauge: StrainGauge = StrainGauge(),
    defects: Sequence[Effect] = (),
) -> list[Path]:
    """Write one measurement CSV (last frame, t = 1) per design: ``out/m_<j>.csv``.

    The fields of :func:`measured_fields` plus noise drawn from ``noise`` (its sd is written
    as sd columns) at ``points`` (default: a DIC-like cloud over +-20 mm, 1 mm step).
    """
    rng = np.random.default_rng(seed)
    points = dic_points(20.0, 1.0, rng) if points is None else np.asarray(points, float)
    fields = measured_fields(config, params, designs, points, effects, mesh_dir, increments, gauge, defects)
    return write_noisy(fields, points, designs, noise, out, int(rng.integers(2**31)))
