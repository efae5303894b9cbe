"""Failed FE runs are information, not crashes; an error on one MPI rank ends every rank at once;
bad measurements get one clear line."""

from __future__ import annotations

import itertools
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from inference.criticism import Data, NoiseModel, calibrate
from inference.forward import ForwardModel
from inference.observations import write_measurement
from tests.cli_helpers import MPIRUN, skinid, skinid_env


class FailingForward(ForwardModel):
    """fields = A tanh(x), but no solution (None) where x[0] > limit: a model with a failure region."""

    def __init__(self, A, limit):
        self.A, self.limit = A, limit
        self.names = [f"p{i}" for i in range(A.shape[1])]
        self.bounds = np.array([[-5.0, 5.0]] * A.shape[1])
        self.null = np.zeros(A.shape[1])

    def evaluate_many(self, points):
        self.runs += len(points)
        return [None if x[0] > self.limit else (self.A @ np.tanh(x)).reshape(1, -1, 3) for x in points]


def test_failed_runs_are_rejected_steps_and_the_fit_still_converges():
    """From a flat start the first Gauss-Newton step overshoots into the failure region: it is
    recorded and shortened, and the fit reaches the least-squares optimum (scipy's, started at
    the truth), which lies outside that region."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (60, 2))
    A = rng.normal(size=(180, 5)) * 1e-3
    truth = np.array([0.8, -0.6, 0.5, 0.3, -0.4])
    noise = NoiseModel(np.full(3, 1e-5), 0.0, 0.0)
    y = (A @ np.tanh(truth)).reshape(1, -1, 3) + noise.sample(xy, (1,), rng)
    data = Data(y, np.ones((1, 60), bool), xy[None], noise)
    forward = FailingForward(A, limit=1.2)
    cal = calibrate(forward, data, np.array([-2.5, 0, 0, 0, 0]), list(range(5)), max_iterations=60)
    expected = least_squares(lambda x: A @ np.tanh(x) - y.ravel(), truth, xtol=1e-14, ftol=1e-14).x
    assert cal.x == pytest.approx(expected, abs=1e-4)
    assert cal.rejected and all(x[0] > 1.2 for x in cal.rejected)


def _measurement(path, extent=20.0, step=2.0):
    g = np.arange(-extent, extent + 1e-9, step)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    return write_measurement(path, xy, np.zeros((len(xy), 3)), (0.05, -0.05), 1.0, np.full((len(xy), 3), 1e-3))


@pytest.mark.parametrize(
    "problem, expected",
    [
        ("outside", "lies outside the block"),
        ("no_edge", "contains no membrane edge"),
        ("nan", "NaN or infinite value"),
        ("few", "4 measured points are not more than the 5 parameters"),
        ("no_mesh", "give the mesh to check on with --config"),
        ("start", "--start is outside the prior box: theta = 120 not in [0, 90]"),
        ("refine", "the quadratic reference is for linear (Q1) meshes"),
    ],
)
def test_bad_measurements_get_one_line_and_no_report(problem, expected, tmp_path):
    path = _measurement(tmp_path / "m.csv")
    text = path.read_text().splitlines()
    if problem == "outside":
        text[-1] = "30,0,0,0,0,0.001,0.001,0.001"
    elif problem == "no_edge":
        path = _measurement(tmp_path / "m.csv", extent=4.0, step=1.0)
        text = path.read_text().splitlines()
    elif problem == "nan":
        text[-1] = "0,0,nan,0,0,0.001,0.001,0.001"
    elif problem == "few":
        text = text[:6] + [f"{x},{y},0,0,0,0.001,0.001,0.001" for x, y in ((10, 10), (10, -10), (-10, 10), (9, 10))]
    path.write_text("\n".join(text) + "\n")
    config = {"no_mesh": [], "refine": ["--config", "check", "--refine", "quadratic"]}.get(
        problem, ["--config", "small"]
    )
    start = ["--start", "1e-3", "0.017", "11", "0.285", "120"] if problem == "start" else []
    res = skinid("check", *config, *start, "--measurement", path, "--out", tmp_path / "report")
    assert res.returncode == 2
    assert expected in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert not (tmp_path / "report").exists()


DRIVER = """
import sys
from mpi4py import MPI
import inference.criticism.check, inference.forward, skinfem.model
from inference.__main__ import main

