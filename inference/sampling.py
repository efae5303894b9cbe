"""NUTS sampling of a :class:`~inference.model.SkinPosterior` and its diagnostics.

Chains run in parallel worker processes (``spawn``), one torch thread each (torch's default
intra-op threading makes these tiny operations several times slower); the processes start
before the mode is found, so that their imports overlap with it. Each chain starts near
the posterior mode (found by L-BFGS from several seeded starts) with a seeded jitter and with
the Laplace covariance there (inverse Hessian of the potential) as its initial inverse mass
matrix, adapts its step size and a dense mass matrix during warm-up, and returns its draws in
the constrained parameters (theta in degrees). Starting from the Laplace metric instead of
the identity, and keeping it until a mass-matrix estimate has at least ``FIRST_WINDOW`` draws,
halves the leapfrog steps of warm-up.

What a run records and writes: :mod:`inference.posterior_file`.

The kernel is set up through Pyro's public interface only (:func:`_nuts_kernel`), and sampler
statistics come from it too: divergences and the acceptance rate from ``MCMC.diagnostics()``,
the step size from ``NUTS.step_size`` in the ``hook_fn`` Pyro calls
after every iteration, the leapfrog steps by counting calls of our own potential (NUTS evaluates
it once per leapfrog step), whether the chain moved by comparing successive draws in that hook.
The Hamiltonian energy is not recorded: Pyro's NUTS does not expose the momentum.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import sys
import time
import warnings
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import dataclass
from functools import partial
from importlib import metadata
from queue import Empty

import numpy as np
import torch

from inference.model import SkinPosterior, prior_draws
from inference.posterior_file import GROUP_ATTRS, PosteriorSamples, data_groups

N_PRIOR_DRAWS = 1000


def find_mode(posterior: SkinPosterior, n_starts: int = 8, seed: int = 0) -> np.ndarray:
    """Unconstrained vector of the highest posterior density found from ``n_starts`` starts."""
    rng = np.random.default_rng(seed)
    best, best_value = None, -np.inf
    latent0 = posterior.initial_latents()
    for k in range(n_starts):
        start = np.concatenate([rng.normal(0, 1.0, 5) if k else np.zeros(5), latent0])
        u = torch.tensor(start, dtype=torch.float64, requires_grad=True)
        opt = torch.optim.LBFGS([u], lr=1.0, max_iter=200, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = -posterior.log_density(u)
            loss.backward()
            return loss

        try:
            opt.step(closure)
        except RuntimeError:
            continue
        with torch.no_grad():
            value = float(posterior.log_density(u))
        if np.isfinite(value) and value > best_value:
            best, best_value = u.detach().numpy().copy(), value
    if best is None:
        raise RuntimeError("no finite posterior density found; check the observations")
    return best


def prepare(posterior: SkinPosterior, seed: int = 0) -> np.ndarray:
    """Find the mode; with ``gp_variance="mode"`` fix the GP variance there (twice: it moves)."""
    mode = find_mode(posterior, seed=seed)
    if posterior.gp_variance == "mode":
        for _ in range(2):
            posterior.fix_gp_variance(posterior.constrain(torch.as_tensor(mode))[:5].numpy())
            mode = find_mode(posterior, n_starts=2, seed=seed)
    return mode


def laplace_inverse_mass(posterior: SkinPosterior, mode: np.ndarray, floor: float = 1e-2) -> np.ndarray:
    """Inverse Hessian of the potential at ``mode`` (dim, dim), eigenvalues of H floored.

    At a mode on the prior box's edge or along an unidentified direction the Hessian can be
    near-singular or indefinite; flooring its eigenvalues at ``floor`` keeps the metric
    positive definite and bounded (the adaptation corrects it during warm-up).
    """
    u = torch.as_tensor(mode, dtype=torch.float64)
    hessian = -torch.autograd.functional.hessian(posterior.log_density, u).numpy()
    eigenvalues, vectors = np.linalg.eigh(0.5 * (hessian + hessian.T))
    if not np.all(np.isfinite(eigenvalues)):
        return np.eye(len(mode))
    return (vectors / np.maximum(eigenvalues, floor)) @ vectors.T


FIRST_WINDOW = 100  # fewest warm-up draws a mass-matrix estimate may replace the Laplace metric with
MAX_TREE_DEPTH, TARGET_ACCEPT = 8, 0.8
# A run whose share of divergent transitions exceeds RESAMPLE_SHARE is run again at
# RESAMPLE_ACCEPT (smaller leapfrog steps). Unknown noise (HalfCauchy) with a few weights per
# sigma makes a funnel: where sigma is small the emulator's error floor alone sets the
# parameters' widths, where it is large they are free, and a step size adapted to one end
# diverges at the other (benchmarks/divergences.py, docs/inference.md).
RESAMPLE_SHARE, RESAMPLE_ACCEPT = 0.005, 0.95


def _nuts_kernel(
    posterior: SkinPosterior,
    inverse_mass: np.ndarray,
    potential_fn=None,
    first_window: int = FIRST_WINDOW,
    target_accept: float = TARGET_ACCEPT,
):
    """Pyro's NUTS on ``potential_fn`` (default ``posterior.potential``) whose warm-up starts
    from ``inverse_mass``, through Pyro's public interface only.

    The metric is Pyro's ``BlockMassMatrix`` (dense, one block) given to the kernel through its
    public ``mass_matrix_adapter`` property; when the kernel is set up, the adapter's
    ``configure`` sets the inverse mass matrix to ``inverse_mass``, and NUTS then finds its
    initial step size for that metric. Pyro's warm-up windows are Stan's (75-step buffer, then
    mass-matrix windows of 25, 50, 100, ... steps, 50-step end buffer) and cannot be set
    publicly; instead a window's estimate replaces the metric only once it holds at least
    ``first_window`` draws -- shorter windows keep the Laplace metric and their draws go into the
    next window's estimate -- so a noisy 25-draw estimate never replaces the Laplace metric.
    (Pyro still restarts its step-size adaptation at the end of such a window.)
    """
    from pyro.infer import NUTS
    from pyro.infer.mcmc.adaptation import BlockMassMatrix

    inverse_mass = np.asarray(inverse_mass, dtype=np.float64)

    class LaplaceStartedMassMatrix(BlockMassMatrix):
        def configure(self, mass_matrix_shape, adapt_mass_matrix=True, options=None):
            options = options or {}
            super().configure(mass_matrix_shape, adapt_mass_matrix, options=options)
            shapes = list(mass_matrix_shape.values())
            if len(shapes) != 1 or tuple(shapes[0]) != inverse_mass.shape:
                raise ValueError(f"a dense {inverse_mass.shape} metric cannot start mass matrices {shapes}")
            self.inverse_mass_matrix = {sites: torch.as_tensor(inverse_mass, **options) for sites in mass_matrix_shape}
            self.window_draws = 0

        def update(self, z, z_grad):
            super().update(z, z_grad)
            self.window_draws += 1

        def end_adaptation(self):
            if self.window_draws >= first_window:  # else: keep the metric, keep accumulating draws
                super().end_adaptation()
                self.window_draws = 0

    potential_fn = posterior.potential if potential_fn is None else potential_fn
    kernel = NUTS(
        potential_fn=potential_fn,
        adapt_step_size=True,
        adapt_mass_matrix=True,
        full_mass=True,
        target_accept_prob=target_accept,
        max_tree_depth=MAX_TREE_DEPTH,
    )
    kernel.mass_matrix_adapter = LaplaceStartedMassMatrix()
    return kernel


class _ChainRecorder:
    """Per-iteration NUTS statistics through public routes: :meth:`potential` is the potential
    NUTS gets (it counts the calls: one per leapfrog step), :meth:`hook` is MCMC's ``hook_fn``
    (called after every warm-up and sampling iteration with the kernel and the new draw)."""

    def __init__(self, potential_fn, init: torch.Tensor):
        self.potential_fn, self.previous, self.queue = potential_fn, init, _PROGRESS
        self.calls = self.calls_seen = 0
        self.n_steps, self.step_size, self.moved = [], [], []

    def potential(self, sites: dict[str, torch.Tensor]) -> torch.Tensor:
        self.calls += 1
        return self.potential_fn(sites)

    def hook(self, kernel, samples, stage, i) -> None:
        self.n_steps.append(self.calls - self.calls_seen)
        self.calls_seen = self.calls
        self.step_size.append(float(kernel.step_size))
        u = samples["u"].detach()
        self.moved.append(not torch.equal(u, self.previous))
        self.previous = u.clone()
        if self.queue is not None and len(self.n_steps) % PROGRESS_EVERY == 0:
            self.queue.put(PROGRESS_EVERY)

    def report_rest(self) -> None:
        """Report the iterations since the last report (the chain has ended)."""
        if self.queue is not None and len(self.n_steps) % PROGRESS_EVERY:
            self.queue.put(len(self.n_steps) % PROGRESS_EVERY)

    def statistics(self, draws: int) -> dict[str, np.ndarray]:
        """(draws,) per statistic of the last ``draws`` iterations (the sampling phase).

        ``tree_depth`` = ceil(log2(n_steps + 1)): the trajectory doublings NUTS started (a
        depth-d tree has 2^d - 1 leapfrog steps; a doubling cut short by a U-turn or a
        divergence inside it counts).
        """
        n_steps = np.array(self.n_steps[-draws:], dtype=np.int64)
        return {
            "step_size": np.array(self.step_size[-draws:]),
            "n_steps": n_steps,
            "tree_depth": np.ceil(np.log2(n_steps + 1)).astype(np.int64),
            "accepted": np.array(self.moved[-draws:], dtype=bool),
        }


def draw_statistics(posterior: SkinPosterior, u: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Per-datum log-likelihood (n, n_obs, G) and log density ``lp`` (n,) (= -potential,
    Jacobian included) at unconstrained draws u (n, dim).

    One draw at a time: the emulator then sees the inputs the sampler gave it, with the same
    round-off (a batched GP mean sums in another order; ill-conditioned GPs make that visible).
    """
    with torch.no_grad():
        terms = torch.stack([posterior.pointwise_log_likelihood(posterior.constrain(v)) for v in u])
        lp = terms.sum((-2, -1)) + posterior.log_prior_and_jacobian(u)
    return terms.numpy(), lp.numpy()


