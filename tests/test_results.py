"""Typed results (no FE): the posterior summary (``summary.json``) and the surrogate's validation
report (``validation.json``) are dataclasses whose JSON is the files' unchanged format; their
consumers (the ``skinid infer`` / ``surrogate`` printouts, the test-set study, the accuracy plot)
read attributes. Also: the sampler silences only the floating-point warnings of the closed-form
density, and parallel chains leave no multiprocessing warning at exit and equal the serial ones.
"""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from dataclasses import asdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from inference.model import ErrorBudget, GpVarianceSpread
from inference.posterior_file import (
    ESS_LIMIT,
    RHAT_LIMIT,
    ParameterSummary,
    PosteriorSamples,
    PosteriorSummary,
    write_outputs,
)
from inference.sampling import quiet_overflow
from surrogate.validation import ComponentValidation, ValidationReport

ROOT = Path(__file__).resolve().parents[1]
BOUNDS = np.array([[0.000543, 0.00206], [0.0117, 0.0225], [8.31, 15.32], [0.27, 0.30], [0.0, 90.0]])
NAMES = ("mu", "k1", "k2", "kappa", "theta", "sigma_xx", "sigma_yy")


def skin_entry(median, lo, hi, r_hat, bulk, tail, k, true):
    return {
        "median": median,
        "q2.5": lo,
        "q97.5": hi,
        "r_hat": r_hat,
        "ess_bulk": bulk,
        "ess_tail": tail,
        "prior": BOUNDS[k].tolist(),
        "interval_share_of_prior": (hi - lo) / float(np.ptp(BOUNDS[k])),
        "true": true,
        "covered": lo <= true <= hi,
    }


# summary.json of a held-out small-mesh material (benchmarks/results/small_heldout_posterior_summary.json)
# with what later versions added: acceptance rates, the error budget and its statement, a model warning
SUMMARY_JSON = {
    "parameters": {
        "mu": skin_entry(
            0.0009140805727651988,
            0.0007404027526394722,
            0.001019260437174447,
            1.001468358514202,
            990.3842219365407,
            1026.9717413509036,
            0,
            0.000977387273495196,
        ),
        "k1": skin_entry(
            0.014539057007493039,
            0.011848835580904339,
            0.021086010433808033,
            1.002417753157047,
            781.0649902514588,
            680.913479669173,
            1,
            0.013164124960430403,
        ),
        "k2": skin_entry(
            11.331147427655342,
            8.472589365502673,
            15.040205069214458,
            1.0017090837307547,
            2648.3332313844644,
            2171.0564112481384,
            2,
            13.834490045784058,
        ),
        "kappa": skin_entry(
            0.2908292880156819,
            0.2735642127603114,
            0.29963706379203564,
            1.002608956345265,
            1462.6398563740734,
            1594.986324655345,
            3,
            0.2851,
        ),
        "theta": skin_entry(41.2, 8.1, 86.3, 1.0123, 350.2, 512.9, 4, 88.0),
        "sigma_xx": {
            "median": 0.0123,
            "q2.5": 0.0011,
            "q97.5": 0.2,
            "r_hat": 1.0004,
            "ess_bulk": 1500.5,
            "ess_tail": 1200.25,
        },
        "sigma_yy": {
            "median": 0.0098,
            "q2.5": 0.0009,
            "q97.5": 0.15,
            "r_hat": 1.0,
            "ess_bulk": 1711.0,
            "ess_tail": 1300.0,
        },
    },
    "chains": 4,
    "draws_per_chain": 1000,
    "divergences": 2,
    "step_sizes": [0.41, 0.39, 0.44, 0.4],
    "acceptance_rates": [0.86, 0.84, 0.9, 0.88],
    "seconds": 27.3,
    "gp_variance_over_posterior": {"ratio_median": 1.02, "ratio_5": 0.81, "ratio_95": 1.3},
    "error_budget": {"noise": 0.05, "gp": 0.3, "held_out_excess": 0.25, "truncation": 0.4, "parameter_shift": 0.0},
    "error_budget_statement": "the emulator's PCA truncation, not your measurement, limits these intervals (...)",
    "warnings": [
        "this emulator has no held-out error model (...)",
        "theta: R-hat 1.012 > 1.01 (chains disagree; sample longer)",
        "theta: ESS 350 < 400",
        "2 divergent transitions",
    ],
    "observations": ["small.h5 material 4, design 7 (0.05, -0.05), frame 9"],
}