def fail_on_ranks(*args, **kwargs):
    if MPI.COMM_WORLD.rank in {ranks}:
        raise {error}("forced failure")
    return original(*args, **kwargs)

original = {target}
{target} = fail_on_ranks
sys.exit(main(["check", "--config", "small", "--measurement", "{measurement}", "--out", "{out}",
               "--mesh-dir", "{mesh_dir}", "--increments", "1", "--no-discretisation"]))
"""


FORCED = {  # where: (patched function, error raised, ranks that raise it)
    "simulation": ("inference.forward.FEForward._simulate", "RuntimeError", (1,)),
    "uncaught": ("inference.criticism.check.spread_start", "RuntimeError", (1,)),
    "start": ("inference.forward.FEForward._simulate", "skinfem.model.ConvergenceError", (0, 1)),
}


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="needs mpirun")
@pytest.mark.parametrize("where", list(FORCED))
def test_an_error_on_one_rank_ends_every_rank_at_once(where, mesh_dir, tmp_path):
    """A simulation error on rank 1 is agreed (both ranks end with one line, exit 2); any other
    exception on rank 1 aborts the job while rank 0 waits in a collective; a start where Newton
    fails on every rank is one line in all (not one per rank), exit 2."""
    measurement = _measurement(tmp_path / "m.csv")
    target, error, ranks = FORCED[where]
    script = tmp_path / "driver.py"
    script.write_text(
        textwrap.dedent(
            DRIVER.format(
                error=error,
                ranks=ranks,
                target=target,
                measurement=measurement,
                out=tmp_path / "report",
                mesh_dir=mesh_dir,
            )
        )
    )
    start = time.perf_counter()
    res = subprocess.run(
        [MPIRUN, "-n", "2", sys.executable, str(script)], capture_output=True, text=True, timeout=300, env=skinid_env()
    )
    seconds = time.perf_counter() - start
    lines = [line for line in res.stderr.splitlines() if "error" in line]
    assert res.returncode != 0 and len(lines) == 1, res.stderr[-2000:]
    if where == "start":
        assert res.returncode == 2 and "starting point" in lines[0], res.stderr[-2000:]
    else:
        assert "rank 1" in lines[0] and "forced failure" in lines[0]
    assert seconds < 120
    assert not (tmp_path / "report" / "report.md").exists()


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="needs mpirun")
def test_a_refinement_that_does_not_apply_is_said_once_under_mpi(tmp_path):
    """`--refine quadratic` on a quadratic mesh under `mpirun -n 2`: both ranks end with exit 2
    and one line between them, before any FE run, and nothing is written."""
    measurement = _measurement(tmp_path / "m.csv")
    command = ["check", "--config", "check", "--refine", "quadratic", "--measurement", measurement]
    res = subprocess.run(
        [MPIRUN, "-n", "2", sys.executable, "-m", "inference", *map(str, command), "--out", str(tmp_path / "report")],
        capture_output=True,
        text=True,
        timeout=120,
        env=skinid_env(),
    )
    lines = [line for line in res.stderr.splitlines() if "error" in line]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert "the quadratic reference is for linear (Q1) meshes" in lines[0]
    assert not (tmp_path / "report").exists()


def corner_forward(config, mesh_dir, alpha):
    """The serial FE forward model (all effects, 2 increments) of one design on a 3 mm grid."""
    from mpi4py import MPI

    from inference.forward import FEForward, PointSet

    bounds = config.sweep.box
    g = np.linspace(-18, 18, 13)
    obs = [PointSet(np.array(alpha), 1.0, np.stack(np.meshgrid(g, g), -1).reshape(-1, 2))]
    return FEForward(config, obs, bounds, mesh_dir, increments=2, comm=MPI.COMM_SELF, continuation=False)


@pytest.mark.slow
@pytest.mark.parametrize("alpha", [(0.05, -0.05), (-0.05, -0.05)])
def test_newton_converges_at_every_corner_of_the_skin_box(small_config, mesh_dir, alpha):
    """All 32 corners of the Table-1 box (mu, k1, k2, kappa, theta), for the mixed design and
    biaxial compression. (Before GMRES stalls were escalated to a factorisation at every
    Newton step, 17 of 32 corners with effects at their bounds failed as 'Newton failed'.)"""
    fe = corner_forward(small_config, mesh_dir, alpha)
    corners = []
    for corner in itertools.product([0, 1], repeat=5):
        x = fe.null.copy()
        x[:5] = fe.bounds[np.arange(5), corner]
        corners.append(x)
    fields = fe.evaluate_many(corners)
    assert fe.failures == []
    assert all(np.all(np.isfinite(f)) and np.abs(f).max() > 0.01 for f in fields)


@pytest.mark.slow
def test_box_corners_with_effects_at_their_bounds_converge_or_are_rejected_cleanly(small_config, mesh_dir):
    """Corners of the prior box with every effect at a prior bound return fields or None (a
    recorded failure), never an exception; most converge."""
    fe = corner_forward(small_config, mesh_dir, (0.05, -0.05))
    rng = np.random.default_rng(0)
    corners = [np.where(rng.random(len(fe.names)) < 0.5, fe.bounds[:, 0], fe.bounds[:, 1]) for _ in range(8)]
    fields = fe.evaluate_many(corners)
    assert all(f is None or np.all(np.isfinite(f)) for f in fields)
    assert len(fe.failures) == sum(f is None for f in fields) <= 2
    assert all("Newton failed" in failure.message for failure in fe.failures)


SPREAD_DRIVER = """
import numpy as np
from mpi4py import MPI
import skinfem.model
from inference.forward import FEForward, PointSet
from skinfem.config import load_config

