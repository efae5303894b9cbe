"""What the check's mesh correction leaves of the mesh's error, and whether two meshes foresee it.

    python benchmarks/remaining_mesh_error.py [--check out/crit_drift/none_0] [--data-dir out/crit_drift]
                                              [--case none] [--levels 2 1] [--out out/remaining_mesh_error]
                                              [--results FILE]

(one rank; the check is read from its kept FE runs and makes none; each extra data mesh of
``--levels`` is one FE run per design, kept in ``--out``)

A check of ``benchmarks/criticism.py`` (``--check``: its folder ``<case>_<seed>``, made with
``--data q2-limit --refine edge --mesh-drift``) corrects its model by a fitted multiple of its
two-mesh shift and carries the rest as a correlated Gaussian field. Its data are the Richardson
limit L of two meshes of one family (Q2, far 4 mm, four muscle and two skin layers) whose
membrane-edge cells are 0.5 and 0.25 mm. At the truth x_t the noise-free remainder
L - model(x_cal) splits into

- L - D_0.5: the data family's error at 0.5 mm edge cells, the size of the check's refined mesh;
- D_0.5 - R(x_t): the data family against the check's refined mesh (far cells 4 against 6 mm,
  muscle layers), R linearised from the baseline x0 by its exact Jacobian (C's and the drift);
- R(x_t) - model(x_cal): what the corrected model misses of its own refined mesh.

Each part is whitened as the check whitens (noise and carried error), taken beyond the span of
the calibrated parameters' Jacobian (skin and correction amplitude), and scored along every
candidate's signature as the check's score test does (its chi^2 statistic, 1 dof per
parameter), beside the mean of the same scores over draws of the carried Gaussian field (what
the check's model of its remaining error expects along each candidate). Then the data family's
successive edge steps 2 -> 1 -> 0.5 -> 0.25 mm at x_t (the first two computed here): their
candidate shares beyond the skin, their cosines, and whether the last step (the shape of
L - D_0.5) lies in the span of the two before it, as it would if the error had two modes of
different orders. Recorded, not asserted.
"""

from __future__ import annotations

import argparse
import json
import sys
from argparse import Namespace
from pathlib import Path

import numpy as np
from mpi4py import MPI

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


class _Captured(BaseException):
    """Ends the check once its diagnosis inputs are known (not an error: BaseException passes
    the CLI's one-line error handling)."""


def diagnosis_inputs(folder: Path, mesh_dir: Path) -> dict:
    """The check's corrected model, baseline calibration, data and candidates as its diagnosis
    receives them: the check of ``folder`` run again from its kept FE runs, stopped there."""
    import criticism as bench

    import inference.criticism.check as check
    from inference.__main__ import main as skinid

    captured = {}
    diagnose = check.diagnose

    def capture(model, cal, data, candidates, *args, **kwargs):
        captured.update(model=model, cal=cal, data=data, candidates=candidates)
        raise _Captured

    options = Namespace(config="check", start="centre", mesh_dir=mesh_dir, refine="edge", confirm=1, mesh_drift=True)
    check.diagnose = capture
    try:
        skinid(bench.check_argv(sorted((folder / "m").glob("m_*.csv")), folder, [], options))
    except _Captured:
        pass
    finally:
        check.diagnose = diagnose
    if not captured:
        raise SystemExit(f"{folder} holds no check that reaches its diagnosis")
    return captured