@dataclass
class ChainResult:
    draws: np.ndarray  # (n_draws, dim) constrained
    diverging: np.ndarray  # (n_draws,) bool
    step_size: float
    seconds: float
    acceptance_rate: float  # Pyro's: share of iterations that moved
    stats: dict[str, np.ndarray]  # (n_draws,) per sampler statistic
    log_likelihood: np.ndarray  # (n_draws, n_obs, G)


@contextlib.contextmanager
def quiet_overflow():
    """Silence the only warnings a chain raises: numpy's floating-point RuntimeWarnings in
    :class:`~inference.density.FusedLogDensity` ("overflow encountered in exp", "... in square",
    "invalid value encountered in multiply", ...) where a NUTS trajectory (the step-size search, a
    divergent transition) reaches |u| of hundreds. The potential there is inf or NaN, which NUTS
    treats as a divergence: the trajectory stops (after warm-up, it is counted in the summary).
    Every other warning still shows."""
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", r"(overflow|invalid value|divide by zero) encountered", RuntimeWarning, r"inference\.density"
        )
        yield


def _run_chain(
    posterior: SkinPosterior,
    init: np.ndarray,
    inverse_mass: np.ndarray,
    warmup: int,
    draws: int,
    seed: int,
    target_accept: float,
) -> ChainResult:
    from pyro.infer import MCMC

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    start = time.perf_counter()
    init = torch.as_tensor(init)
    recorder = _ChainRecorder(posterior.potential, init)
    kernel = _nuts_kernel(posterior, inverse_mass, recorder.potential, target_accept=target_accept)
    mcmc = MCMC(
        kernel,
        num_samples=draws,
        warmup_steps=warmup,
        initial_params={"u": init},
        disable_progbar=True,
        hook_fn=recorder.hook,
    )
    with quiet_overflow():
        mcmc.run()
    recorder.report_rest()
    u = mcmc.get_samples()["u"]
    with torch.no_grad():
        values = posterior.constrain(u).numpy()
    diagnostics = mcmc.diagnostics()
    diverging = np.zeros(draws, dtype=bool)
    diverging[np.asarray(diagnostics["divergences"]["chain 0"], dtype=int)] = True
    stats = recorder.statistics(draws)
    log_likelihood, stats["lp"] = draw_statistics(posterior, u)
    return ChainResult(
        values,
        diverging,
        float(kernel.step_size),
        time.perf_counter() - start,
        float(diagnostics["acceptance rate"]["chain 0"]),
        stats,
        log_likelihood,
    )


