"""The strain-field emulator: parameters + design + load fraction -> PC weights -> strain field.

Inputs, in this order and these units (as in the dataset):
    mu [MPa], k1 [MPa], k2 [-], kappa [-], theta [deg], alpha11*t [-], alpha22*t [-]
scaled to the unit box of the training data. Outputs: the PC weights of each modelled strain
component (``xx``, ``yy`` and optionally ``xy``), concatenated component by component, and the
fields reconstructed from them (inverse PCA).

Emulator directory (written by :meth:`Emulator.save`):
    meta.json   format, inputs, bounds, components and PC counts, training split, scores,
                versions, fitting options and time
    pca.npz     per component: mean, scale, components, explained_variance_ratio; cell xy, volume
    gp.npz      the GP bank (see :class:`surrogate.gp.GPBank`)
    sklearn_gps.joblib   the fitted scikit-learn regressors (reference implementation)
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import joblib
import numpy as np
import torch

from skinfem.io import STATUS_OK, StrainDataset
from surrogate.gp import GPBank, fit_gps
from surrogate.pca import StrainPCA

INPUT_NAMES = ("mu", "k1", "k2", "kappa", "theta", "alpha11_t", "alpha22_t")
COMPONENTS = ("xx", "yy", "xy")
FORMAT = "skinid-emulator"
FORMAT_VERSION = 1


def model_inputs(params, alpha, t) -> np.ndarray:
    """Raw emulator inputs (B, 7) from params (B, 5), alpha (B, 2) or (2,), t (B,) or scalar."""
    params = np.atleast_2d(np.asarray(params, dtype=float))
    alpha = np.broadcast_to(np.asarray(alpha, dtype=float), (len(params), 2))
    t = np.broadcast_to(np.asarray(t, dtype=float), (len(params),))
    return np.column_stack([params, alpha * t[:, None]])


@dataclass(frozen=True)
class TrainingRows:
    """Rows (material, design, frame) of a dataset and their inputs and fields."""

    index: np.ndarray  # (n, 3) i_mat, i_des, i_frame
    inputs: np.ndarray  # (n, 7)
    fields: np.ndarray  # (n, n_cells, 3)

    @classmethod
    def from_dataset(cls, data: StrainDataset, materials: np.ndarray) -> TrainingRows:
        index, inputs, fields = [], [], []
        for i in materials:
            strain = data.strain(int(i))  # (n_des, n_frames, n_cells, 3)
            for j in np.flatnonzero(data.status[i] == STATUS_OK):
                for k, t in enumerate(data.t):
                    index.append((i, j, k))
                fields.append(strain[j])
                inputs.append(model_inputs(np.repeat(data.params[i][None], len(data.t), 0), data.designs[j], data.t))
        if not index:
            raise ValueError(f"no converged simulation among materials {list(materials)} of {data.path}")
        return cls(np.array(index), np.concatenate(inputs), np.concatenate(fields))


@dataclass
class Emulator:
    """PCA per strain component + one GP per retained PC weight."""

    pcas: dict[str, StrainPCA]
    gps: GPBank
    lower: np.ndarray  # (7,) input box
    upper: np.ndarray
    xy: np.ndarray  # (n_cells, 2) skin-cell centroids [mm]
    volume: np.ndarray  # (n_cells,) [mm^3]
    meta: dict = field(default_factory=dict)
    sklearn_gps: list | None = None

    # -- sizes ---------------------------------------------------------------------------
    @property
    def components(self) -> tuple[str, ...]:
        return tuple(self.pcas)

    @property
    def n_weights(self) -> dict[str, int]:
        return {c: p.n_components_ for c, p in self.pcas.items()}

    def weight_slices(self) -> dict[str, slice]:
        """Where each component's weights sit in the concatenated weight vector."""
        out, start = {}, 0
        for c, m in self.n_weights.items():
            out[c] = slice(start, start + m)
            start += m
        return out

    @property
    def param_bounds(self) -> np.ndarray:
        """(5, 2) the parameter box the emulator was trained on (theta in degrees)."""
        return np.stack([self.lower[:5], self.upper[:5]], 1)

    # -- prediction ----------------------------------------------------------------------
    def scale(self, x):
        """Raw inputs (B, 7) -> unit box (numpy or torch)."""
        lower, span = self.lower, self.upper - self.lower
        if isinstance(x, torch.Tensor):
            lower = torch.as_tensor(lower, dtype=x.dtype, device=x.device)
            span = torch.as_tensor(span, dtype=x.dtype, device=x.device)
        return (x - lower) / span

    def predict_weights(self, x: torch.Tensor, return_var: bool = True):
        """PC weights at raw inputs x (B, 7) (torch, differentiable): mean (B, G)[, var (B, G)]."""
        return self.gps(self.scale(x), return_var=return_var)

    def predict_fields(self, params, alpha, t) -> np.ndarray:
        """Mean strain fields (B, n_cells, n_comp) for params (B, 5), alpha (2,) or (B, 2), t."""
        x = torch.as_tensor(model_inputs(params, alpha, t), device=self.gps.alpha.device)
        with torch.no_grad():
            weights = self.predict_weights(x, return_var=False).cpu().numpy()
        return self.fields_of_weights(weights)

    def fields_of_weights(self, weights: np.ndarray) -> np.ndarray:
        """Inverse PCA: (B, G) -> (B, n_cells, n_comp)."""
        slices = self.weight_slices()
        return np.stack([self.pcas[c].inverse_transform(weights[:, slices[c]]) for c in self.components], -1)

    def weights_of_fields(self, fields: np.ndarray) -> np.ndarray:
        """PCA projection: fields (B, n_cells, n_comp) -> weights (B, G)."""
        return np.concatenate(
            [self.pcas[c].transform(fields[..., k]) for k, c in enumerate(self.components)], 1
        )

    def dataset_fields(self, strain: np.ndarray) -> np.ndarray:
        """Select the modelled components from dataset strains (..., n_cells, 3)."""
        return strain[..., [COMPONENTS.index(c) for c in self.components]]

    # -- persistence ---------------------------------------------------------------------
    def save(self, directory: Path | str) -> Path:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        arrays = {"xy": self.xy, "volume": self.volume}
        for c, pca in self.pcas.items():
            arrays.update(pca.to_arrays(f"{c}_"))
        np.savez(directory / "pca.npz", **arrays)
        np.savez(directory / "gp.npz", **self.gps.to_arrays())
        if self.sklearn_gps is not None:
            joblib.dump(self.sklearn_gps, directory / "sklearn_gps.joblib")
        meta = {
            **self.meta,
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "inputs": list(INPUT_NAMES),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
            "components": list(self.components),
            "n_weights": self.n_weights,
        }
        (directory / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
        return directory

    @classmethod
    def load(cls, directory: Path | str, device: str = "cpu") -> Emulator:
        """Read an emulator directory.

        Raises:
            FileNotFoundError / ValueError: not an emulator directory, or another format version.
        """
        directory = Path(directory)
        meta_path = directory / "meta.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"'{directory}' is not an emulator directory (no meta.json)")
        meta = json.loads(meta_path.read_text())
        if meta.get("format") != FORMAT:
            raise ValueError(f"'{directory}' is not a skinid emulator")
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"'{directory}' was written in emulator format {meta.get('format_version')} "
                f"(skinid {meta.get('versions', {}).get('skinid', '?')}); this skinid reads "
                f"format {FORMAT_VERSION}: refit it with 'skinid surrogate fit'"
            )
        with np.load(directory / "pca.npz") as arrays:
            pcas = {c: StrainPCA.from_arrays(arrays, f"{c}_") for c in meta["components"]}
            xy, volume = arrays["xy"], arrays["volume"]
        with np.load(directory / "gp.npz") as arrays:
            gps = GPBank(dict(arrays)).to(device)
        sk_path = directory / "sklearn_gps.joblib"
        return cls(
            pcas=pcas,
            gps=gps,
            lower=np.array(meta["lower"]),
            upper=np.array(meta["upper"]),
            xy=xy,
            volume=volume,
            meta=meta,
            sklearn_gps=joblib.load(sk_path) if sk_path.exists() else None,
        )


