"""posterior.nc is a complete ArviZ file, and bad inputs to ``skinid infer`` are refused with one line.

Everything runs on a synthetic emulator (no FE): smooth low-rank strain fields of the skin
parameters and alpha * t, written as a dataset and fitted like a real one. Designs all have
alpha11 = 0.05 and frames t >= 0.5, so the emulator's training range of alpha11 * t is
[0.025, 0.05]: a small load fraction falls outside it.
"""

import numpy as np
import pytest
import torch
from scipy.stats import invgamma

from inference.__main__ import main
from inference.model import ObservedWeights, SkinPosterior, pyro_model
from inference.observations import Observation, from_dataset, write_measurement
from inference.posterior_file import write_outputs
from inference.sampling import draw_statistics, sample_posterior
from skinfem.config import PARAM_NAMES, load_config
from skinfem.io import STATUS_OK, StrainDataset, create_dataset, write_simulation
from surrogate.emulator import Emulator, fit_emulator

DESIGNS = np.array([[0.05, -0.05], [0.05, 0.0], [0.05, 0.05]])
FRAMES = np.array([0.5, 0.75, 1.0])
GROUPS = {"posterior", "sample_stats", "log_likelihood", "observed_data", "prior", "constant_data"}


def synthetic_strain(params: np.ndarray, bounds: np.ndarray, alpha: np.ndarray, t: float, xy: np.ndarray) -> np.ndarray:
    """(n_cells, 3) log strain: five fixed spatial modes weighted by the unit-box parameters times alpha * t."""
    p = (params - bounds[:, 0]) / (bounds[:, 1] - bounds[:, 0])
    x, y = xy[:, 0] / 20, xy[:, 1] / 20
    modes = np.stack([np.exp(-(x**2 + y**2)), x * y, np.cos(2 * x), np.sin(y) * x, x**2 - y**2])
    a11, a22 = alpha * t
    exx = (a11 * (1 + p[0]) + 0.3 * a22 * p[1]) * modes[0] + 0.2 * a11 * p[2] * modes[1] + 0.1 * a11 * p[4] * modes[4]
    eyy = (a22 * (1 + p[1]) + 0.3 * a11 * p[0]) * modes[0] + 0.2 * a11 * p[3] * modes[2] + 0.1 * a22 * p[4] * modes[3]
    return np.column_stack([exx, eyy, 0.1 * (exx - eyy)])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A 12-material dataset (2 held out) of :func:`synthetic_strain` on a 12 x 12 grid of cells."""
    config = load_config("small")
    bounds = config.sweep.box
    rng = np.random.default_rng(0)
    params = bounds[:, 0] + rng.uniform(size=(12, 5)) * (bounds[:, 1] - bounds[:, 0])
    g = np.linspace(-18, 18, 12)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    path = tmp_path_factory.mktemp("synthetic") / "data.h5"
    split = np.r_[np.zeros(10), np.ones(2)]
    create_dataset(path, config, params, DESIGNS, FRAMES, xy, np.ones(len(xy)), split, "synthetic", bounds)
    for i, p in enumerate(params):
        for j, alpha in enumerate(DESIGNS):
            frames = np.stack([synthetic_strain(p, bounds, alpha, t, xy) for t in FRAMES])
            write_simulation(path, i, j, frames, STATUS_OK)
    return StrainDataset.open(path)


@pytest.fixture(scope="module")
def emulator_dir(dataset, tmp_path_factory):
    emulator = fit_emulator(dataset, gp_fraction=0.5, restarts=0, seed=0, n_jobs=1)
    return emulator.save(tmp_path_factory.mktemp("emulator") / "emu")


@pytest.fixture(scope="module")
def emulator(emulator_dir):
    return Emulator.load(emulator_dir)


def sampled(emulator, observations, tmp_path, **options):
    """(posterior, samples, DataTree read back from posterior.nc) of a short NUTS run."""
    import arviz as az

    post = SkinPosterior(emulator, ObservedWeights.project(emulator, observations), **options)
    samples = sample_posterior(post, chains=2, warmup=150, draws=100, seed=1, n_jobs=1, progress=False)
    write_outputs(samples, tmp_path)
    return post, samples, az.from_netcdf(tmp_path / "posterior.nc")


@pytest.fixture(scope="module")
def run(emulator, dataset, tmp_path_factory):
    """Unknown noise (halfcauchy), exact GP variance, the emulator scale sampled, two frames of two designs."""
    observations = from_dataset(dataset, 10, designs=[0, 2], frames=[-2, -1])
    return sampled(emulator, observations, tmp_path_factory.mktemp("post"), emulator_scale=True)


@pytest.fixture(scope="module")
def known_run(emulator, dataset, tmp_path_factory):
    """Known noise (a stated sd), GP variance fixed at the mode, one observation."""
    observations = from_dataset(dataset, 11, designs=[1], frames=[-1])
    observations[0].sd = np.array([1e-4, 2e-4, 1e-4])
    return sampled(emulator, observations, tmp_path_factory.mktemp("post_known"), noise="known", gp_variance="mode")


# -- the file ----------------------------------------------------------------------------------
def test_file_has_every_group_with_its_variables(run, dataset):
    post, samples, dt = run
    assert GROUPS <= set(dt.children)
    assert set(dt["posterior"].data_vars) == set(post.names)
    assert {"diverging", "step_size", "n_steps", "tree_depth", "accepted", "lp"} <= set(dt["sample_stats"].data_vars)
    n_datum = post.weights.numel()
    assert dt["log_likelihood"]["weights"].dims == ("chain", "draw", "datum")
    assert dt["log_likelihood"]["weights"].shape == (2, 100, n_datum)
    np.testing.assert_array_equal(dt["observed_data"]["weights"].values, post.observed.weights.ravel())
    assert dt["prior"]["mu"].shape == (1, 1000)
    constant = dt["constant_data"]
    np.testing.assert_allclose(constant["alpha11"], DESIGNS[[0, 0, 2, 2], 0])
    np.testing.assert_allclose(constant["alpha22"], DESIGNS[[0, 0, 2, 2], 1])
    np.testing.assert_allclose(constant["t"], FRAMES[[-2, -1, -2, -1]])
    np.testing.assert_allclose(constant["cell_x"], dataset.xy[:, 0])
    assert constant["strain_field"].shape == (4, len(dataset.xy), 3)
    np.testing.assert_allclose(constant["truth"], dataset.params[10])
    assert list(constant["datum_observation"].values[:3]) == [0, 0, 0]
    assert dt.attrs["seed"] == 1 and "momentum" in dt["sample_stats"].attrs["energy"]


def test_per_datum_log_likelihood_sums_to_the_models_likelihood(run, known_run):
    """At a few draws: the file's terms summed over datum = SkinPosterior.log_likelihood and the
    log probability of pyro_model's ``weights`` site; lp = log_density at given unconstrained
    vectors, and -potential at the file's draws (up to the round-off of unconstraining them, and
    of the closed-form potential NUTS uses with the GP variance fixed)."""
    from pyro import poutine

    for post, _, dt in (run, known_run):
        draws = np.stack([dt["posterior"][n].values for n in post.names], -1)  # (chain, draw, dim)
        terms = dt["log_likelihood"]["weights"].values
        for c, d in [(0, 0), (0, 57), (1, 99)]:
            values = torch.as_tensor(draws[c, d])
            expected = float(post.log_likelihood(*post.latents(values)))
            assert terms[c, d].sum() == pytest.approx(expected, rel=1e-10)
            sites = {n: values[k] for k, n in enumerate(post.names)}
            trace = poutine.trace(poutine.condition(pyro_model, data=sites)).get_trace(post)
            node = trace.nodes["weights"]
            assert terms[c, d].sum() == pytest.approx(float(node["fn"].log_prob(node["value"])), rel=1e-10)
            lp = -float(post.potential({"u": post.unconstrain(values)}))  # stored values: logit round-off
            assert float(dt["sample_stats"]["lp"][c, d]) == pytest.approx(lp, rel=1e-5)
        u = torch.as_tensor(np.random.default_rng(0).normal(size=(3, post.dim)))
        _, lp = draw_statistics(post, u)
        np.testing.assert_allclose(lp, [float(post.log_density(v)) for v in u], rtol=1e-10)


def test_arviz_summary_and_loo_run_on_the_file(run):
    import arviz as az

    post, _, dt = run
    table = az.summary(dt)
    assert set(post.names) <= set(table.index)
    loo = az.loo(dt)
    assert loo.n_data_points == post.weights.numel()
    assert np.isfinite(loo.elpd)


def test_sample_stats_match_the_sampler(run):
    _, samples, dt = run
    stats = dt["sample_stats"]
    np.testing.assert_array_equal(stats["diverging"].values, samples.diverging)
    np.testing.assert_allclose(stats["accepted"].values.mean(1), samples.acceptance_rates, atol=1e-12)
    np.testing.assert_allclose(stats["step_size"].values, np.array(samples.step_sizes)[:, None] * np.ones((1, 100)))
    n_steps, depth = stats["n_steps"].values, stats["tree_depth"].values
    assert n_steps.min() >= 1 and n_steps.max() <= 2**8 - 1
    assert np.all((2 ** (depth - 1) <= n_steps) & (n_steps <= 2**depth - 1))


def test_prior_draws_follow_the_prior(run):
    post, _, dt = run
    for k, name in enumerate(PARAM_NAMES):
        x = dt["prior"][name].values.ravel()
        lo, hi = post.emulator.param_bounds[k]
        assert lo <= x.min() and x.max() <= hi
        assert x.mean() == pytest.approx((lo + hi) / 2, abs=0.06 * (hi - lo))  # uniform: sd of the mean 0.009
    sigma = dt["prior"]["sigma_xx"].values.ravel()
    assert sigma.min() > 0 and np.median(sigma) == pytest.approx(post.noise_scale, rel=0.15)  # HalfCauchy median
    scale = dt["prior"]["emulator_scale"].values.ravel()  # InverseGamma(a, a - 1): mean 1 when a > 1
    a, b = post.scale_prior
    assert b == pytest.approx(a - 1) and np.median(scale) == pytest.approx(invgamma(a, scale=b).median(), rel=0.15)


def test_known_noise_and_fixed_gp_variance_are_recorded(known_run):
    post, _, dt = known_run
    constant = dt["constant_data"]
    np.testing.assert_allclose(constant["noise_sd"], np.sqrt(post.noise_var.numpy()).ravel())
    gp = torch.diagonal(post.fixed_gp_cov, dim1=-2, dim2=-1).T  # (n_obs, G)
    np.testing.assert_allclose(constant["gp_variance"], gp.numpy().ravel())
    np.testing.assert_allclose(
        constant["held_out_excess"], np.tile(post.emulator.held_out_excess.variance, len(post.weights))
    )
    assert dt.attrs["emulator_error"] == "on"
    np.testing.assert_allclose(constant["stated_sd"], [[1e-4, 2e-4, 1e-4]])
    assert set(dt["posterior"].data_vars) == set(PARAM_NAMES)  # no noise sigma, no emulator scale
    assert dt.attrs["noise"] == "known" and dt.attrs["gp_variance"] == "mode"


# -- bad input: one line, exit code 2 -------------------------------------------------------------
def infer(capsys, emulator_dir, tmp_path, measurement) -> tuple[int, list[str]]:
    code = main(
        [
            "infer",
            "--emulator",
            str(emulator_dir),
            "--measurement",
            str(measurement),
            "--out",
            str(tmp_path / "post"),
            "--quiet",
        ]
    )
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize(
    "alpha, t, message",
    [
        ((0.08, -0.05), 1.0, "alpha11*t = 0.08 is outside the emulator's training range [0.025, 0.05] of alpha11*t"),
        ((0.05, -0.05), 0.25, "alpha11*t = 0.0125 is outside the emulator's training range [0.025, 0.05]"),
        ((0.05, 0.07), 1.0, "alpha22*t = 0.07 is outside the emulator's training range [-0.05, 0.05]"),
    ],
)
def test_designs_and_frames_outside_the_training_range_are_refused(
    capsys, emulator, emulator_dir, tmp_path, alpha, t, message
):
    strain = np.zeros((len(emulator.xy), 3))
    path = write_measurement(tmp_path / "m.csv", emulator.xy, strain, alpha, t)
    code, lines = infer(capsys, emulator_dir, tmp_path, path)
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith("skinid infer: error: ") and message in lines[0]
    assert not (tmp_path / "post").exists()


def test_a_zero_stated_noise_sd_is_refused(capsys, emulator, emulator_dir, tmp_path):
    strain, sd = np.zeros((len(emulator.xy), 3)), np.full((len(emulator.xy), 3), 1e-4)
    sd[5, 1] = 0.0
    path = write_measurement(tmp_path / "m.csv", emulator.xy, strain, (0.05, 0.0), 1.0, sd=sd)
    code, lines = infer(capsys, emulator_dir, tmp_path, path)
    assert code == 2 and len(lines) == 1 and "standard deviations must be > 0" in lines[0]
    # observations made through the API are checked when they are projected
    observation = Observation(
        np.array([0.05, 0.0]), 1.0, strain, np.ones(len(strain), bool), sd=np.zeros(3), source="api"
    )
    with pytest.raises(
        ValueError,
        match=r"api \(alpha11 = 0.05, alpha22 = 0, t = 1\): the stated noise sd "
        r"\[0.0, 0.0, 0.0\] \(xx, yy, xy\) must be positive and finite",
    ):
        ObservedWeights.project(emulator, [observation])


@pytest.mark.parametrize("t", [0.0, 1.5, float("nan")])
def test_an_api_observation_outside_the_load_fraction_range_is_refused(emulator, t):
    strain = np.zeros((len(emulator.xy), 3))
    observation = Observation(np.array([0.05, 0.0]), t, strain, np.ones(len(strain), bool), source="api")
    with pytest.raises(ValueError, match=rf"api \(.*\): the load fraction t = {t} must be in \(0, 1\]"):
        ObservedWeights.project(emulator, [observation])


def test_a_non_positive_noise_scale_is_refused(emulator, dataset):
    observed = ObservedWeights.project(emulator, from_dataset(dataset, 10, designs=[0]))
    with pytest.raises(ValueError, match="noise_scale .* must be > 0, got 0"):
        SkinPosterior(emulator, observed, noise_scale=0.0)


def test_the_parameter_shift_is_recorded_with_its_coupling(emulator, dataset):
    """With '--emulator-error shift' constant_data holds U (datum, 5): U U^T is the coupling the
    likelihood adds between any two data (the coupled covariance minus its per-PC blocks,
    reordered from (pc, observation) to the file's datum order)."""
    from inference.model import coupled_covariance
    from inference.posterior_file import data_groups

    observations = from_dataset(dataset, 10, designs=[0, 2], frames=[-1])
    post = SkinPosterior(emulator, ObservedWeights.project(emulator, observations), emulator_shift=True)
    post.fix_gp_variance(dataset.params[3])
    factor = data_groups(post)["constant_data"]["parameter_shift_factor"]
    blocks = post.model_covariance(post.fixed_gp_cov)
    coupling = (coupled_covariance(blocks, post.fixed_shift, 1.0) - torch.block_diag(*blocks)).numpy()
    n_obs, n_weights = post.weights.shape
    order = (np.arange(n_weights)[None, :] * n_obs + np.arange(n_obs)[:, None]).ravel()  # datum -> (g, o) index
    np.testing.assert_allclose(factor @ factor.T, coupling[np.ix_(order, order)], rtol=1e-12, atol=1e-15)
    assert np.abs(factor).max() > 0
