"""The demo: the built-in small case end to end, resumable (a second run reuses finished work).

    python scripts/demo.py [--out out/demo]

mesh -> sweep (80 FE simulations) -> PCA + GP emulator + validation -> posterior of a
held-out material from the "mixed" design -> report.md with the figures.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BIN = Path(sys.executable).parent


def step(title: str) -> None:
    print(f"\n== {title}", flush=True)


def run(*args: str) -> None:
    subprocess.run([str(BIN / "skinid"), *args], check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"))
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    data, emu, post = out / "small.h5", out / "emulator", out / "posterior"
    mpirun = BIN / "mpirun"

    step("1/4 sweep: 16 materials x 5 membrane designs x 10 frames (small preset)")
    cmd = ["sweep", "--config", "small", "--out", str(data)] + (["--resume"] if data.exists() else [])
    if mpirun.exists():
        subprocess.run([str(mpirun), "-n", "2", str(BIN / "skinid"), *cmd], check=True)
    else:
        run(*cmd)

    step("2/4 surrogate: PCA + GPs, validated on the 4 held-out materials")
    if not (emu / "validation.json").exists():
        run("surrogate", "fit", "--data", str(data), "--out", str(emu), "--gp-fraction", "0.5")

    from inference.plots import strain_maps
    from skinfem.io import StrainDataset
    from surrogate.emulator import Emulator

    dataset, emulator = StrainDataset.open(data), Emulator.load(emu)
    material = int(np.flatnonzero(dataset.split)[0])
    mixed = int(np.flatnonzero(np.all(np.isclose(dataset.designs, [0.05, -0.05]), axis=1))[0])

    step(f"3/4 posterior of held-out material {material} from the mixed design (0.05, -0.05)")
    if not (post / "summary.json").exists():
        run("infer", "--emulator", str(emu), "--data", str(data), "--material", str(material),
            "--designs", str(mixed), "--out", str(post), "--gp-variance", "mode")
    summary = json.loads((post / "summary.json").read_text())

    step("4/4 report")
    truth = dataset.params[material]
    fe = dataset.strain(material, mixed, -1)
    median = np.array([summary["parameters"][n]["median"] for n in ("mu", "k1", "k2", "kappa", "theta")])
    pred = emulator.predict_fields(median[None], dataset.designs[mixed], 1.0)[0]
    strain_maps(dataset.xy, [fe[:, 0], fe[:, 1], pred[:, 0] - fe[:, 0], pred[:, 1] - fe[:, 1]],
                ["FE E_xx", "FE E_yy", "E_xx: emulator − FE", "E_yy: emulator − FE"],
                out / "strain_maps.png", theta_deg=float(truth[4]),
                suptitle=f"material {material}, design (0.05, −0.05), t = 1")
    rows = "\n".join(
        f"| {n} | {e['true']:.4g} | {e['median']:.4g} | [{e['q2.5']:.4g}, {e['q97.5']:.4g}] | "
        f"{'yes' if e['covered'] else 'no'} | {e['r_hat']:.3f} | {min(e['ess_bulk'], e['ess_tail']):.0f} |"
        for n, e in summary["parameters"].items() if "true" in e
    )
    val = json.loads((emu / "validation.json").read_text())["components"]
    report = f"""# skinid demo (small preset)

Dataset `{data.name}`: 16 materials × 5 designs × 10 frames, {dataset.xy.shape[0]} skin cells.
Emulator: {emulator.n_weights} PCs, GP R² on held-out materials:
E_xx {', '.join(f'{v:.4f}' for v in val['xx']['r2_per_pc'])};
E_yy {', '.join(f'{v:.4f}' for v in val['yy']['r2_per_pc'])}.

![strain maps](strain_maps.png)

## Posterior of held-out material {material} (design (0.05, −0.05), last frame)

| parameter | true | median | 95 % interval | covered | R-hat | ESS |
|---|---|---|---|---|---|---|
{rows}

![corner](posterior/corner.png)

![emulator validation](emulator/validation.png)

Model criticism is not part of the demo yet.
"""
    (out / "report.md").write_text(report)
    print(f"\ndemo finished in {time.perf_counter() - start:.0f} s; report: {out / 'report.md'}")


if __name__ == "__main__":
    main()
