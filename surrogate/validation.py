"""Validation of an emulator on held-out materials (the dataset's test split).

Every converged (design, frame) of every test material is one validation row. Reported:
R^2 of each retained PC weight, and the field error of the emulator in strain units -- both
against the simulated field and against its own PCA reconstruction (the PCA floor), so one
can see whether the PCA truncation or the GPs dominate.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from skinfem.io import StrainDataset
from skinfem.outputs import save_figure, write_text
from surrogate.emulator import Emulator, HeldOutScores, TrainingRows


def r2_score(true: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Coefficient of determination per column of (n, k) arrays."""
    ss_res = np.sum((true - pred) ** 2, axis=0)
    ss_tot = np.sum((true - true.mean(0)) ** 2, axis=0)
    return 1.0 - ss_res / ss_tot


@dataclass(frozen=True)
class ComponentValidation:
    """Scores of one strain component on the held-out rows (fields in strain units)."""

    r2_per_pc: tuple[float, ...]  # R^2 of each retained PC weight [-]
    min_r2: float  # the smallest of them [-]
    field_rmse: float  # RMS error of the emulated field [-]
    field_rmse_relative: float  # field_rmse over the RMS simulated strain [-]
    pca_floor_rmse: float  # RMS error of the PCA reconstruction of the simulated field (the floor) [-]
    field_max_abs_error: float  # largest |emulated - simulated| over cells and rows [-]
    field_rms: float  # RMS simulated strain [-]
    weight_z_rms: tuple[float, ...]  # per PC weight: RMS of (true - mean) / GP sd (1: calibrated) [-]

    def held_out_scores(self) -> HeldOutScores:
        """What ``meta.json`` records of these scores."""
        return HeldOutScores(
            min_r2=self.min_r2, field_rmse=self.field_rmse, field_rmse_relative=self.field_rmse_relative
        )

    def to_json(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_json(cls, entry: dict) -> ComponentValidation:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in entry.items()})


@dataclass(frozen=True)
class ValidationReport:
    """What ``validation.json`` holds: the held-out materials, their rows and the scores per component."""

    test_materials: tuple[int, ...]  # material indices of the dataset's test split
    n_rows: int  # converged (material, design, frame) rows validated on
    components: dict[str, ComponentValidation]  # by strain component: xx, yy[, xy]

    def to_json(self) -> dict:
        """The content of ``validation.json``."""
        return {
            "test_materials": list(self.test_materials),
            "n_rows": self.n_rows,
            "components": {c: r.to_json() for c, r in self.components.items()},
        }

    @classmethod
    def from_json(cls, report: dict) -> ValidationReport:
        return cls(
            tuple(report["test_materials"]),
            report["n_rows"],
            {c: ComponentValidation.from_json(r) for c, r in report["components"].items()},
        )

    @classmethod
    def load(cls, path: Path | str) -> ValidationReport:
        """Read a ``validation.json``."""
        return cls.from_json(json.loads(Path(path).read_text()))

    def write(self, path: Path | str) -> Path:
        """Write ``validation.json`` (2-space indented JSON, a final newline)."""
        return write_text(path, json.dumps(self.to_json(), indent=2) + "\n")


@dataclass(frozen=True)
class ValidationArrays:
    """PC weights of the validation rows (n_rows, G), for plots."""

    true: np.ndarray  # projections of the simulated fields
    pred: np.ndarray  # the emulator's mean
    sd: np.ndarray  # the emulator's sd
    index: np.ndarray  # (n_rows, 3) material, design, frame of each row


def validate(emulator: Emulator, data: StrainDataset) -> tuple[ValidationReport, ValidationArrays]:
    """Scores on the test materials of ``data``.

    Returns:
        (report, arrays): the report (``validation.json``) and the true/predicted weights for plots.
    """
    if data.mesh_sha256 != emulator.provenance.mesh_sha256:
        raise ValueError(f"'{data.path}' was simulated on another mesh than the emulator's data")
    test = np.flatnonzero(data.split == 1)
    if len(test) == 0:
        raise ValueError(f"'{data.path}' has no test materials (sweep.n_test = 0)")
    rows = TrainingRows.from_dataset(data, test)
    fields = emulator.dataset_fields(rows.fields)
    true_w = emulator.weights_of_fields(fields)
    with torch.no_grad():
        mean, var = emulator.predict_weights(torch.as_tensor(rows.inputs))
    pred_w, pred_var = mean.numpy(), var.numpy()
    pred_fields = emulator.fields_of_weights(pred_w)
    floor_fields = emulator.fields_of_weights(true_w)
    r2 = r2_score(true_w, pred_w)
    z = (true_w - pred_w) / np.sqrt(pred_var)
    components = {}
    for k, (c, sl) in enumerate(emulator.weight_slices().items()):
        err = pred_fields[..., k] - fields[..., k]
        floor = floor_fields[..., k] - fields[..., k]
        rms = float(np.sqrt(np.mean(fields[..., k] ** 2)))
        components[c] = ComponentValidation(
            r2_per_pc=tuple(r2[sl].tolist()),
            min_r2=float(r2[sl].min()),
            field_rmse=float(np.sqrt(np.mean(err**2))),
            field_rmse_relative=float(np.sqrt(np.mean(err**2)) / rms),
            pca_floor_rmse=float(np.sqrt(np.mean(floor**2))),
            field_max_abs_error=float(np.abs(err).max()),
            field_rms=rms,
            weight_z_rms=tuple(np.sqrt(np.mean(z[:, sl] ** 2, axis=0)).tolist()),
        )
    report = ValidationReport(tuple(test.tolist()), int(len(rows.index)), components)
    return report, ValidationArrays(true_w, pred_w, np.sqrt(pred_var), rows.index)