def file_attrs(
    posterior: SkinPosterior, chains: int, warmup: int, draws: int, seed: int, target_accept: float
) -> dict[str, dict]:
    """Attributes of ``posterior.nc``: the run's settings and versions (root) and each group's notes."""
    root = {
        "skinid_version": metadata.version("skinid"),
        "pyro_version": metadata.version("pyro-ppl"),
        "sampler": "NUTS, dense mass matrix",
        "seed": seed,
        "chains": chains,
        "warmup": warmup,
        "draws": draws,
        "max_tree_depth": MAX_TREE_DEPTH,
        "target_accept_prob": target_accept,
        "noise": posterior.noise,
        "noise_scale": posterior.noise_scale,
        "gp_variance": posterior.gp_variance,
        "emulator_error": (
            "scaled"
            if posterior.scale_prior
            else "shift"
            if posterior.shift
            else "on"
            if posterior.emulator_error
            else "off"
        ),
    }
    prior = {"draws": f"{N_PRIOR_DRAWS} draws of inference.model.pyro_prior, seed {seed}"}
    return {"/": root, "prior": prior, **GROUP_ATTRS}


_PROGRESS = None  # in a chain process: the queue its chains report their iterations to
PROGRESS_EVERY = 50  # iterations between two reports


def _start_worker(progress) -> None:
    """Initializer of a chain process: keep the progress queue and import what a chain needs
    now, while the parent process finds the mode, not when the first chain arrives."""
    global _PROGRESS
    _PROGRESS = progress
    import pyro.infer  # noqa: F401


