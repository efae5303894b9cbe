"""The strain-field emulator: parameters + design + load fraction -> PC weights -> strain field.

Inputs, in this order and these units (as in the dataset):
    mu [MPa], k1 [MPa], k2 [-], kappa [-], theta [deg], alpha11*t [-], alpha22*t [-]
scaled to the unit box of the training data. Outputs: the PC weights of each modelled strain
component (``xx``, ``yy`` and optionally ``xy``), concatenated component by component, and the
fields reconstructed from them (inverse PCA).

Emulator directory (written by :meth:`Emulator.save`):
    meta.json   format, inputs, bounds, components and PC counts, and the entries of
                :class:`EmulatorProvenance` (dataset, training split, fitting options and
                time, versions, validation scores)
    pca.npz     per component: mean, scale, components, explained_variance_ratio; cell xy, volume
    gp.npz      the GP bank (see :class:`surrogate.gp.GPBank`)
    sklearn_gps.joblib   the fitted scikit-learn regressors (reference implementation):
                :class:`surrogate.gp.StandardisedGP` (files of earlier versions: scikit-learn
                ``normalize_y=True`` regressors, the same model); both ``predict(x, return_std)``
                in target units
"""

from __future__ import annotations

import json
import time
import tomllib
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from importlib import metadata
from pathlib import Path

import joblib
import numpy as np
import torch

from skinfem.io import COMPONENTS, STATUS_OK, AddedNoise, StrainDataset
from skinfem.outputs import write_text
from surrogate.error_model import FOLDS, HeldOutExcess, cross_validated_excess, design_correlation, material_folds
from surrogate.gp import GPBank, fit_gps
from surrogate.pca import StrainPCA

INPUT_NAMES = ("mu", "k1", "k2", "kappa", "theta", "alpha11_t", "alpha22_t")
FORMAT = "skinid-emulator"
FORMAT_VERSION = 1
REFIT = "refit the emulator with 'skinid surrogate fit'"


def model_inputs(params, alpha, t) -> np.ndarray:
    """Raw emulator inputs (B, 7) from params (B, 5), alpha (B, 2) or (2,), t (B,) or scalar."""
    params = np.atleast_2d(np.asarray(params, dtype=float))
    alpha = np.broadcast_to(np.asarray(alpha, dtype=float), (len(params), 2))
    t = np.broadcast_to(np.asarray(t, dtype=float), (len(params),))
    return np.column_stack([params, alpha * t[:, None]])


