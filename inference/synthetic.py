"""Synthetic measurements: FE fields with optional hidden effects and DIC-like noise, as CSV files.

Used to test model criticism on data whose truth is known (README "Model criticism").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mpi4py import MPI

from inference.criticism import NoiseModel
from inference.observations import write_measurement
from skinfem.config import Config
from skinfem.params import Design, SkinParams


def synthetic_measurements(config: Config, params: SkinParams, designs: list[tuple[float, float]], noise: NoiseModel,
                           out: Path | str, effects: dict[str, float] | None = None, seed: int = 0,
                           mesh_dir: Path | str = "meshes", increments: int | None = None) -> list[Path]:
    """Write one measurement CSV (last frame, t = 1) per design: ``out/m_<j>.csv``.

    Args:
        effects: hidden effect parameters by qualified name, e.g. {"pre_stretch.eps_xx": 0.06}.
        noise: the noise model the fields are perturbed with; its sd is written as sd columns.

    Points are the skin-cell centroids of the configuration's mesh [mm].
    """
    from skinfem.model import SkinModel

    effects = effects or {}
    if increments is not None:
        config = config.with_changes(solver={"increments": int(increments)})
    names = sorted({name.split(".")[0] for name in effects})
    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=names)
    model.set_effects(effects)
    rng = np.random.default_rng(seed)
    out = Path(out)
    paths = []
    for j, alpha in enumerate(designs):
        frames = model.simulate(params, Design(*alpha))
        xy = frames.xy
        field = frames.strain[-1] + noise.sample(xy, (), rng)
        sd = np.broadcast_to(noise.sd, field.shape)
        paths.append(write_measurement(out / f"m_{j}.csv", xy, field, alpha, 1.0, sd))
    return paths