@dataclass
class _ChainWorkers:
    """Spawned chain processes and their progress queue (None: the chains run in this process)."""

    pool: ProcessPoolExecutor | None = None
    progress: object = None


@contextlib.contextmanager
def _chain_workers(n_jobs: int):
    """Start ``n_jobs`` chain processes at once (each imports torch and Pyro) and yield
    them as :class:`_ChainWorkers`; shut them down on exit."""
    if n_jobs == 1:
        yield _ChainWorkers()
        return
    ctx = mp.get_context("spawn")
    progress = ctx.Queue()
    with ProcessPoolExecutor(n_jobs, mp_context=ctx, initializer=_start_worker, initargs=(progress,)) as pool:
        for _ in range(n_jobs):
            pool.submit(int)  # a no-op task per worker spawns it now
        yield _ChainWorkers(pool, progress)


def _run_chains(
    posterior: SkinPosterior,
    inits: list[np.ndarray],
    inverse_mass: np.ndarray,
    warmup: int,
    draws: int,
    seeds: list[int],
    workers: _ChainWorkers,
    bar,
    target_accept: float,
) -> list[ChainResult]:
    """One chain per start in ``inits`` on ``workers`` (in this process when it has none),
    advancing the progress ``bar`` (or None) as they go."""
    if workers.pool is None:
        results = []
        for c in range(len(inits)):
            results.append(_run_chain(posterior, inits[c], inverse_mass, warmup, draws, seeds[c], target_accept))
            if bar is not None:
                bar.update(warmup + draws)
        return results
    pool = workers.pool
    futures = [
        pool.submit(_run_chain, posterior, inits[c], inverse_mass, warmup, draws, seeds[c], target_accept)
        for c in range(len(inits))
    ]
    pending, reported = futures, 0
    while pending:
        done, pending = wait(pending, timeout=0.2, return_when=FIRST_EXCEPTION)
        reported += _advance(bar, workers.progress)
        error = next((f.exception() for f in done if f.exception() is not None), None)
        if error is not None:
            pool.shutdown(cancel_futures=True)  # drop the chains not started yet
            raise error
    _advance(bar, workers.progress, len(inits) * (warmup + draws) - reported)  # reports still on their way
    return [f.result() for f in futures]