calls = []
original = skinfem.model.SkinModel.simulate
skinfem.model.SkinModel.simulate = lambda self, *a, **k: calls.append(1) or original(self, *a, **k)
xy = np.array([[9.0, 3.0], [11.0, -6.0], [-14.0, 2.0]])
obs = [PointSet(np.array(alpha), 1.0, xy) for alpha in ((0.05, 0.05), (0.05, -0.05))]
bounds = np.array([[2e-4, 2e-3], [1e-3, 0.05], [1.0, 20.0], [0.0, 0.3], [-90.0, 90.0]])
config = load_config("small")
spread = FEForward(config, obs, bounds, "{mesh_dir}", increments=1, comm=MPI.COMM_WORLD)
x = np.concatenate([[1.2e-3, 0.017, 11.0, 0.285, 30.0], spread.null[5:]])
fields, jacobian = spread.evaluate_with_jacobian([x], spread.names[:2])[0]
counts = MPI.COMM_WORLD.gather(len(calls))
if MPI.COMM_WORLD.rank == 0:
    serial = FEForward(config, obs, bounds, "{mesh_dir}", increments=1, comm=MPI.COMM_SELF)
    f, j = serial.evaluate_with_jacobian([x], serial.names[:2])[0]
    print("COUNTS", counts, "DIFF", np.abs(f - fields).max(), np.abs(j - jacobian).max(), np.abs(f).max())
"""


@pytest.mark.mpi
@pytest.mark.skipif(MPIRUN is None, reason="needs mpirun")
def test_one_points_designs_are_spread_over_ranks(mesh_dir, tmp_path):
    """A single parameter point with two designs runs one simulation on each rank, and the
    gathered fields and Jacobian equal a serial evaluation's."""
    script = tmp_path / "spread.py"
    script.write_text(SPREAD_DRIVER.format(mesh_dir=mesh_dir))
    res = subprocess.run(
        [MPIRUN, "-n", "2", sys.executable, str(script)], capture_output=True, text=True, timeout=300, env=skinid_env()
    )
    line = next(line for line in res.stdout.splitlines() if line.startswith("COUNTS"))
    counts, diffs = line.split("DIFF")
    assert counts.split(None, 1)[1].strip() == "[1, 1]"
    diff_fields, diff_jacobian, scale = map(float, diffs.split())
    assert scale > 1e-3 and diff_fields <= 1e-12 * scale and diff_jacobian <= 1e-9
