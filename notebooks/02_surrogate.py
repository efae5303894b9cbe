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
# # 02 — The surrogate: PCA of the strain fields + one GP per PC weight
#
# Needs the small sweep and its emulator (`make demo` makes both in `out/demo/`; or set
# `SKINID_DATA` and `SKINID_EMULATOR`).

# %%
import os
from pathlib import Path

import numpy as np

from skinfem.io import StrainDataset
from surrogate.emulator import Emulator
from surrogate.validation import plot_explained_variance, plot_predicted_vs_true, validate

data = StrainDataset.open(os.environ.get("SKINID_DATA", "../out/demo/small.h5"))
emulator = Emulator.load(os.environ.get("SKINID_EMULATOR", "../out/demo/emulator"))
out = Path(os.environ.get("SKINID_NOTEBOOK_OUT", "../out/notebooks")) / "02"
out.mkdir(parents=True, exist_ok=True)
print(f"{data.shape[0]} materials x {data.shape[1]} designs x {data.shape[2]} frames, {data.shape[3]} cells")
print("PCs per component:", emulator.n_weights)

# %% [markdown]
# Explained variance against the number of PCs (the paper's Fig. 5): a handful of PCs hold
# 99 % of the standardised variance.

# %%
plot_explained_variance(emulator, out / "explained_variance.png")
for c, pca in emulator.pcas.items():
    print(c, np.round(np.cumsum(pca.explained_variance_ratio_)[:5], 4))

# %% [markdown]
# ![explained variance](../out/notebooks/02/explained_variance.png)
#
# Validation on the held-out materials (never seen by the PCA or the GPs): R² per PC weight
# and the field error against the PCA's own truncation floor.

# %%
report, arrays = validate(emulator, data)
plot_predicted_vs_true(emulator, arrays, out / "predicted_vs_true.png")
for c, r in report.components.items():
    print(c, "R² per PC:", np.round(r.r2_per_pc, 5))
assert min(r.min_r2 for r in report.components.values()) > 0.99

# %% [markdown]
# ![predicted vs true](../out/notebooks/02/predicted_vs_true.png)
#
# The emulator is differentiable (torch): the sampler gets exact gradients.

# %%
import torch

x = torch.tensor([[0.0012, 0.017, 11.0, 0.285, 30.0, 0.05, -0.05]], dtype=torch.float64, requires_grad=True)
mean = emulator.predict_weights(x, return_var=False)
mean[0, 0].backward()
print("d w1 / d (mu, k1, k2, kappa, theta):", x.grad[0, :5].numpy())
