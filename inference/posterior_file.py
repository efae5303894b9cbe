"""What a posterior run records: ``posterior.nc`` (ArviZ groups posterior, sample_stats,
log_likelihood, observed_data, prior, constant_data: :meth:`PosteriorSamples.inference_data`,
their dimensions and notes), ``summary.json`` (:class:`PosteriorSummary`: median, 95 % interval,
R-hat, bulk/tail ESS per :class:`ParameterSummary`, divergences, acceptance rates, the true value
when known) and ``corner.png``, written together by :func:`write_outputs`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from inference.model import ErrorBudget, GpVarianceSpread, ObservedFields, SkinPosterior
from skinfem.config import PARAM_NAMES
from skinfem.io import COMPONENTS
from skinfem.outputs import write_atomically

RHAT_LIMIT, ESS_LIMIT = 1.01, 400


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
    first_target_accept: float | None = None  # that first run's, when it was run again

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