def plot_predicted_vs_true(emulator: Emulator, arrays: ValidationArrays, path: Path | str) -> Path:
    """The paper's Fig. 5: predicted vs simulated PC weight, one panel per PC and component."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    slices = emulator.weight_slices()
    n_cols = max(emulator.n_weights.values())
    fig, axes = plt.subplots(len(slices), n_cols, figsize=(2.3 * n_cols, 2.4 * len(slices)), squeeze=False)
    for r, (c, sl) in enumerate(slices.items()):
        for j in range(n_cols):
            ax = axes[r, j]
            if j >= sl.stop - sl.start:
                ax.axis("off")
                continue
            g = sl.start + j
            t, p = arrays.true[:, g], arrays.pred[:, g]
            ax.scatter(t, p, s=3, alpha=0.5, color="C0")
            lim = [min(t.min(), p.min()), max(t.max(), p.max())]
            ax.plot(lim, lim, color="k", lw=0.8)
            ax.set_title(f"E_{c} PC{j + 1}  R²={r2_score(t[:, None], p[:, None])[0]:.3f}", fontsize=9)
            ax.tick_params(labelsize=7)
            if j == 0:
                ax.set_ylabel("emulator weight [-]", fontsize=8)
            if r == len(slices) - 1:
                ax.set_xlabel("simulated weight [-]", fontsize=8)
    fig.suptitle("PC weights of held-out materials: emulator vs finite elements", fontsize=10)
    return save_figure(fig, path, dpi=130)


def plot_explained_variance(emulator: Emulator, path: Path | str, n_max: int = 20) -> Path:
    """Cumulative explained variance of the training PCA per component (the paper's Fig. 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    styles = [("C0", "-", "o"), ("C1", "--", "s"), ("C2", ":", "^"), ("C3", "-.", "D")]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    offsets = np.linspace(-0.15, 0.15, len(emulator.pcas)) if len(emulator.pcas) > 1 else np.zeros(1)
    for (c, pca), (colour, ls, marker), dx in zip(emulator.pcas.items(), styles * len(emulator.pcas), offsets):
        ratio = np.cumsum(pca.explained_variance_ratio_)[:n_max]
        ax.plot(
            np.arange(1, len(ratio) + 1) + dx,
            ratio,
            color=colour,
            ls=ls,
            marker=marker,
            ms=4,
            lw=1.4,
            label=f"E_{c} (M = {pca.n_components_})",
        )
    ax.axhline(0.99, color="k", lw=0.8, ls="--", label="99 %")
    ax.set_xlabel("number of principal components M")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("cumulative explained variance [-]")
    ax.set_ylim(top=1.005)
    ax.legend(fontsize=8, loc="lower right", title="strain component", title_fontsize=8)
    ax.grid(alpha=0.3)
    return save_figure(fig, path, dpi=130)


def held_out_scores(report: ValidationReport) -> dict[str, HeldOutScores]:
    """The per-component scores of a :func:`validate` report that ``meta.json`` records."""
    return {c: r.held_out_scores() for c, r in report.components.items()}


def validate_directory(directory: Path | str, data_path: Path | str | None = None) -> ValidationReport:
    """Validate a saved emulator: ``validation.json`` + ``validation.png`` into it, scores into ``meta.json``."""
    directory = Path(directory)
    emulator = Emulator.load(directory)
    data = StrainDataset.open(data_path or emulator.provenance.dataset)
    report, arrays = validate(emulator, data)
    report.write(directory / "validation.json")
    plot_predicted_vs_true(emulator, arrays, directory / "validation.png")
    emulator.provenance = emulator.provenance.validated(held_out_scores(report))
    emulator.save_meta(directory)
    return report