def test_summary_round_trips_through_its_json_unchanged(tmp_path):
    summary = PosteriorSummary.from_json(SUMMARY_JSON)
    assert summary.to_json() == SUMMARY_JSON
    assert json.dumps(summary.to_json(), indent=2) == json.dumps(SUMMARY_JSON, indent=2)  # key order too
    path = summary.write(tmp_path / "summary.json")
    assert path.read_text() == json.dumps(SUMMARY_JSON, indent=2) + "\n"
    assert PosteriorSummary.load(path) == summary
    mu, theta, sigma = summary.parameters["mu"], summary.parameters["theta"], summary.parameters["sigma_xx"]
    assert (mu.q2_5, mu.q97_5, mu.prior, mu.covered) == (
        0.0007404027526394722,
        0.001019260437174447,
        (0.000543, 0.00206),
        True,
    )
    assert theta.ess == 350.2 and summary.max_r_hat == 1.0123 and summary.min_ess == 350.2
    assert sigma.prior is None and sigma.true is None and sigma.covered is None
    for name, entry in SUMMARY_JSON["parameters"].items():  # the skin parameters' keys, then the sigmas' fewer
        assert ParameterSummary.from_json(entry) == summary.parameters[name]
        assert list(summary.parameters[name].to_json().items()) == list(entry.items())
    assert summary.error_budget == ErrorBudget(0.05, 0.3, 0.25, 0.4)
    assert summary.gp_variance_over_posterior == GpVarianceSpread(1.02, 0.81, 1.3)
    budget = {k: v for k, v in SUMMARY_JSON["error_budget"].items() if k != "parameter_shift"}  # written before it
    assert PosteriorSummary.from_json({**SUMMARY_JSON, "error_budget": budget}).error_budget.parameter_shift == 0.0


def test_summaries_of_earlier_versions_load(tmp_path):
    """A summary written before acceptance rates and the error budget (the recorded held-out
    summary without those keys) loads with them empty."""
    entry = json.loads((ROOT / "benchmarks" / "results" / "small_heldout_posterior_summary.json").read_text())
    for key in ("acceptance_rates", "error_budget", "error_budget_statement"):
        entry.pop(key, None)
    path = tmp_path / "summary.json"
    path.write_text(json.dumps(entry))
    summary = PosteriorSummary.load(path)
    assert summary.acceptance_rates == () and summary.error_budget is None and summary.error_budget_statement is None
    assert summary.to_json()["parameters"] == json.loads(path.read_text())["parameters"]
    assert summary.parameters["mu"].covered and summary.observations


def fake_samples(
    truth: bool = True, budget: bool = True, spread: bool = True, model_warnings: tuple[str, ...] = ()
) -> PosteriorSamples:
    """Uniform draws over the prior box (mu ... theta) and lognormal sigmas; no sampler."""
    rng = np.random.default_rng(0)
    draws = np.concatenate(
        [BOUNDS[:, 0] + rng.uniform(size=(4, 300, 5)) * np.ptp(BOUNDS, 1), np.exp(rng.normal(size=(4, 300, 2)))], -1
    )
    diverging = np.zeros((4, 300), bool)
    diverging[1, 5] = True
    return PosteriorSamples(
        names=NAMES,
        draws=draws,
        diverging=diverging,
        step_sizes=[0.31, 0.29, 0.33, 0.3],
        seconds=12.5,
        truth=draws[0, 0, :5] if truth else None,
        bounds=BOUNDS,
        acceptance_rates=[0.8, 0.85, 0.79, 0.9],
        stats={},
        log_likelihood=np.zeros((4, 300, 1, 1)),
        prior=np.zeros((10, 7)),
        data={},
        attrs={},
        gp_variance_spread=GpVarianceSpread(1.01, 0.9, 1.2) if spread else None,
        error_budget=ErrorBudget(0.2, 0.3, 0.1, 0.4) if budget else None,
        error_budget_at=draws[0, 1, :5],
        model_warnings=model_warnings,
    )