def _advance(bar, queue, wait_for: int = 0, timeout: float = 10.0) -> int:
    """Advance ``bar`` (or None) by the iterations reported to ``queue`` so far, waiting up to
    ``timeout`` s for each report until ``wait_for`` iterations are read; return the count read."""
    read = 0
    while True:
        try:
            n = queue.get(timeout=timeout) if read < wait_for else queue.get_nowait()
        except Empty:
            return read
        read += n
        if bar is not None:
            bar.update(n)


def sample_posterior(
    posterior: SkinPosterior,
    chains: int = 4,
    warmup: int = 500,
    draws: int = 1000,
    seed: int = 0,
    n_jobs: int = 2,
    progress: bool = True,
    target_accept: float = TARGET_ACCEPT,
    resample: bool = True,
) -> PosteriorSamples:
    """Run ``chains`` NUTS chains (``n_jobs`` at a time) from around the posterior mode at
    ``target_accept``; when more than RESAMPLE_SHARE of their transitions diverge (and
    ``resample``), run them again at RESAMPLE_ACCEPT."""
    start = time.perf_counter()
    with _chain_workers(max(1, min(n_jobs, chains))) as workers:  # they start while the mode is found
        mode = prepare(posterior, seed=seed)
        inverse_mass = laplace_inverse_mass(posterior, mode)
        rng = np.random.default_rng(seed)
        inits = [mode + rng.normal(0, 0.1, size=mode.shape) for _ in range(chains)]
        seeds = [seed * 1000 + c for c in range(chains)]
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=chains * (warmup + draws), desc="NUTS", unit="it", file=sys.stderr)
        run = partial(_run_chains, posterior, inits, inverse_mass, warmup, draws, seeds, workers, bar)
        first_target_accept, diverged_before = target_accept, None
        results = run(target_accept)
        diverged = sum(int(r.diverging.sum()) for r in results)
        if resample and target_accept < RESAMPLE_ACCEPT and diverged > RESAMPLE_SHARE * chains * draws:
            if bar is not None:
                bar.total += chains * (warmup + draws)
            target_accept, diverged_before = RESAMPLE_ACCEPT, diverged
            results = run(target_accept)
        if bar is not None:
            bar.close()
    samples = PosteriorSamples(
        names=posterior.names,
        draws=np.stack([r.draws for r in results]),
        diverging=np.stack([r.diverging for r in results]),
        step_sizes=[r.step_size for r in results],
        seconds=time.perf_counter() - start,
        truth=posterior.observed.truth,
        bounds=posterior.emulator.param_bounds,
        acceptance_rates=[r.acceptance_rate for r in results],
        stats={name: np.stack([r.stats[name] for r in results]) for name in results[0].stats},
        log_likelihood=np.stack([r.log_likelihood for r in results]),
        prior=prior_draws(posterior, N_PRIOR_DRAWS, seed),
        data=data_groups(posterior),
        attrs=file_attrs(posterior, chains, warmup, draws, seed, target_accept),
        divergences_before_resampling=diverged_before,
        first_target_accept=first_target_accept,
    )
    if posterior.gp_variance == "mode":
        samples.gp_variance_spread = posterior.gp_variance_spread(samples.draws[..., :5].reshape(-1, 5))
    medians = np.median(samples.draws.reshape(-1, posterior.dim), axis=0)
    samples.error_budget, samples.error_budget_at = posterior.error_budget(medians), medians[:5]
    samples.model_warnings = tuple(posterior.model_warnings(medians[-1] if posterior.scale_prior else None))
    return samples