def at_points(fields: np.ndarray, points: np.ndarray, xy: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(n_obs, n_pts, 3) fields given at ``points`` (m, 2) [mm], taken at the check's points
    ``xy`` (n_obs, n_pts, 2) (a subset of them; zero off ``masks``)."""
    out = np.zeros((*masks.shape, 3))
    for o, mask in enumerate(masks):
        distance = np.linalg.norm(points[None] - xy[o, mask][:, None], axis=2)
        if distance.min(1).max() > 1e-6:
            raise SystemExit("the check's points are not the data's points")
        out[o, mask] = fields[o, distance.argmin(1)]
    return out


def scored(field: np.ndarray, inputs: dict, signatures: dict) -> dict:
    """Whitened squared norm of ``field`` [chi^2 units], its part beyond the calibrated
    parameters, and each candidate's score statistic on it, with the candidate's parameters
    fitted to it (linearised, beyond what the calibrated ones absorb)."""
    from inference.criticism.diagnosis import fit_beyond

    data, cal = inputs["data"], inputs["cal"]
    w = data.whiten(np.where(data.masks[..., None], field, 0.0))
    q, _ = np.linalg.qr(cal.jac)
    beyond = w - q @ (q.T @ w)
    row = {"chi2": float(w @ w), "beyond_calibrated": float(beyond @ beyond)}
    for name, S in signatures.items():
        estimate, fitted = fit_beyond(q, S, w)
        row[name] = float(fitted @ fitted)
        row[f"{name}_estimate"] = estimate.tolist()  # the linearised fit of its parameters to ``field``
    return row


def carried_expectation(inputs: dict, signatures: dict, draws: int = 200, seed: int = 0) -> dict:
    """Mean of :func:`scored` over ``draws`` fields of the carried model error alone."""
    data = inputs["data"]
    rng = np.random.default_rng(seed)
    fields = np.zeros((draws, *data.fields.shape))
    for o, mask in enumerate(data.masks):
        fields[:, o, mask] = data.model_error.sample(data.xy[o, mask], o, mask, (draws,), rng)
    rows = [scored(field, inputs, signatures) for field in fields]
    return {key: float(np.mean([row[key] for row in rows])) for key in rows[0] if not key.endswith("_estimate")}


def refined_at_truth(model, x_true: np.ndarray) -> np.ndarray:
    """The check's refined mesh at ``x_true``, linearised from the shift's point: C(x0) + s0 +
    (J_C + drift)(x_true - x0), every term from the check's kept runs."""
    ((c0, jacobian),) = model.base.evaluate_with_jacobian([model.at], model.base.names)
    return c0 + model.shift + (jacobian + model.drift) @ (x_true - model.at)


def remainder_parts(inputs: dict, signatures: dict, data: dict[float, np.ndarray], x_true: np.ndarray) -> dict:
    """The noise-free remainder and its three parts (module doc), each scored."""
    import criticism as bench

    model, corrected = inputs["model"], inputs["cal"].model_fields
    limit = bench.extrapolated(data[0.5], data[0.25])
    refined = refined_at_truth(model, x_true)
    parts = {
        "noise-free remainder: L - corrected model": limit - corrected,
        "L - D_0.5 (the data family's error at 0.5 mm edge cells)": limit - data[0.5],
        "D_0.5 - R(x_t) (data family against the check's refined mesh, linearised)": data[0.5] - refined,
        "R(x_t) - corrected model": refined - corrected,
    }
    return {label: scored(field, inputs, signatures) for label, field in parts.items()}


def edge_steps(inputs: dict, signatures: dict, data: dict[float, np.ndarray]) -> dict:
    """The data family's successive edge steps at the truth: each scored with the candidates'
    shares of its part beyond the calibrated parameters, consecutive cosines there, and the last
    step and the remainder L - D_0.5 fitted by the steps before them."""
    import criticism as bench

    cal, data_model = inputs["cal"], inputs["data"]
    q, _ = np.linalg.qr(cal.jac)

    def beyond(field):
        w = data_model.whiten(np.where(data_model.masks[..., None], field, 0.0))
        return w - q @ (q.T @ w)

    sizes = sorted(data, reverse=True)
    steps = {f"{a:g} -> {b:g} mm": data[b] - data[a] for a, b in zip(sizes, sizes[1:])}
    vectors = {label: beyond(step) for label, step in steps.items()}
    out = {"steps": {}, "cosines": {}, "fitted_by_coarser_steps": {}}
    for label, step in steps.items():
        row = scored(step, inputs, signatures)
        out["steps"][label] = {**row, **{f"{n}_share": row[n] / row["beyond_calibrated"] for n in signatures}}
    labels = list(vectors)
    for a, b in zip(labels, labels[1:]):
        out["cosines"][f"{a} | {b}"] = float(
            vectors[a] @ vectors[b] / np.linalg.norm(vectors[a]) / np.linalg.norm(vectors[b])
        )
    targets = {
        labels[-1]: vectors[labels[-1]],
        "L - D_0.5": beyond(bench.extrapolated(data[0.5], data[0.25]) - data[0.5]),
    }
    for k in (1, 2):
        basis = np.stack([vectors[label] for label in labels[-1 - k : -1]], 1)
        for name, target in targets.items():
            coefficients, *_ = np.linalg.lstsq(basis, target, rcond=None)
            left = target - basis @ coefficients
            out["fitted_by_coarser_steps"][f"{name} by {', '.join(labels[-1 - k : -1])}"] = {
                "beyond_calibrated": float(target @ target),
                "left": float(left @ left),
                "coefficients": coefficients.tolist(),
            }
    return out


def data_family(h_edge: float, case: str, points: np.ndarray, args) -> np.ndarray:
    """Noise-free data of ``case`` on the limit pair's mesh family with ``h_edge`` [mm] edge
    cells (kept in ``args.out``), or the pair's own kept fields."""
    import criticism as bench

    pair = {0.5: "q2-fine-coarser", 0.25: "q2-fine"}
    if h_edge in pair:
        return np.load(bench.kept_data_path(args.data_dir, pair[h_edge], case))
    config = bench.data_config("q2-fine-coarser").with_changes(mesh={"h_edge": h_edge})
    path = args.out / f"data_edge{h_edge:g}_{case}.npy"
    return bench.data_fields(config, case, points, args.mesh_dir, MPI.COMM_WORLD, path)


def main() -> None:
    import criticism as bench

    import skinfem.model  # noqa: F401  (PETSc first)
    from inference.criticism.diagnosis import signatures
    from inference.synthetic import dic_points

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", type=Path, default=Path("out/crit_drift/none_0"))
    parser.add_argument("--data-dir", type=Path, default=Path("out/crit_drift"))
    parser.add_argument("--case", default="none", choices=list(bench.hidden_effects()))
    parser.add_argument("--levels", type=float, nargs="+", default=[2.0, 1.0], help="extra edge cell sizes [mm]")
    parser.add_argument("--out", type=Path, default=Path("out/remaining_mesh_error"))
    parser.add_argument("--mesh-dir", type=Path, default=Path("meshes"))
    parser.add_argument("--results", type=Path, default=HERE / "results" / "remaining_mesh_error.json")
    args = parser.parse_args()
    points = dic_points(18.0, 1.0, np.random.default_rng(0))  # the criticism benchmark's cloud
    fields = {h: data_family(h, args.case, points, args) for h in [*args.levels, 0.5, 0.25]}
    inputs = diagnosis_inputs(args.check, args.mesh_dir)
    data, model = inputs["data"], inputs["model"]
    fields = {h: at_points(f, points, data.xy, data.masks) for h, f in fields.items()}
    sigs = signatures(model, inputs["cal"], data, inputs["candidates"])
    x_true = model.base.null.copy()
    x_true[:5] = bench.TRUTH
    for name, value in bench.hidden_effects()[args.case].items():
        x_true[model.base.names.index(name)] = value
    residual = data.fields - inputs["cal"].model_fields
    result = {
        "command": f"python benchmarks/remaining_mesh_error.py --check {args.check} --case {args.case} "
        f"--levels {' '.join(f'{h:g}' for h in args.levels)}",
        "n_data": data.n,
        "correction_amplitude": float(inputs["cal"].x[-1]),
        "measured_residual": scored(np.where(data.masks[..., None], residual, 0.0), inputs, sigs),
        "carried_error_expected": carried_expectation(inputs, sigs),
        "remainder_parts": remainder_parts(inputs, sigs, fields, x_true),
        "edge_steps": edge_steps(inputs, sigs, fields),
    }
    args.results.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
