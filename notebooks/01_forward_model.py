# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 01 — The forward model
#
# A 50 × 50 mm block of skin (0.6 mm, Holzapfel–Gasser–Ogden) on muscle (10 mm,
# neo-Hookean) with a 20 × 20 mm active membrane bonded on top. The membrane's eigen-strain
# (α11, α22) is ramped in 10 increments; the skin's log strain is read per cell.
# Units: mm, MPa; angles in degrees.
#
# Run from the `notebooks/` folder (or set `SKINID_MESH_DIR`, `SKINID_NOTEBOOK_OUT`).

# %%
import os
from pathlib import Path

import numpy as np
from mpi4py import MPI

from inference.plots import strain_maps
from skinfem.config import load_config
from skinfem.io import FieldWriter
from skinfem.model import SkinModel
from skinfem.params import Design, SkinParams

mesh_dir = Path(os.environ.get("SKINID_MESH_DIR", "../meshes"))
out = Path(os.environ.get("SKINID_NOTEBOOK_OUT", "../out/notebooks")) / "01"
out.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# The `small` preset: 2 mm cells under the membrane, graded to 6 mm at the block edge.

# %%
config = load_config("small")
model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir)
print(f"{model.n_dofs} dofs, {len(model.strain_sampler.xy)} observed skin cells, mesh {model.mesh_path.name}")

# %% [markdown]
# One simulation: a "mixed" membrane (stretches along x, contracts along y) on skin with
# fibers at 30°. The ParaView file holds the displacement and the cell strain of every frame.

# %%
params = SkinParams(mu=0.0012, k1=0.017, k2=11.0, kappa=0.285, theta=30.0)
design = Design(0.05, -0.05)
with FieldWriter(model, out / "mixed.xdmf") as writer:  # mixed.xdmf + mixed.h5, in place when complete
    frames = model.simulate(params, design, on_frame=writer.write)
print(f"{len(frames.t)} frames in {frames.seconds:.1f} s; Newton iterations {frames.newton_iterations}")

# %% [markdown]
# Under the membrane the skin follows the membrane (ln(1 + α) ≈ 0.049 along x); the fibers at
# 30° make the field asymmetric; strain concentrates at the membrane corners.

# %%
E = frames.strain[-1]
centre = np.argmin(np.linalg.norm(frames.xy, axis=1))
print(f"centre E_xx = {E[centre, 0]:.4f} (ln 1.05 = {np.log(1.05):.4f}), E_yy = {E[centre, 1]:.4f}")
strain_maps(
    frames.xy,
    [E[:, 0], E[:, 1], E[:, 2]],
    ["E_xx", "E_yy", "E_xy"],
    out / "mixed.png",
    theta_deg=params.theta,
    suptitle="mixed membrane (0.05, −0.05), t = 1",
)

# %% [markdown]
# ![strain maps](../out/notebooks/01/mixed.png)
#
# The load ramp: strain at the centre and at a membrane corner against the load fraction.

# %%
import matplotlib.pyplot as plt

corner = np.argmin(np.linalg.norm(frames.xy - [10.0, 10.0], axis=1))
fig, ax = plt.subplots(figsize=(5, 3.5))
ax.plot(frames.t, frames.strain[:, centre, 0], "o-", label="centre E_xx")
ax.plot(frames.t, frames.strain[:, corner, 2], "s-", label="corner E_xy")
ax.set_xlabel("load fraction t [-]")
ax.set_ylabel("log strain [-]")
ax.legend()
fig.tight_layout()
fig.savefig(out / "ramp.png", dpi=100)
assert abs(E[centre, 0] - np.log(1.05)) < 0.01
