"""The demo: the built-in small case end to end, resumable (a second run reuses finished work).

    python scripts/demo.py [--out out/demo]

mesh -> sweep (80 FE simulations) -> PCA + GP emulator + validation -> posterior of a
held-out material from the "mixed" design -> model criticism of synthetic measurements of that
material with a hidden skin pre-stretch -> report.md with the figures.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from inference.posterior_file import PosteriorSummary
from surrogate.validation import ValidationReport

if TYPE_CHECKING:
    from inference.criticism.report_file import ReportFile

BIN = Path(sys.executable).parent


def step(title: str) -> None:
    print(f"\n== {title}", flush=True)


def run(*args: str) -> None:
    subprocess.run([str(BIN / "skinid"), *args], check=True)


def overview(out: Path, top: Path, bottom: list[Path]) -> Path:
    """One figure of the demo for the README: strain maps on top; where the model fails and the
    error falling below. The figures are placed at their own pixel size (no rescaling), so their
    fonts, drawn at the same size and dpi, stay the same size in the montage."""
    from inference.plots import pyplot

    plt = pyplot()
    top_image, *images = (_rgb(plt.imread(p)) for p in (top, *bottom))
    row = _pad_stack(images, axis=1)
    plt.imsave(out / "overview.png", _pad_stack([top_image, row], axis=0))
    return out / "overview.png"


def _rgb(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) floats in [0, 1] of a PNG read by matplotlib (alpha dropped)."""
    return image[..., :3].astype(float)


def _pad_stack(images: list[np.ndarray], axis: int) -> np.ndarray:
    """Images side by side (axis 1) or one above the other (axis 0), centred and padded with
    white to a common height (width)."""
    across = 1 - axis
    size = max(im.shape[across] for im in images)
    padded = []
    for im in images:
        before = (size - im.shape[across]) // 2
        pad = [(0, 0)] * 3
        pad[across] = (before, size - im.shape[across] - before)
        padded.append(np.pad(im, pad, constant_values=1.0))
    return np.concatenate(padded, axis=axis)


def run_parallel(*args: str) -> None:
    """``skinid`` on 2 MPI ranks when mpirun is installed, else serial."""
    mpirun = BIN / "mpirun"
    if mpirun.exists():
        subprocess.run([str(mpirun), "-n", "2", str(BIN / "skinid"), *args], check=True)
    else:
        run(*args)


def hidden_prestretch_check(out: Path, emu: Path, truth: np.ndarray) -> ReportFile:
    """Synthetic measurements of material ``truth`` with a hidden pre-stretch, and their check
    (resumed if a killed run left FE runs); returns its report.json."""
    from inference.criticism import NoiseModel
    from inference.criticism.report_file import read_report
    from inference.synthetic import synthetic_measurements
    from skinfem.config import load_config
    from skinfem.effects import prestretch_log_strain
    from skinfem.params import SkinParams

    check = out / "check"
    if not (check / "report.json").exists():
        hidden = {f"pre_stretch.{k}": v for k, v in prestretch_log_strain(1.08, 1.02, 30.0).items()}
        files = synthetic_measurements(
            load_config("small"),
            SkinParams.from_array(truth),
            [(0.05, 0.05), (0.05, -0.05)],
            NoiseModel(np.full(3, 2e-4), 2.0, 0.3),
            out / "measurements",
            hidden,
            seed=1,
            increments=2,
        )
        cmd = [
            "check",
            "--emulator",
            str(emu),
            "--measurement",
            *map(str, files),
            "--out",
            str(check),
            "--noise-length",
            "2",
            "--noise-nugget",
            "0.3",
            "--add",
            "pre_stretch",
            "--increments",
            "2",
            "--spacing",
            "2",
            "--no-discretisation",
        ]  # data from the checked mesh: its model is exact
        run_parallel(*cmd, *(["--resume"] if check.exists() else []))  # a killed check: reuse its FE runs
    try:
        return read_report(check / "report.json")
    except ValueError as exc:  # a check left by an older version
        raise SystemExit(f"demo: {exc} (remove {check} to rerun it)") from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"))
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    data, emu, post = out / "small.h5", out / "emulator", out / "posterior"

    step("1/5 sweep: 16 materials x 5 membrane designs x 10 frames (small preset)")
    run_parallel("sweep", "--config", "small", "--out", str(data), *(["--resume"] if data.exists() else []))

    step("2/5 surrogate: PCA + GPs, validated on the 4 held-out materials")
    if not (emu / "validation.json").exists():  # --force: replace an incomplete folder of an earlier run
        run("surrogate", "fit", "--data", str(data), "--out", str(emu), "--gp-fraction", "0.5", "--force")

    from skinfem.io import StrainDataset, design_index
    from surrogate.emulator import Emulator

    dataset, emulator = StrainDataset.open(data), Emulator.load(emu)
    material = int(np.flatnonzero(dataset.split)[0])
    mixed = design_index(dataset.designs, (0.05, -0.05), dataset.path)

    step(f"3/5 posterior of held-out material {material} from the mixed design (0.05, -0.05)")
    if not (post / "summary.json").exists():
        run(
            "infer",
            "--emulator",
            str(emu),
            "--data",
            str(data),
            "--material",
            str(material),
            "--designs",
            str(mixed),
            "--out",
            str(post),
            "--gp-variance",
            "mode",
            "--force",
        )
    summary = PosteriorSummary.load(post / "summary.json")

    step(f"4/5 model criticism: material {material} with a hidden pre-stretch 1.08 x 1.02 at 30 deg")
    criticism = hidden_prestretch_check(out, emu, dataset.params[material])

    step("5/5 report")
    write_report(out, dataset, emulator, material, mixed, summary, criticism)
    print(f"\ndemo finished in {time.perf_counter() - start:.0f} s; report: {out / 'report.md'}")