def legacy_summary(samples: PosteriorSamples) -> dict:
    """The summary dict as skinid built it before it was typed (the reference of the format)."""
    import arviz as az

    dt = az.from_dict({"posterior": samples.posterior_dict()})
    rhat, bulk, tail = az.rhat(dt), az.ess(dt, method="bulk"), az.ess(dt, method="tail")
    out = {}
    for k, n in enumerate(samples.names):
        x = samples.draws[..., k].ravel()
        e = {
            "median": float(np.median(x)),
            "q2.5": float(np.percentile(x, 2.5)),
            "q97.5": float(np.percentile(x, 97.5)),
            "r_hat": float(rhat[n].values),
            "ess_bulk": float(bulk[n].values),
            "ess_tail": float(tail[n].values),
        }
        if k < 5:
            e["prior"] = samples.bounds[k].tolist()
            e["interval_share_of_prior"] = (e["q97.5"] - e["q2.5"]) / float(np.ptp(samples.bounds[k]))
            if samples.truth is not None:
                e["true"] = float(samples.truth[k])
                e["covered"] = bool(e["q2.5"] <= samples.truth[k] <= e["q97.5"])
        out[n] = e
    messages = list(samples.model_warnings)
    for n, e in out.items():
        if e["r_hat"] > RHAT_LIMIT:
            messages.append(f"{n}: R-hat {e['r_hat']:.3f} > {RHAT_LIMIT} (chains disagree; sample longer)")
        if min(e["ess_bulk"], e["ess_tail"]) < ESS_LIMIT:
            messages.append(f"{n}: ESS {min(e['ess_bulk'], e['ess_tail']):.0f} < {ESS_LIMIT}")
    if samples.diverging.any():
        messages.append(f"{int(samples.diverging.sum())} divergent transitions")
    budget, spread = samples.error_budget, samples.gp_variance_spread
    return {
        "parameters": out,
        "chains": 4,
        "draws_per_chain": 300,
        "divergences": int(samples.diverging.sum()),
        "step_sizes": samples.step_sizes,
        "acceptance_rates": samples.acceptance_rates,
        "seconds": samples.seconds,
        "gp_variance_over_posterior": None if spread is None else asdict(spread),
        "error_budget": None if budget is None else asdict(budget),
        "error_budget_statement": None if budget is None else budget.statement(samples.error_budget_at),
        "warnings": messages,
    }


@pytest.mark.parametrize("known", [True, False], ids=["truth-budget-spread", "none-of-them"])
def test_summary_of_samples_is_the_earlier_dict(known):
    samples = fake_samples(truth=known, budget=known, spread=known, model_warnings=() if known else ("old emu",))
    expected = legacy_summary(samples)
    summary = samples.summary()
    assert json.dumps(summary.to_json(), indent=2) == json.dumps(expected, indent=2)
    sources = ["a.csv", "b.csv"]
    with_sources = samples.summary(sources)
    assert json.dumps(with_sources.to_json(), indent=2) == json.dumps({**expected, "observations": sources}, indent=2)
    assert PosteriorSummary.from_json(with_sources.to_json()) == with_sources
    assert summary.warnings[-1] == "1 divergent transitions"


def legacy_print_summary(summary: dict, out: Path) -> None:
    """``skinid infer``'s printout as it read the summary dict."""
    print(f"{'':>8} {'median':>10} {'95 % interval':>24} {'R-hat':>6} {'ESS':>6} {'true':>10}")
    for name, e in summary["parameters"].items():
        true = f"{e['true']:.4g}" if "true" in e else ""
        print(
            f"{name:>8} {e['median']:>10.4g} [{e['q2.5']:>10.4g}, {e['q97.5']:>10.4g}] "
            f"{e['r_hat']:>6.3f} {min(e['ess_bulk'], e['ess_tail']):>6.0f} {true:>10}"
        )
    for w in summary["warnings"]:
        print(f"warning: {w}")
    if summary.get("error_budget_statement"):
        print(summary["error_budget_statement"][0].upper() + summary["error_budget_statement"][1:])
    print(f"{summary['divergences']} divergences, {summary['seconds']:.1f} s")
    print(f"wrote {out}/posterior.nc, summary.json, corner.png")


@pytest.mark.parametrize("known", [True, False], ids=["truth", "no-truth"])
def test_infer_prints_the_summary_as_before(capsys, known):
    from inference.__main__ import print_summary

    summary = fake_samples(truth=known, budget=known, spread=known).summary(["m.csv"])
    legacy_print_summary(summary.to_json(), Path("out"))
    expected = capsys.readouterr().out
    print_summary(summary, Path("out"))
    assert capsys.readouterr().out == expected
    assert ("The emulator's PCA truncation" in expected) == known


