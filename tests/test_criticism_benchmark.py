"""benchmarks/criticism.py's confusion table from finished rows (no FE)."""

from __future__ import annotations

from pathlib import Path

from tests.scripts import ROOT, load_script


def load_benchmark():
    return load_script(ROOT / "benchmarks" / "criticism.py", "criticism_bench")


def row(case: str, verdict: str, rank, rmse: float, added, seconds: float) -> dict:
    return dict(
        case=case,
        verdict=verdict,
        rank_of_true_effect=rank,
        rmse_baseline=rmse,
        rmse_with_true_effect=added,
        discretisation_sigma=4.0,
        carried_sigma=1.5,
        seconds=seconds,
    )


def test_the_table_counts_verdicts_and_takes_medians_per_case():
    rows = [
        row("none", "no missing effect", None, 1e-3, None, 600),
        row("pre_stretch", "pre_stretch", 1, 2e-3, 1.0e-3, 1000),
        row("pre_stretch", "no missing effect", 2, 4e-3, 1.2e-3, 1200),
        row("pre_stretch", "pre_stretch", 1, 3e-3, 1.1e-3, 1100),
    ]
    lines = load_benchmark().markdown_table(rows).splitlines()
    assert len(lines) == 4  # header, rule, two cases
    assert lines[2] == "| none | 1 | no missing effect: 1 | — | 1.00e-03 | — | 4.0 / 1.5 | 600 |"
    assert lines[3] == (
        "| pre_stretch | 3 | pre_stretch: 2, no missing effect: 1 | 2/3 | 3.00e-03 | 1.10e-03 | 4.0 / 1.5 | 1100 |"
    )


def test_an_understated_noise_is_its_own_verdict_in_the_table():
    rows = [
        {**row("understated_noise", "no missing effect", None, 2e-3, None, 1000), "noise_factor": {"estimated": 1.93}},
        {**row("understated_noise", "no missing effect", None, 2e-3, None, 1100), "noise_factor": {"estimated": 1.96}},
        {**row("none", "no missing effect", None, 1e-3, None, 600), "noise_factor": {"estimated": 1.0}},
    ]
    lines = load_benchmark().markdown_table(rows).splitlines()
    assert "| understated_noise | 2 | no missing effect (noise understated): 2 | — |" in lines[2]
    assert "| none | 1 | no missing effect: 1 | — |" in lines[3]


def test_the_limit_data_are_exact_for_fields_that_converge_at_the_measured_order():
    """``--data q2-limit``: fields f(h) = f* + C h^p of two meshes whose edge cells differ by 2
    extrapolate to f*; the pair differs in the edge cells only."""
    import numpy as np

    from inference.criticism.discretisation import OBSERVED_ORDER

    bench = load_benchmark()
    rng = np.random.default_rng(1)
    limit, c = rng.normal(size=(2, 5, 3)), rng.normal(size=(2, 5, 3))
    coarser, finer = (limit + c * h ** OBSERVED_ORDER[2] for h in (0.5, 0.25))
    np.testing.assert_allclose(bench.extrapolated(coarser, finer), limit, atol=1e-12)
    a, b = (bench.DATA_MESHES[name] for name in bench.LIMITS["q2-limit"])
    assert {k for k in a if a[k] != b[k]} == {"h_edge"} and a["h_edge"] == 2 * b["h_edge"]