def fit_emulator(
    data: StrainDataset,
    components: tuple[str, ...] = ("xx", "yy"),
    n_components: int | float = 0.99,
    gp_fraction: float = 0.1,
    max_gp_rows: int | None = None,
    restarts: int = 2,
    seed: int = 0,
    n_jobs: int = -1,
) -> Emulator:
    """Fit PCA on every training row and the GPs on a seeded subset of them.

    Only the dataset's training materials (``split == 0``) are used.

    Args:
        gp_fraction: share of the training rows the GPs are fitted on (paper: 0.1).
        max_gp_rows: cap on the number of GP rows (exact GP cost grows as rows^3).
    """
    unknown = set(components) - set(COMPONENTS)
    if unknown or not components:
        raise ValueError(f"components must be among {COMPONENTS}, got {components}")
    if not 0 < gp_fraction <= 1:
        raise ValueError(f"gp_fraction must be in (0, 1], got {gp_fraction}")
    start = time.perf_counter()
    train = np.flatnonzero(data.split == 0)
    rows = TrainingRows.from_dataset(data, train)
    cols = [COMPONENTS.index(c) for c in components]
    pcas = {c: StrainPCA(n_components).fit(rows.fields[..., k]) for c, k in zip(components, cols)}
    weights = np.concatenate([pcas[c].transform(rows.fields[..., k]) for c, k in zip(components, cols)], 1)

    lower = np.concatenate([data.lower, rows.inputs[:, 5:].min(0)])
    upper = np.concatenate([data.upper, rows.inputs[:, 5:].max(0)])
    n_gp = max(2, int(round(gp_fraction * len(rows.index))))
    if max_gp_rows is not None:
        n_gp = min(n_gp, max_gp_rows)
    subset = np.sort(np.random.default_rng(seed).choice(len(rows.index), n_gp, replace=False))
    x_unit = (rows.inputs[subset] - lower) / (upper - lower)
    pca_seconds = time.perf_counter() - start
    gps = fit_gps(x_unit, weights[subset], restarts=restarts, seed=seed, n_jobs=n_jobs)
    meta = {
        "dataset": str(data.path.resolve()),
        "dataset_config": data.config.to_toml(),
        "mesh_sha256": data.mesh_sha256,
        "block_half_length": data.config.mesh.length / 2,
        "train_materials": train.tolist(),
        "test_materials": np.flatnonzero(data.split == 1).tolist(),
        "n_training_rows": int(len(rows.index)),
        "n_gp_rows": int(n_gp),
        "gp_fraction": gp_fraction,
        "restarts": restarts,
        "seed": seed,
        "explained_variance_ratio": {c: p.explained_variance_ratio_[:20].tolist() for c, p in pcas.items()},
        "fit_seconds": {"pca": pca_seconds, "total": time.perf_counter() - start},
        "versions": {n: metadata.version(n) for n in ("skinid", "scikit-learn", "torch", "numpy")},
    }
    emulator = Emulator(
        pcas=pcas,
        gps=GPBank.from_sklearn(gps),
        lower=lower,
        upper=upper,
        xy=data.xy,
        volume=data.volume,
        meta=meta,
        sklearn_gps=gps,
    )
    return emulator