def test_test_set_study_resumes_from_summary_files(tmp_path, monkeypatch):
    """Finished materials are read back (PosteriorSummary.load), not sampled again; study.json
    holds what the study returns and reads back (read_study)."""
    import inference.studies as studies

    summaries = {i: fake_samples().summary([f"material {i}"]) for i in (3, 5)}
    for i, s in summaries.items():
        (tmp_path / f"material_{i:03d}").mkdir()
        s.write(tmp_path / f"material_{i:03d}" / "summary.json")
    monkeypatch.setattr(studies, "posterior_of", lambda *args, **kwargs: pytest.fail("sampled a finished material"))
    result = studies.test_set_study(
        SimpleNamespace(param_bounds=BOUNDS), None, [7], [-1], studies.SamplerSettings(), tmp_path, materials=[3, 5]
    )
    assert (tmp_path / "accuracy.png").read_bytes()[:4] == b"\x89PNG"
    study = studies.read_study(tmp_path / "study.json")
    assert study == result
    mu = [s.parameters["mu"] for s in summaries.values()]
    assert (study.designs, study.frames, study.materials) == ([7], [-1], [3, 5])
    assert study.coverage_95["mu"] == np.mean([p.covered for p in mu])
    assert study.median_interval_share_of_prior["mu"] == np.median([p.interval_share_of_prior for p in mu])
    assert study.max_r_hat == max(s.parameters[n].r_hat for s in summaries.values() for n in NAMES[:5])


def test_write_outputs_returns_what_summary_json_holds(tmp_path, monkeypatch):
    import inference.plots

    samples = fake_samples()
    monkeypatch.setattr(
        PosteriorSamples,
        "inference_data",
        lambda self: SimpleNamespace(to_netcdf=lambda path: Path(path).write_bytes(b"")),
    )
    monkeypatch.setattr(inference.plots, "corner_plot", lambda samples, path: Path(path).write_bytes(b""))
    summary = write_outputs(samples, tmp_path / "post", ["m.csv"])
    assert (tmp_path / "post" / "summary.json").read_text() == json.dumps(
        {**legacy_summary(samples), "observations": ["m.csv"]}, indent=2
    ) + "\n"
    assert PosteriorSummary.load(tmp_path / "post" / "summary.json") == summary


# validation.json of a small-mesh emulator (two components, 4 and 3 PCs)
VALIDATION_JSON = {
    "test_materials": [4, 9, 17],
    "n_rows": 378,
    "components": {
        "xx": {
            "r2_per_pc": [0.99991, 0.99962, 0.99874, 0.99315],
            "min_r2": 0.99315,
            "field_rmse": 0.000412,
            "field_rmse_relative": 0.0121,
            "pca_floor_rmse": 0.000355,
            "field_max_abs_error": 0.0042,
            "field_rms": 0.034,
            "weight_z_rms": [0.91, 1.12, 1.3, 0.77],
        },
        "yy": {
            "r2_per_pc": [0.99988, 0.9993, 0.9951],
            "min_r2": 0.9951,
            "field_rmse": 0.000388,
            "field_rmse_relative": 0.0117,
            "pca_floor_rmse": 0.00031,
            "field_max_abs_error": 0.0039,
            "field_rms": 0.0331,
            "weight_z_rms": [1.05, 0.98, 1.41],
        },
    },
}


def test_validation_report_round_trips_through_its_json_unchanged(tmp_path):
    report = ValidationReport.from_json(VALIDATION_JSON)
    assert report.to_json() == VALIDATION_JSON
    assert json.dumps(report.to_json(), indent=2) == json.dumps(VALIDATION_JSON, indent=2)
    assert report.write(tmp_path / "validation.json").read_text() == json.dumps(VALIDATION_JSON, indent=2) + "\n"
    assert ValidationReport.load(tmp_path / "validation.json") == report
    xx = report.components["xx"]
    assert isinstance(xx, ComponentValidation) and xx.r2_per_pc[3] == 0.99315 and report.test_materials == (4, 9, 17)
    assert xx.held_out_scores().field_rmse_relative == 0.0121


@pytest.fixture(scope="module")
def synthetic_emulator_dir(tmp_path_factory):
    """An emulator fitted on the synthetic dataset of tests/test_posterior_file.py (no FE)."""
    from skinfem.config import load_config
    from skinfem.io import STATUS_OK, StrainDataset, create_dataset, write_simulation
    from surrogate.emulator import fit_emulator
    from tests.test_posterior_file import DESIGNS, FRAMES, synthetic_strain

    config = load_config("small")
    bounds = config.sweep.box
    params = bounds[:, 0] + np.random.default_rng(0).uniform(size=(8, 5)) * np.ptp(bounds, 1)
    g = np.linspace(-18, 18, 10)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    path = tmp_path_factory.mktemp("synthetic") / "data.h5"
    create_dataset(
        path, config, params, DESIGNS, FRAMES, xy, np.ones(len(xy)), np.r_[np.zeros(6), np.ones(2)], "synthetic", bounds
    )
    for i, p in enumerate(params):
        for j, alpha in enumerate(DESIGNS):
            write_simulation(
                path, i, j, np.stack([synthetic_strain(p, bounds, alpha, t, xy) for t in FRAMES]), STATUS_OK
            )
    emulator = fit_emulator(StrainDataset.open(path), gp_fraction=0.5, restarts=0, seed=0, n_jobs=1)
    return emulator.save(tmp_path_factory.mktemp("emulator") / "emu")