def test_recorded_rows_are_kept_and_another_setups_file_is_refused(tmp_path):
    """With --keep-recorded, seeds can be added to a results file from an empty --out, and a file of
    another setup is not overwritten; without it, nothing recorded is reused."""
    import json
    from argparse import Namespace

    import pytest

    bench = load_benchmark()
    args = Namespace(
        config="check",
        data="q2-limit",
        refine="edge",
        start="centre",
        confirm=1,
        mesh_drift=False,
        results=tmp_path / "r.json",
        keep_recorded=True,
    )
    assert bench.recorded_rows(args) == {}
    command = (
        f"mpirun -n 2 python benchmarks/criticism.py --config check --cases none --seeds 1 {bench.setup_flags(args)}"
    )
    earlier = {"command": command, "checked_config": "check", "rows": [{"case": "none", "seed": 0, "verdict": "x"}]}
    args.results.write_text(json.dumps(earlier))
    assert bench.recorded_rows(args) == {("none", 0): earlier["rows"][0]}
    assert bench.recorded_rows(Namespace(**{**vars(args), "keep_recorded": False})) == {}  # a rerun measures anew
    with pytest.raises(SystemExit, match="another setup"):
        bench.recorded_rows(Namespace(**{**vars(args), "refine": "uniform"}))
    with pytest.raises(SystemExit, match="another setup"):
        bench.recorded_rows(Namespace(**{**vars(args), "confirm": 2}))
    with pytest.raises(SystemExit, match="another setup"):
        bench.recorded_rows(Namespace(**{**vars(args), "mesh_drift": True}))
    for malformed in ("{not json", json.dumps({"command": command}), json.dumps({**earlier, "rows": [1]})):
        args.results.write_text(malformed)
        with pytest.raises(SystemExit, match="not a results file"):
            bench.recorded_rows(args)


def test_a_benchmark_check_is_a_valid_skinid_check_command_started_at_the_box_centre(tmp_path):
    """``check_argv`` is what the benchmark runs and what ``criticism_basin.py`` rebuilds from."""
    import argparse

    from inference.cli_parsers import build_parser
    from skinfem.config import load_config

    bench = load_benchmark()
    args = argparse.Namespace(
        config="check", refine="edge", start="centre", confirm=2, mesh_dir=tmp_path / "meshes", mesh_drift=False
    )
    files = [tmp_path / "m_0.csv", tmp_path / "m_1.csv"]
    argv = bench.check_argv(files, tmp_path / "none_0", ["pre_stretch"], args)
    assert argv[0] == "check"
    parsed = build_parser("skinid check").parse_args(argv[1:])
    assert parsed.measurement == files and Path(parsed.out) == tmp_path / "none_0" / "report"
    assert parsed.start == load_config("check").sweep.box.mean(axis=1).tolist()
    assert (parsed.refine, parsed.spacing, parsed.increments, parsed.add) == ("edge", 2.0, 2, ["pre_stretch"])
    assert (parsed.noise_length, parsed.noise_nugget, parsed.resume, parsed.confirm) == (2.0, 0.3, True, 2)
    assert parsed.mesh_drift is False
    spread = argparse.Namespace(**{**vars(args), "start": "spread", "mesh_drift": True})
    parsed = build_parser("skinid check").parse_args(bench.check_argv(files, tmp_path, [], spread)[1:])
    assert parsed.start is None and parsed.mesh_drift


def test_a_killed_data_run_resumes_from_the_designs_it_finished(tmp_path, monkeypatch):
    import numpy as np
    from mpi4py import MPI

    import inference.synthetic

    bench = load_benchmark()
    points = np.zeros((4, 2))
    computed = []

    def measured_fields(config, params, designs, *args, **kwargs):
        computed.extend(designs)
        return [np.full((len(points), 3), float(bench.DESIGNS.index(d))) for d in designs]

    monkeypatch.setattr(inference.synthetic, "measured_fields", measured_fields)
    path = tmp_path / "data_mesh_none.npy"
    np.save(bench.design_path(path, 0), np.full((len(points), 3), 7.0))  # finished before the kill
    fields = bench.data_fields(None, "none", points, "meshes", MPI.COMM_SELF, path)
    assert computed == bench.DESIGNS[1:]
    assert fields.shape == (len(bench.DESIGNS), len(points), 3)
    assert np.all(fields[0] == 7.0) and np.all(fields[1] == 1.0)
    assert np.array_equal(np.load(path), fields)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # the parts merged into one file
    assert np.array_equal(bench.data_fields(None, "none", points, "meshes", MPI.COMM_SELF, path), fields)
    assert computed == bench.DESIGNS[1:]  # the whole file read, nothing recomputed


def test_comparing_data_that_are_not_made_yet_is_one_line(tmp_path):
    import pytest

    script = load_script(ROOT / "benchmarks" / "limit_data.py", "limit_data")
    bench = load_benchmark()
    with pytest.raises(SystemExit, match="data_q2-fine-coarser-m8_none.npy, .*data_q2-fine-m8_none.npy not made yet"):
        script.kept_fields(bench, tmp_path, "q2-limit-m8", "none")