def write_report(
    out: Path, dataset, emulator, material: int, mixed: int, summary: PosteriorSummary, criticism: ReportFile
) -> None:
    """report.md with the strain maps, the posterior table and the criticism's verdict, and the
    README's overview figure."""
    from inference.plots import strain_maps

    truth = dataset.params[material]
    fe = dataset.strain(material, mixed, -1)
    median = np.array([summary.parameters[n].median for n in ("mu", "k1", "k2", "kappa", "theta")])
    pred = emulator.predict_fields(median[None], dataset.designs[mixed], 1.0)[0]
    strain_maps(
        dataset.xy,
        [fe[:, 0], fe[:, 1], pred[:, 0] - fe[:, 0], pred[:, 1] - fe[:, 1]],
        ["FE E_xx", "FE E_yy", "E_xx: emulator − FE", "E_yy: emulator − FE"],
        out / "strain_maps.png",
        theta_deg=float(truth[4]),
        suptitle=f"material {material}, design (0.05, −0.05), t = 1",
    )
    rows = "\n".join(
        f"| {n} | {e.true:.4g} | {e.median:.4g} | [{e.q2_5:.4g}, {e.q97_5:.4g}] | "
        f"{'yes' if e.covered else 'no'} | {e.r_hat:.3f} | {e.ess:.0f} |"
        for n, e in summary.parameters.items()
        if e.true is not None
    )
    val = ValidationReport.load(out / "emulator" / "validation.json").components
    versions = "\n".join(
        f"| {v.label} | {v.metrics.rmse:.2e} | {v.metrics.chi2_per_dof:.2f} | "
        f"{v.metrics.ppc_p:.3f} | {'no' if v.metrics.structured else 'yes'} |"
        for v in criticism.versions
    )
    (out / "report.md").write_text(
        REPORT.format(
            data=dataset.path.name,
            cells=dataset.xy.shape[0],
            n_weights=emulator.n_weights,
            r2_xx=", ".join(f"{v:.4f}" for v in val["xx"].r2_per_pc),
            r2_yy=", ".join(f"{v:.4f}" for v in val["yy"].r2_per_pc),
            material=material,
            rows=rows,
            verdict=criticism.diagnosis.verdict,
            versions=versions,
        )
    )
    check = out / "check"
    overview(out, out / "strain_maps.png", [check / "regions.png", check / "error_falls.png"])


REPORT = """# skinid demo (small preset)

Dataset `{data}`: 16 materials × 5 designs × 10 frames, {cells} skin cells.
Emulator: {n_weights} PCs, GP R² on held-out materials:
E_xx {r2_xx};
E_yy {r2_yy}.

![strain maps](strain_maps.png)

## Posterior of held-out material {material} (design (0.05, −0.05), last frame)

| parameter | true | median | 95 % interval | covered | R-hat | ESS |
|---|---|---|---|---|---|---|
{rows}

![corner](posterior/corner.png)

![emulator validation](emulator/validation.png)

## Model criticism: measurements with a hidden skin pre-stretch

Synthetic DIC measurements of material {material} under two membranes, made with a skin
pre-stretch of 1.08 × 1.02 at 30° that the baseline model does not have, plus correlated noise
(sd 2e-4, 2 mm). Full report: [check/report.md](check/report.md).

> {verdict}

| version | RMSE | χ²/dof | PPC p | consistent with noise |
|---|---|---|---|---|
{versions}

![error falls](check/error_falls.png)

![where the baseline fails](check/regions.png)

![baseline residual](check/residual_baseline_obs1.png)
"""


if __name__ == "__main__":
    main()