def test_validate_writes_the_report_and_the_cli_prints_it(synthetic_emulator_dir, capsys):
    from surrogate.__main__ import main
    from surrogate.emulator import Emulator

    assert main(["validate", "--emulator", str(synthetic_emulator_dir), "--force"]) == 0
    out = capsys.readouterr().out
    text = (synthetic_emulator_dir / "validation.json").read_text()
    report = ValidationReport.load(synthetic_emulator_dir / "validation.json")
    assert text == json.dumps(report.to_json(), indent=2) + "\n"
    raw = json.loads(text)
    assert list(raw) == ["test_materials", "n_rows", "components"] and raw["test_materials"] == [6, 7]
    assert [list(c) for c in raw["components"].values()] == [list(VALIDATION_JSON["components"]["xx"])] * 2
    for c, r in report.components.items():
        assert len(r.r2_per_pc) == len(r.weight_z_rms) and r.min_r2 == min(r.r2_per_pc)
        r2 = ", ".join(f"{v:.4f}" for v in r.r2_per_pc)
        assert f"E_{c}: R² per PC [{r2}]; field RMSE {r.field_rmse:.2e} " in out
    assert Emulator.load(synthetic_emulator_dir).provenance.validation == {
        c: r.held_out_scores() for c, r in report.components.items()
    }


def test_chains_silence_only_the_densitys_floating_point_warnings():
    """Divergent NUTS trajectories overflow numpy in inference.density (inf potential: a divergence)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with quiet_overflow(), np.errstate(all="warn"):
            density = {"__name__": "inference.density", "np": np}
            exec("np.exp(np.array([800.0])); np.array([np.inf]) * 0.0; np.square(np.array([1e200]))", density)
            exec("np.exp(np.array([800.0]))", {"__name__": "inference.model", "np": np})
            exec("import warnings; warnings.warn('other', UserWarning)", {"__name__": "inference.density"})
    assert [(w.category, str(w.message)) for w in caught] == [
        (RuntimeWarning, "overflow encountered in exp"),
        (UserWarning, "other"),
    ]


PARALLEL_CHAINS = """
import warnings
import numpy as np
import torch
from inference.model import ObservedWeights, SkinPosterior
from inference.sampling import sample_posterior
from tests.test_inference import LinearEmulator

if __name__ == "__main__":
    warnings.simplefilter("default")
    emu = LinearEmulator()
    design = np.array([[0.05, -0.05], [0.05, 0.0]])
    x = np.column_stack([np.tile([0.3, -0.2, 0.5, 0.1, -0.4], (2, 1)), design])
    w = (torch.as_tensor(x) @ emu.A + emu.b).numpy() + 0.1 * np.random.default_rng(1).normal(size=(2, 6))
    post = SkinPosterior(emu, ObservedWeights(design, w, np.full((2, 6), 0.02), None), noise="known")
    runs = [sample_posterior(post, chains=3, warmup=50, draws=50, seed=3, n_jobs=n, progress=True)
            for n in (1, 2)]
    print(np.array_equal(runs[0].draws, runs[1].draws), runs[1].draws.shape)
"""


def test_parallel_chains_equal_serial_ones_and_leave_no_warning_at_exit():
    """Chains in spawned processes (ProcessPoolExecutor) give the serial chains' draws; the progress
    bar is complete and nothing but it is written to stderr (no leaked-semaphore warning at exit)."""
    res = subprocess.run([sys.executable, "-c", PARALLEL_CHAINS], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["True", "(3,", "50,", "5)"]
    lines = [line.strip() for line in res.stderr.replace("\r", "\n").splitlines() if line.strip()]
    assert all(line.startswith("NUTS:") for line in lines), lines
    assert sum(line.startswith("NUTS:   0%") for line in lines) == 2  # the serial and the parallel run
    assert sum("300/300" in line for line in lines) >= 2  # each complete: 3 chains x (50 + 50) iterations