def unit_span(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The width of the inputs' box per input, used to scale it to the unit box; 1 for an input
    constant over the training rows (alpha22 t of a uniaxial design alone), which then scales
    to 0 like every training row instead of 0 / 0."""
    span = np.asarray(upper, dtype=float) - np.asarray(lower, dtype=float)
    return np.where(span > 0, span, 1.0)


@dataclass(frozen=True)
class TrainingRows:
    """Rows (material, design, frame) of a dataset and their inputs and fields."""

    index: np.ndarray  # (n, 3) i_mat, i_des, i_frame
    inputs: np.ndarray  # (n, 7)
    fields: np.ndarray  # (n, n_cells, 3)

    @classmethod
    def from_dataset(cls, data: StrainDataset, materials: np.ndarray) -> TrainingRows:
        """Every converged (design, frame) row of the given material indices."""
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


@dataclass(frozen=True)
class HeldOutScores:
    """Scores of one strain component on the held-out materials (see :mod:`surrogate.validation`)."""

    min_r2: float  # smallest R^2 over the component's PC weights [-]
    field_rmse: float  # RMS error of the emulated field [-] (strain)
    field_rmse_relative: float  # field_rmse over the RMS simulated strain [-]


@dataclass(frozen=True)
class EmulatorProvenance:
    """Where an emulator came from and how it was fitted: the entries of ``meta.json`` that
    are not derived from the emulator's arrays.

    Attributes:
        dataset: the dataset (.h5) it was fitted on (absolute path at fit time).
        dataset_config: that dataset's configuration as TOML text (``skinfem.config.config_from_toml``).
        mesh_sha256: SHA-256 of the dataset's mesh; data to validate on must share it.
        block_half_length: half the side of the simulated block [mm]; the skin cells lie in
            [-block_half_length, block_half_length]^2.
        train_materials: material indices of the dataset's training split (``split == 0``).
        test_materials: material indices of its test split (``split == 1``).
        n_training_rows: (material, design, frame) rows the PCA was fitted on.
        n_gp_rows: the seeded subset of those rows the GPs were fitted on.
        gp_fraction: the requested share of training rows for the GPs [-].
        restarts: optimizer restarts per GP.
        seed: seed of the GP-row subset and of the optimizer restarts.
        explained_variance_ratio: per component, the first (at most 20) PCA explained-variance
            ratios [-].
        fit_seconds: wall time [s] of the fit: ``"pca"`` (rows and PCA), ``"held_out_excess"`` (the
            cross-validation: the GPs fitted once per fold), ``"total"`` (all of it).
        versions: package versions at fit time (skinid, scikit-learn, torch, numpy).
        validation: per component, the scores on the held-out materials; None until
            :func:`surrogate.validation.validate_directory` has run.
        held_out_excess: the GPs' error beyond their own variance on left-out training
            materials (:mod:`surrogate.error_model`); None for emulators fitted before it.
        training_noise: the measurement noise the training strains carry (a dataset ``skinid
            noise`` wrote), or None (simulated strains). With it the GPs' white-noise level is that
            noise, not an emulator error (:meth:`Emulator.white_noise_is_measurement`).
    """

    dataset: Path
    dataset_config: str
    mesh_sha256: str
    block_half_length: float
    train_materials: tuple[int, ...]
    test_materials: tuple[int, ...]
    n_training_rows: int
    n_gp_rows: int
    gp_fraction: float
    restarts: int
    seed: int
    explained_variance_ratio: dict[str, tuple[float, ...]]
    fit_seconds: dict[str, float]
    versions: dict[str, str]
    validation: dict[str, HeldOutScores] | None = None
    held_out_excess: HeldOutExcess | None = None
    training_noise: AddedNoise | None = None

    def to_json(self) -> dict:
        """The ``meta.json`` entries (JSON types), as :meth:`from_json` reads them."""
        out = {
            "dataset": str(self.dataset),
            "dataset_config": self.dataset_config,
            "mesh_sha256": self.mesh_sha256,
            "block_half_length": self.block_half_length,
            "train_materials": list(self.train_materials),
            "test_materials": list(self.test_materials),
            "n_training_rows": self.n_training_rows,
            "n_gp_rows": self.n_gp_rows,
            "gp_fraction": self.gp_fraction,
            "restarts": self.restarts,
            "seed": self.seed,
            "explained_variance_ratio": {c: list(r) for c, r in self.explained_variance_ratio.items()},
            "fit_seconds": dict(self.fit_seconds),
            "versions": dict(self.versions),
        }
        if self.validation is not None:
            out["validation"] = {c: asdict(s) for c, s in self.validation.items()}
        if self.held_out_excess is not None:
            out["held_out_excess"] = self.held_out_excess.to_json()
        if self.training_noise is not None:
            out["training_noise"] = self.training_noise.to_json()
        return out

    @classmethod
    def from_json(cls, meta: dict) -> EmulatorProvenance:
        """Read the entries of a ``meta.json`` dict (its format entries are ignored).

        Raises:
            KeyError: an entry is missing.
        """
        validation, excess, noise = meta.get("validation"), meta.get("held_out_excess"), meta.get("training_noise")
        return cls(
            dataset=Path(meta["dataset"]),
            dataset_config=meta["dataset_config"],
            mesh_sha256=meta["mesh_sha256"],
            block_half_length=_block_half_length(meta),
            train_materials=tuple(meta["train_materials"]),
            test_materials=tuple(meta["test_materials"]),
            n_training_rows=meta["n_training_rows"],
            n_gp_rows=meta["n_gp_rows"],
            gp_fraction=meta["gp_fraction"],
            restarts=meta["restarts"],
            seed=meta["seed"],
            explained_variance_ratio={c: tuple(r) for c, r in meta["explained_variance_ratio"].items()},
            fit_seconds=dict(meta["fit_seconds"]),
            versions=dict(meta["versions"]),
            validation=None if validation is None else {c: HeldOutScores(**s) for c, s in validation.items()},
            held_out_excess=None if excess is None else HeldOutExcess.from_json(excess),
            training_noise=None if noise is None else AddedNoise.from_json(noise),
        )

    def validated(self, scores: dict[str, HeldOutScores]) -> EmulatorProvenance:
        """A copy with the held-out scores recorded."""
        return replace(self, validation=dict(scores))


def _block_half_length(meta: dict) -> float:
    """``block_half_length`` [mm] of a ``meta.json`` dict; emulators fitted before it was
    recorded: half the ``mesh.length`` of their dataset's configuration."""
    if "block_half_length" in meta:
        return meta["block_half_length"]
    return tomllib.loads(meta["dataset_config"])["mesh"]["length"] / 2


def _read_npz(path: Path, read):
    """``read(arrays)`` of the arrays in ``path``.

    Raises:
        ValueError: the file is truncated or corrupt, or lacks an array ``read`` needs.
    """
    try:
        with np.load(path) as arrays:
            return read(arrays)
    except (zipfile.BadZipFile, KeyError, EOFError, ValueError) as exc:
        problem = exc.args[0] if isinstance(exc, KeyError) else exc
        raise ValueError(f"'{path}' is truncated or corrupt ({problem}): {REFIT}") from exc


@dataclass
class Emulator:
    """PCA per strain component + one GP per retained PC weight."""

    pcas: dict[str, StrainPCA]
    gps: GPBank
    lower: np.ndarray  # (7,) input box
    upper: np.ndarray
    xy: np.ndarray  # (n_cells, 2) skin-cell centroids [mm]
    volume: np.ndarray  # (n_cells,) [mm^3]
    provenance: EmulatorProvenance
    sklearn_gps: list | None = None  # StandardisedGP (or, when loaded from old files, normalize_y=True GPs)

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
    def pca_scaling(self) -> str:
        """The PCAs' per-cell scaling: "cell" (standardised, the paper's) or "none" (:mod:`surrogate.pca`)."""
        return next(iter(self.pcas.values())).scaling

    @property
    def param_bounds(self) -> np.ndarray:
        """(5, 2) the parameter box the emulator was trained on (theta in degrees)."""
        return np.stack([self.lower[:5], self.upper[:5]], 1)

    @property
    def input_span(self) -> np.ndarray:
        """(7,) the width the inputs are scaled by (:func:`unit_span` of the training box)."""
        return unit_span(self.lower, self.upper)

    # -- prediction ----------------------------------------------------------------------
    def scale(self, x):
        """Raw inputs (B, 7) -> unit box (numpy or torch)."""
        lower, span = self.lower, self.input_span
        if isinstance(x, torch.Tensor):
            lower = torch.as_tensor(lower, dtype=x.dtype, device=x.device)
            span = torch.as_tensor(span, dtype=x.dtype, device=x.device)
        return (x - lower) / span

    def predict_weights(self, x: torch.Tensor, return_var: bool = True, white_noise: bool = True):
        """PC weights at raw inputs x (B, 7) (torch, differentiable): mean (B, G)[, var (B, G)],
        the variance with the GPs' white-noise level unless ``white_noise`` is False."""
        return self.gps(self.scale(x), return_var=return_var, white_noise=white_noise)

    def predict_joint(self, x: torch.Tensor, white_noise: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """PC weights at raw inputs x (B, 7): mean (B, G) and each GP's joint covariance (G, B, B),
        with the GPs' white-noise level unless ``white_noise`` is False."""
        return self.gps.joint(self.scale(x), white_noise=white_noise)

    @property
    def white_noise_is_measurement(self) -> bool:
        """True when the training strains carry measurement noise (``training_noise``): the GPs'
        white-noise level is then that noise -- the weights of a noisy measurement vary by it
        about the GP's latent function -- and a likelihood that models the measurement's noise
        carries the GPs' latent covariance as the emulator's error, so as not to count the
        noise twice. Otherwise (simulated strains) it is the fields' roughness, an emulator error."""
        return self.provenance.training_noise is not None

    @property
    def held_out_excess(self) -> HeldOutExcess | None:
        """The GPs' cross-validated error beyond their own variance (None for older emulators)."""
        return self.provenance.held_out_excess

    def error_correlation(self, design_inputs: np.ndarray) -> np.ndarray:
        """(G, n, n) correlation of one material's emulator error between n observations with raw
        design inputs (alpha11 t, alpha22 t) (n, 2) (:func:`surrogate.error_model.design_correlation`)."""
        return design_correlation(self.gps, (np.asarray(design_inputs) - self.lower[5:]) / self.input_span[5:])

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
        return np.concatenate([self.pcas[c].transform(fields[..., k]) for k, c in enumerate(self.components)], 1)

    def dataset_fields(self, strain: np.ndarray) -> np.ndarray:
        """Select the modelled components from dataset strains (..., n_cells, 3)."""
        return strain[..., [COMPONENTS.index(c) for c in self.components]]

    # -- persistence ---------------------------------------------------------------------
    def save(self, directory: Path | str) -> Path:
        """Write the emulator directory (see the module docstring); returns it."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        arrays = {"xy": self.xy, "volume": self.volume}
        for c, pca in self.pcas.items():
            arrays.update(pca.to_arrays(f"{c}_"))
        np.savez(directory / "pca.npz", **arrays)
        np.savez(directory / "gp.npz", **self.gps.to_arrays())
        if self.sklearn_gps is not None:
            joblib.dump(self.sklearn_gps, directory / "sklearn_gps.joblib")
        self.save_meta(directory)
        return directory

    def save_meta(self, directory: Path) -> None:
        """(Re)write ``meta.json`` of an emulator directory (atomically; written last by :meth:`save`,
        so a directory with a ``meta.json`` is complete): format entries + provenance."""
        meta = {
            **self.provenance.to_json(),
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "inputs": list(INPUT_NAMES),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
            "components": list(self.components),
            "n_weights": self.n_weights,
        }
        write_text(directory / "meta.json", json.dumps(meta, indent=2) + "\n")

    @classmethod
    def load(cls, directory: Path | str, device: str = "cpu") -> Emulator:
        """Read an emulator directory.

        Raises:
            FileNotFoundError / ValueError: not an emulator directory, another format version,
                or a truncated or corrupt file.
        """
        directory = Path(directory)
        meta_path = directory / "meta.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"'{directory}' is not an emulator directory (no meta.json)")
        try:
            meta = json.loads(meta_path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"'{meta_path}' is not valid JSON ({exc}): {REFIT}") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise ValueError(f"'{directory}' is not a skinid emulator")
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"'{directory}' was written in emulator format {meta.get('format_version')} "
                f"(skinid {meta.get('versions', {}).get('skinid', '?')}); this skinid reads "
                f"format {FORMAT_VERSION}: refit it with 'skinid surrogate fit'"
            )
        try:
            provenance = EmulatorProvenance.from_json(meta)
            lower, upper, components = np.array(meta["lower"]), np.array(meta["upper"]), meta["components"]
        except KeyError as exc:
            raise ValueError(f"'{meta_path}' has no entry {exc}: {REFIT}") from exc
        pcas, xy, volume = _read_npz(
            directory / "pca.npz",
            lambda a: ({c: StrainPCA.from_arrays(a, f"{c}_") for c in components}, a["xy"], a["volume"]),
        )
        gps = _read_npz(directory / "gp.npz", GPBank).to(device)
        sk_path = directory / "sklearn_gps.joblib"
        try:
            sklearn_gps = joblib.load(sk_path) if sk_path.exists() else None
        except Exception as exc:  # a truncated or garbage pickle fails in many ways
            raise ValueError(f"'{sk_path}' cannot be read ({type(exc).__name__}: {exc}): {REFIT}") from exc
        return cls(
            pcas=pcas,
            gps=gps,
            lower=lower,
            upper=upper,
            xy=xy,
            volume=volume,
            provenance=provenance,
            sklearn_gps=sklearn_gps,
        )


def gp_rows(n_rows: int, gp_fraction: float, max_gp_rows: int | None, seed: int) -> np.ndarray:
    """Sorted indices of the seeded subset of ``n_rows`` training rows the GPs are fitted on:
    ``gp_fraction`` of them (at least 2), at most ``max_gp_rows``."""
    n_gp = max(2, int(round(gp_fraction * n_rows)))
    if max_gp_rows is not None:
        n_gp = min(n_gp, max_gp_rows)
    return np.sort(np.random.default_rng(seed).choice(n_rows, n_gp, replace=False))


def fold_refit(gps: list, seed: int = 0, n_jobs: int = 1) -> Callable[[np.ndarray, np.ndarray], GPBank]:
    """Fits a GP bank to unit-box inputs (n, 7) and targets (n, G) from the fitted kernels of
    ``gps``, without restarts: a cross-validation fold's GPs."""
    kernels = [g.gp.kernel_ for g in gps]
    return lambda x, y: GPBank.from_sklearn(fit_gps(x, y, restarts=0, seed=seed, n_jobs=n_jobs, kernels=kernels))


def _cross_validated_excess(
    gps: list,
    rows: TrainingRows,
    weights: np.ndarray,
    box: tuple[np.ndarray, np.ndarray],
    subset: np.ndarray,
    seed: int,
    n_jobs: int,
    folds: int,
):
    """The held-out excess of :func:`surrogate.error_model.cross_validated_excess` over ``folds``
    folds of materials, each fold's GPs refitted from the fitted kernels (``box``: the inputs'
    (lower, upper)); the material scale from each design's last frame."""
    lower, upper = box
    bank = GPBank.from_sklearn(gps)
    return cross_validated_excess(
        fold_refit(gps, seed, n_jobs),
        (rows.inputs - lower) / unit_span(lower, upper),
        weights,
        rows.index[:, 0],
        rows.inputs[:, 5:],
        subset,
        rows.index[:, 2] == rows.index[:, 2].max(),
        lambda design: design_correlation(bank, (design - lower[5:]) / unit_span(lower[5:], upper[5:])),
        folds,
        seed,
    )


def fit_emulator(
    data: StrainDataset,
    components: tuple[str, ...] = ("xx", "yy"),
    n_components: int | float = 0.99,
    pca_scaling: str = "cell",
    gp_fraction: float = 0.1,
    max_gp_rows: int | None = None,
    restarts: int = 2,
    seed: int = 0,
    n_jobs: int = -1,
    cv_folds: int = FOLDS,
) -> Emulator:
    """Fit PCA on every training row and the GPs on a seeded subset of them.

    Only the dataset's training materials (``split == 0``) are used.

    Args:
        pca_scaling: "cell" (per-cell standardisation, the paper's) or "none" (strain units:
            noise keeps its size in the weights; :mod:`surrogate.pca`).
        gp_fraction: share of the training rows the GPs are fitted on (paper: 0.1).
        max_gp_rows: cap on the number of GP rows (exact GP cost grows as rows^3).
        cv_folds: folds of training materials of the error model's cross-validation (as many
            as training materials: leave one material out).

    Longer than a screen: the fit's steps in order, then its provenance record field by field.
    """
    unknown = set(components) - set(COMPONENTS)
    if unknown or not components:
        raise ValueError(f"components must be among {COMPONENTS}, got {components}")
    if not 0 < gp_fraction <= 1:
        raise ValueError(f"gp_fraction must be in (0, 1], got {gp_fraction}")
    start = time.perf_counter()
    train = np.flatnonzero(data.split == 0)
    rows = TrainingRows.from_dataset(data, train)
    material_folds(rows.index[:, 0], cv_folds)  # too few materials for the folds: refused before the fit
    cols = [COMPONENTS.index(c) for c in components]
    pcas = {c: StrainPCA(n_components, pca_scaling).fit(rows.fields[..., k]) for c, k in zip(components, cols)}
    weights = np.concatenate([pcas[c].transform(rows.fields[..., k]) for c, k in zip(components, cols)], 1)

    lower = np.concatenate([data.lower, rows.inputs[:, 5:].min(0)])
    upper = np.concatenate([data.upper, rows.inputs[:, 5:].max(0)])
    subset = gp_rows(len(rows.index), gp_fraction, max_gp_rows, seed)
    x_unit = (rows.inputs[subset] - lower) / unit_span(lower, upper)
    pca_seconds = time.perf_counter() - start
    gps = fit_gps(x_unit, weights[subset], restarts=restarts, seed=seed, n_jobs=n_jobs)
    cv_start = time.perf_counter()
    excess = _cross_validated_excess(gps, rows, weights, (lower, upper), subset, seed, n_jobs, cv_folds)
    cv_seconds = time.perf_counter() - cv_start
    provenance = EmulatorProvenance(
        dataset=data.path.resolve(),
        dataset_config=data.config.to_toml(),
        mesh_sha256=data.mesh_sha256,
        block_half_length=data.config.mesh.length / 2,
        train_materials=tuple(train.tolist()),
        test_materials=tuple(np.flatnonzero(data.split == 1).tolist()),
        n_training_rows=int(len(rows.index)),
        n_gp_rows=len(subset),
        gp_fraction=gp_fraction,
        restarts=restarts,
        seed=seed,
        explained_variance_ratio={c: tuple(p.explained_variance_ratio_[:20].tolist()) for c, p in pcas.items()},
        fit_seconds={"pca": pca_seconds, "held_out_excess": cv_seconds, "total": time.perf_counter() - start},
        versions={n: metadata.version(n) for n in ("skinid", "scikit-learn", "torch", "numpy")},
        held_out_excess=excess,
        training_noise=data.added_noise,
    )
    emulator = Emulator(
        pcas=pcas,
        gps=GPBank.from_sklearn(gps),
        lower=lower,
        upper=upper,
        xy=data.xy,
        volume=data.volume,
        provenance=provenance,
        sklearn_gps=gps,
    )
    return emulator
