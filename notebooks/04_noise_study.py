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
# # 04 — Spatially correlated measurement noise
#
# DIC strain maps carry noise correlated over a few mm. Here: noise fields with a 1 mm and a
# 5 mm correlation length at 5 % of the peak strain, and what they do to the PCA (how much
# variance the clean number of PCs still explains). The full study, with emulators refitted
# on noisy data and test-set posteriors, is `skinid study noise` (the paper's 9 cases; see
# the README and `benchmarks/results/noise_study/`).

# %%
import os
from pathlib import Path

import numpy as np

from inference.noise import add_noise, correlation_factor, noise_amplitude, noise_fields
from inference.plots import strain_maps
from skinfem.io import StrainDataset
from surrogate.pca import StrainPCA

data = StrainDataset.open(os.environ.get("SKINID_DATA", "../out/demo/small.h5"))
out = Path(os.environ.get("SKINID_NOTEBOOK_OUT", "../out/notebooks")) / "04"
out.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# Noise fields on the skin cells: amplitude = 5 % of max |strain| of the training materials.

# %%
rng = np.random.default_rng(0)
amplitude = noise_amplitude(data, 0.05)
fields = [noise_fields(correlation_factor(data.xy, length), amplitude, (), rng)[:, 0] for length in (1.0, 5.0)]
strain_maps(
    data.xy,
    fields,
    ["noise E_xx, ℓ = 1 mm", "noise E_xx, ℓ = 5 mm"],
    out / "noise_fields.png",
    window=25.0,
    suptitle="5 % correlated noise",
)
print("amplitude per component:", amplitude)

# %% [markdown]
# ![noise](../out/notebooks/04/noise_fields.png)
#
# The clean data need few PCs; noise spreads the variance over many more.

# %%
train = np.flatnonzero(data.split == 0)
clean = np.concatenate([data.strain(int(i))[..., 0].reshape(-1, data.shape[3]) for i in train])
pca = StrainPCA(0.99).fit(clean)
print(f"clean: M = {pca.n_components_} PCs for 99 %")
shares = {}
for length in (1.0, 5.0):
    noisy_path = out / f"noisy_{length:g}mm.h5"
    if not noisy_path.exists():
        add_noise(data, noisy_path, length, 0.05, seed=1)
    noisy = StrainDataset.open(noisy_path)
    rows = np.concatenate([noisy.strain(int(i))[..., 0].reshape(-1, data.shape[3]) for i in train])
    shares[length] = StrainPCA(pca.n_components_).fit(rows).explained_variance(rows)[-1]
    print(f"ℓ = {length:g} mm: the clean M explains {shares[length]:.1%} of the noisy variance")

# %% [markdown]
# Short-range noise is spread over many PCs (it is nearly white), long-range noise looks
# like signal: both lower the share of variance the clean number of PCs explains.

# %%
assert all(s < 0.99 for s in shares.values())
