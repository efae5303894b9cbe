"""NUTS sampling of a :class:`~inference.model.SkinPosterior`, diagnostics and outputs.

Chains run in parallel worker processes (``spawn``), one torch thread each (torch's default
intra-op threading makes these tiny operations several times slower); the processes start
before the mode is found, so that their imports overlap with it. Each chain starts near
the posterior mode (found by L-BFGS from several seeded starts) with a seeded jitter and with
the Laplace covariance there (inverse Hessian of the potential) as its initial inverse mass
matrix, adapts its step size and a dense mass matrix during warm-up, and returns its draws in
the constrained parameters (theta in degrees). Starting from the Laplace metric instead of
the identity, and keeping it until a mass-matrix estimate has at least ``FIRST_WINDOW`` draws,
halves the leapfrog steps of warm-up.

Outputs (:func:`write_outputs`): ArviZ ``posterior.nc`` (groups posterior, sample_stats,
log_likelihood, observed_data, prior, constant_data: :meth:`PosteriorSamples.inference_data`),
``summary.json`` (:class:`PosteriorSummary`: median, 95 % interval, R-hat, bulk/tail ESS per
:class:`ParameterSummary`, divergences, acceptance rates, the true value when known) and ``corner.png``.

The kernel is set up through Pyro's public interface only (:func:`_nuts_kernel`), and sampler
statistics come from it too: divergences and the acceptance rate from ``MCMC.diagnostics()``,
the step size from ``NUTS.step_size`` in the ``hook_fn`` Pyro calls
after every iteration, the leapfrog steps by counting calls of our own potential (NUTS evaluates
it once per leapfrog step), whether the chain moved by comparing successive draws in that hook.
The Hamiltonian energy is not recorded: Pyro's NUTS does not expose the momentum.
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import sys
import time
import warnings
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, fields
from functools import partial
from importlib import metadata
from pathlib import Path
from queue import Empty
from typing import ClassVar

import numpy as np
import torch

from inference.model import ErrorBudget, GpVarianceSpread, ObservedFields, SkinPosterior, prior_draws
from skinfem.config import PARAM_NAMES
from skinfem.io import COMPONENTS
from skinfem.outputs import write_atomically

RHAT_LIMIT, ESS_LIMIT = 1.01, 400
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


# dimensions of the variables of posterior.nc beyond (chain, draw); datum = (observation, PC weight)
DIMS = {
    "weights": ["datum"],
    "datum_observation": ["datum"],
    "datum_component": ["datum"],
    "datum_pc": ["datum"],
    "noise_sd": ["datum"],
    "gp_variance": ["datum"],
    "truncation_variance": ["datum"],
    "held_out_excess": ["datum"],
    "parameter_shift_factor": ["datum", "shift_direction"],
    "alpha11": ["observation"],
    "alpha22": ["observation"],
    "t": ["observation"],
    "alpha11_t": ["observation"],
    "alpha22_t": ["observation"],
    "source": ["observation"],
    "stated_sd": ["observation", "component"],
    "cell_x": ["cell"],
    "cell_y": ["cell"],
    "strain_field": ["observation", "cell", "component"],
    "prior_lower": ["parameter"],
    "prior_upper": ["parameter"],
    "truth": ["parameter"],
}
COORDS = {"component": list(COMPONENTS), "parameter": list(PARAM_NAMES)}
GROUP_ATTRS = {
    "sample_stats": {
        "diverging": "the transition diverged (Pyro's MCMC.diagnostics)",
        "step_size": "leapfrog step size (NUTS.step_size)",
        "n_steps": "leapfrog steps of the transition (calls of the potential)",
        "tree_depth": "trajectory doublings started, ceil(log2(n_steps + 1))",
        "accepted": "the chain moved to a new point; its mean per chain is Pyro's acceptance rate",
        "lp": "log posterior density of the sampled unconstrained vector, Jacobian included (= -potential)",
        "energy": "not recorded: Pyro's NUTS does not expose the momentum of a draw",
    },
    "log_likelihood": {
        "weights": "log density of each whitened PC weight (datum: see constant_data datum_*): the weights of one "
        "PC are correlated across observations by the emulator's error, so the terms are those of "
        "L^-1 w (L the Cholesky factor of that PC's covariance, or of every datum's with emulator_error "
        "'shift'); they sum to the likelihood NUTS samples",
    },
    "observed_data": {
        "weights": "PC weights of the observed log strains (masked least-squares projection on the emulator's "
        "PCA basis); raw, not whitened; covariance per PC over the observations: emulator_scale x (GP + "
        "held-out excess + PCA truncation) + noise, plus the parameter shift J C J^T over every PC with "
        "emulator_error 'shift' (inference.model)",
    },
    "constant_data": {
        "noise": "no spatial correlation: 'known' carries the stated sd of independent skin cells through the "
        "projection (noise_sd, PC-weight units); 'halfcauchy' has one sigma per strain component",
        "strain_field": "observed log strain on the emulator's skin cells (cell_x, cell_y [mm]); NaN: masked",
        "held_out_excess": "variance of the emulator's error on held-out materials beyond the GP's, per datum "
        "(PC-weight units); with emulator_error 'shift' the part the parameter shift leaves",
        "parameter_shift_factor": "U with J C J^T = U U^T, the parameter shift's covariance between any two data "
        "(emulator_error 'shift'; at the mode, with gp_variance; PC-weight units)",
    },
}


def data_groups(posterior: SkinPosterior) -> dict[str, dict[str, np.ndarray]]:
    """observed_data and constant_data of ``posterior.nc``: arrays by variable (dims in DIMS).

    Datum d = o * G + g is PC weight g (of G) of observation o.
    """
    observed = posterior.observed
    n_obs = len(observed.weights)
    n_weights = posterior.emulator.n_weights
    constant = {
        "alpha11_t": observed.design_inputs[:, 0],
        "alpha22_t": observed.design_inputs[:, 1],
        "datum_observation": np.repeat(np.arange(n_obs), sum(n_weights.values())),
        "datum_component": np.tile(np.concatenate([[c] * m for c, m in n_weights.items()]), n_obs),
        "datum_pc": np.tile(np.concatenate([np.arange(m) for m in n_weights.values()]), n_obs),
        "prior_lower": posterior.emulator.param_bounds[:, 0],
        "prior_upper": posterior.emulator.param_bounds[:, 1],
    }
    if posterior.noise == "known":
        constant["noise_sd"] = np.sqrt(observed.noise_var).ravel()
    if posterior.variance_is_fixed:
        constant["gp_variance"] = torch.diagonal(posterior.fixed_gp_cov, dim1=-2, dim2=-1).T.numpy().ravel()
    constant["truncation_variance"] = posterior.truncation_var.numpy().ravel()
    constant["held_out_excess"] = torch.diagonal(posterior.excess_cov, dim1=-2, dim2=-1).T.numpy().ravel()
    if posterior.fixed_shift is not None:  # (G, n_obs, k) -> (datum, k)
        constant["parameter_shift_factor"] = posterior.fixed_shift.numpy().transpose(1, 0, 2).reshape(-1, 5)
    if observed.truth is not None:
        constant["truth"] = observed.truth
    if observed.fields is not None:
        constant.update(_field_constants(observed.fields))
    return {"observed_data": {"weights": observed.weights.ravel()}, "constant_data": constant}


def _field_constants(fields: ObservedFields) -> dict[str, np.ndarray]:
    """Designs, load fractions, sources, cells, observed strain fields and stated sd."""
    out = {
        "alpha11": fields.alpha[:, 0],
        "alpha22": fields.alpha[:, 1],
        "t": fields.t,
        "source": np.array(fields.sources, dtype=str),
        "cell_x": fields.xy[:, 0],
        "cell_y": fields.xy[:, 1],
        "strain_field": fields.strain,
    }
    if fields.sd is not None:
        out["stated_sd"] = fields.sd
    return out


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


@dataclass(frozen=True)
class ParameterSummary:
    """One sampled parameter of ``summary.json``, in its unit (theta in degrees, sigma in PC-weight
    units, the emulator scale lambda a factor on the emulator's error variance).

    ``prior`` and ``interval_share_of_prior`` are given for the five skin parameters only, ``true``
    and ``covered`` when the truth is known; they are left out of ``summary.json`` otherwise.
    """

    median: float
    q2_5: float  # 2.5 % quantile of the draws ("q2.5" in summary.json)
    q97_5: float  # 97.5 % quantile ("q97.5")
    r_hat: float  # rank-normalised split R-hat (ArviZ)
    ess_bulk: float
    ess_tail: float
    prior: tuple[float, float] | None = None  # bounds of the uniform prior
    interval_share_of_prior: float | None = None  # (q97_5 - q2_5) / prior range [-]
    true: float | None = None
    covered: bool | None = None  # q2_5 <= true <= q97_5

    JSON_KEYS: ClassVar[dict[str, str]] = {"q2_5": "q2.5", "q97_5": "q97.5"}  # attribute -> summary.json key

    @property
    def ess(self) -> float:
        """The smaller of the bulk and tail effective sample sizes."""
        return min(self.ess_bulk, self.ess_tail)

    def to_json(self) -> dict:
        """The entry of ``summary.json`` ("parameters" -> name)."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None or f.default is not None:
                out[self.JSON_KEYS.get(f.name, f.name)] = list(value) if isinstance(value, tuple) else value
        return out

    @classmethod
    def from_json(cls, entry: dict) -> ParameterSummary:
        """Read an entry of ``summary.json``'s "parameters"."""
        attributes = {v: k for k, v in cls.JSON_KEYS.items()}
        values = {attributes.get(k, k): v for k, v in entry.items()}
        if values.get("prior") is not None:
            values["prior"] = tuple(values["prior"])
        return cls(**values)


@dataclass(frozen=True)
class PosteriorSummary:
    """What ``summary.json`` holds (:func:`write_outputs`); :meth:`to_json` is its exact content.

    Files written before ``acceptance_rates``, ``gp_variance_over_posterior`` or the error budget
    were recorded read with those empty or None.
    """

    parameters: dict[str, ParameterSummary]  # mu, k1, k2, kappa, theta, sigma_<component>, emulator_scale
    chains: int
    draws_per_chain: int
    divergences: int  # divergent transitions after warm-up, all chains
    step_sizes: tuple[float, ...]  # per chain, at the end of warm-up
    acceptance_rates: tuple[float, ...]  # Pyro's, per chain
    seconds: float  # wall time of the mode search and the chains
    gp_variance_over_posterior: GpVarianceSpread | None  # with the GP variance fixed at the mode
    error_budget: ErrorBudget | None  # at the posterior medians
    error_budget_statement: str | None  # which term limits the intervals
    warnings: tuple[str, ...]  # the model's, then R-hat, ESS and divergences
    observations: tuple[str, ...] | None = None  # sources of the observations, when given

    @property
    def max_r_hat(self) -> float:
        """The largest R-hat over all parameters (noise sigmas and emulator scale included)."""
        return max(p.r_hat for p in self.parameters.values())

    @property
    def min_ess(self) -> float:
        """The smallest bulk or tail ESS over all parameters (noise sigmas and emulator scale included)."""
        return min(p.ess for p in self.parameters.values())

    def to_json(self) -> dict:
        """The content of ``summary.json`` (JSON types; keys in the file's order)."""
        out = {
            "parameters": {n: p.to_json() for n, p in self.parameters.items()},
            "chains": self.chains,
            "draws_per_chain": self.draws_per_chain,
            "divergences": self.divergences,
            "step_sizes": list(self.step_sizes),
            "acceptance_rates": list(self.acceptance_rates),
            "seconds": self.seconds,
            "gp_variance_over_posterior": _asdict_or_none(self.gp_variance_over_posterior),
            "error_budget": _asdict_or_none(self.error_budget),
            "error_budget_statement": self.error_budget_statement,
            "warnings": list(self.warnings),
        }
        if self.observations is not None:
            out["observations"] = list(self.observations)
        return out

    @classmethod
    def from_json(cls, summary: dict) -> PosteriorSummary:
        """Read the content of a ``summary.json`` (see the class doc for older files)."""
        spread, budget = summary.get("gp_variance_over_posterior"), summary.get("error_budget")
        observations = summary.get("observations")
        return cls(
            parameters={n: ParameterSummary.from_json(e) for n, e in summary["parameters"].items()},
            chains=summary["chains"],
            draws_per_chain=summary["draws_per_chain"],
            divergences=summary["divergences"],
            step_sizes=tuple(summary["step_sizes"]),
            acceptance_rates=tuple(summary.get("acceptance_rates", ())),
            seconds=summary["seconds"],
            gp_variance_over_posterior=None if spread is None else GpVarianceSpread(**spread),
            error_budget=None if budget is None else ErrorBudget(**budget),
            error_budget_statement=summary.get("error_budget_statement"),
            warnings=tuple(summary["warnings"]),
            observations=None if observations is None else tuple(observations),
        )

    @classmethod
    def load(cls, path: Path | str) -> PosteriorSummary:
        """Read a ``summary.json``."""
        return cls.from_json(json.loads(Path(path).read_text()))

    def write(self, path: Path | str) -> Path:
        """Write ``summary.json`` (2-space indented JSON, a final newline)."""
        path = Path(path)
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")
        return path


def _asdict_or_none(value) -> dict | None:
    return None if value is None else asdict(value)


@dataclass
class PosteriorSamples:
    """Draws of all chains, their diagnostics and what ``posterior.nc`` records of the model."""

    names: tuple[str, ...]
    draws: np.ndarray  # (chains, n_draws, dim)
    diverging: np.ndarray  # (chains, n_draws)
    step_sizes: list[float]
    seconds: float
    truth: np.ndarray | None
    bounds: np.ndarray  # (5, 2)
    acceptance_rates: list[float]  # Pyro's, per chain
    stats: dict[str, np.ndarray]  # (chains, n_draws) per sampler statistic (see GROUP_ATTRS)
    log_likelihood: np.ndarray  # (chains, n_draws, n_obs, G)
    prior: np.ndarray  # (n_prior, dim) prior draws
    data: dict[str, dict[str, np.ndarray]]  # observed_data, constant_data (see data_groups)
    attrs: dict[str, dict]  # per group, "/" for the root (see file_attrs)
    gp_variance_spread: GpVarianceSpread | None = None
    error_budget: ErrorBudget | None = None
    error_budget_at: np.ndarray | None = None  # (5,) the posterior medians it was evaluated at
    model_warnings: tuple[str, ...] = ()  # SkinPosterior.model_warnings
    divergences_before_resampling: int | None = None  # of the first run, when it was run again
    first_target_accept: float = TARGET_ACCEPT  # that first run's

    @property
    def target_accept(self) -> float:
        """NUTS's target acceptance of these draws (``posterior.nc``'s root attribute)."""
        return self.attrs["/"]["target_accept_prob"]

    def posterior_dict(self) -> dict[str, np.ndarray]:
        """(chains, n_draws) draws per parameter name."""
        return {n: self.draws[..., k] for k, n in enumerate(self.names)}

    def inference_data(self):
        """The ArviZ DataTree of ``posterior.nc`` (groups: see docs/file-formats.md)."""
        import arviz as az

        groups = {
            "posterior": self.posterior_dict(),
            "sample_stats": {"diverging": self.diverging, **self.stats},
            "log_likelihood": {"weights": self.log_likelihood.reshape(*self.diverging.shape, -1)},
            "prior": {n: self.prior[None, :, k] for k, n in enumerate(self.names)},
            **self.data,
        }
        return az.from_dict(groups, dims=DIMS, coords=COORDS, attrs=self.attrs)

    def summary(self, observations: list[str] | None = None) -> PosteriorSummary:
        """Median, 95 % interval, R-hat and ESS per parameter, sampler statistics, error budget, warnings;
        ``observations``: the sources of the observations, recorded when given."""
        parameters = self._parameter_summaries()
        return PosteriorSummary(
            parameters=parameters,
            chains=int(self.draws.shape[0]),
            draws_per_chain=int(self.draws.shape[1]),
            divergences=int(self.diverging.sum()),
            step_sizes=tuple(self.step_sizes),
            acceptance_rates=tuple(self.acceptance_rates),
            seconds=self.seconds,
            gp_variance_over_posterior=self.gp_variance_spread,
            error_budget=self.error_budget,
            error_budget_statement=None
            if self.error_budget is None
            else self.error_budget.statement(self.error_budget_at),
            warnings=tuple(self.warnings(parameters)),
            observations=None if observations is None else tuple(observations),
        )

    def _parameter_summaries(self) -> dict[str, ParameterSummary]:
        import arviz as az

        dt = az.from_dict({"posterior": self.posterior_dict()})
        rhat = az.rhat(dt)
        bulk, tail = az.ess(dt, method="bulk"), az.ess(dt, method="tail")
        out = {}
        for k, n in enumerate(self.names):
            x = self.draws[..., k].ravel()
            lo, hi = float(np.percentile(x, 2.5)), float(np.percentile(x, 97.5))
            skin = {}
            if k < 5:
                skin = {
                    "prior": tuple(self.bounds[k].tolist()),
                    "interval_share_of_prior": (hi - lo) / float(np.ptp(self.bounds[k])),
                }
                if self.truth is not None:
                    skin.update(true=float(self.truth[k]), covered=bool(lo <= self.truth[k] <= hi))
            out[n] = ParameterSummary(
                float(np.median(x)), lo, hi, float(rhat[n].values), float(bulk[n].values), float(tail[n].values), **skin
            )
        return out

    def warnings(self, table: dict[str, ParameterSummary]) -> list[str]:
        messages = list(self.model_warnings)
        for n, e in table.items():
            if e.r_hat > RHAT_LIMIT:
                messages.append(f"{n}: R-hat {e.r_hat:.3f} > {RHAT_LIMIT} (chains disagree; sample longer)")
            if e.ess < ESS_LIMIT:
                messages.append(f"{n}: ESS {e.ess:.0f} < {ESS_LIMIT}")
        if self.divergences_before_resampling is not None:
            messages.append(
                f"{self.divergences_before_resampling} of {self.diverging.size} transitions diverged at target "
                f"acceptance {self.first_target_accept}: these draws are a rerun at {self.target_accept}"
            )
        if self.diverging.any():
            messages.append(f"{int(self.diverging.sum())} divergent transitions")
        return messages


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


def write_outputs(
    samples: PosteriorSamples, out: Path | str, observations: list[str] | None = None
) -> PosteriorSummary:
    """posterior.nc, summary.json and corner.png into the folder ``out`` (written under a
    temporary name and renamed, so a folder with a summary.json is complete); returns the summary
    (``observations``: the sources of the observations, recorded in it)."""
    from inference.plots import corner_plot

    summary = samples.summary(observations)

    def write(tmp: Path) -> None:
        tmp.mkdir()
        samples.inference_data().to_netcdf(tmp / "posterior.nc")
        summary.write(tmp / "summary.json")
        corner_plot(samples, tmp / "corner.png")

    write_atomically(out, write)
    return summary
