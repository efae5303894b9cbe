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
# # 03 — Posteriors: one frame, several frames, several membranes
#
# NUTS posteriors of (μ, k1, k2, κ, θ) for a held-out material of the small sweep, from three
# setups (the paper's Fig. 8): the last frame of the "mixed" membrane; the last three frames
# of it; and the last frame of three membranes. Short chains here (2 × 300 after 300 warm-up,
# GP variance fixed at the mode) — use `skinid infer` with the defaults for real work.

# %%
import os
from pathlib import Path

import numpy as np

from inference.model import ObservedWeights, SkinPosterior
from inference.observations import from_dataset
from inference.plots import corner_plot
from inference.sampling import sample_posterior
from inference.studies import spread_designs
from skinfem.io import StrainDataset, design_index
from surrogate.emulator import Emulator

data = StrainDataset.open(os.environ.get("SKINID_DATA", "../out/demo/small.h5"))
emulator = Emulator.load(os.environ.get("SKINID_EMULATOR", "../out/demo/emulator"))
out = Path(os.environ.get("SKINID_NOTEBOOK_OUT", "../out/notebooks")) / "03"
out.mkdir(parents=True, exist_ok=True)
material = int(np.flatnonzero(data.split)[0])
mixed = design_index(data.designs, (0.05, -0.05), data.path)
others = spread_designs(data.designs, mixed, 3)[1:]  # the two designs farthest from it and each other
print("material", material, "true", dict(zip(("mu", "k1", "k2", "kappa", "theta"), data.params[material])))

# %%
setups = {
    "single frame": from_dataset(data, material, [mixed], [-1]),
    "3 frames": from_dataset(data, material, [mixed], [-3, -2, -1]),
    "3 membranes": from_dataset(data, material, [mixed, *others], [-1]),
}
widths = {}
for name, observations in setups.items():
    posterior = SkinPosterior(emulator, ObservedWeights.project(emulator, observations), gp_variance="mode")
    samples = sample_posterior(posterior, chains=2, warmup=300, draws=300, seed=1, n_jobs=2, progress=False)
    path = out / f"corner_{name.replace(' ', '_')}.png"
    corner_plot(samples, path, title=f"{name}: posterior (blue) vs prior (grey), truth red")
    table = samples.summary().parameters
    widths[name] = {
        n: (e.q97_5 - e.q2_5) / np.ptp(emulator.param_bounds[i]) for i, (n, e) in enumerate(table.items()) if i < 5
    }
    print(f"{name:>13}: 95 % interval / prior width", {n: round(w, 2) for n, w in widths[name].items()})

# %% [markdown]
# ![single](../out/notebooks/03/corner_single_frame.png)
# ![3 membranes](../out/notebooks/03/corner_3_membranes.png)
#
# More membranes constrain the parameters more than more frames of one membrane: the frames
# of one ramp are nearly proportional, the membranes probe different directions.

# %%
mean_width = {k: np.mean(list(v.values())) for k, v in widths.items()}
print(mean_width)
assert mean_width["3 membranes"] < mean_width["single frame"]
