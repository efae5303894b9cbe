"""Which effect is missing: candidate signatures, score tests, confirmation fits, the verdict."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

from inference.criticism.calibration import Calibration, calibrate
from inference.criticism.data import Data, stack
from inference.criticism.discretisation import AMPLITUDE, MESH_RESOLVED_SIGMA
from inference.criticism.metrics import (
    Hotspot,
    MembraneRegions,
    RegionResidual,
    ResidualMetrics,
    morans_i,
    rank_regions,
    region_heterogeneity,
    residual_hotspot,
    residual_metrics,
)
from inference.forward import ForwardModel
from skinfem.effects import get_effect

log = logging.getLogger(__name__)

STRONG_EVIDENCE = 6.0  # Delta BIC above which a candidate is reported (Kass & Raftery: strong)
MIN_SHARE = 0.5  # ... and it must explain at least this share of the excess residual
# a candidate whose signature the skin parameters absorb beyond this share at the calibrated point
# has a blind linearised test (a large effect may still differ from what they absorb): it is fitted
CONFOUNDED = 0.8
MAX_MESH_FACTOR = 10.0  # the largest multiple of the carried model error the other explanation tries
# a candidate whose signature reproduces at least this share of the mesh's own error (the two-mesh
# shift, beyond what the calibrated parameters reproduce) cannot be told from that error while it
# exceeds the noise. Measured on the quadratic check mesh's checks of converged data: compressibility
# 0.12-0.35, every other registered candidate <= 0.023 (docs/criticism.md §22)
MESH_LIKE = 0.05
NOISE_STRUCTURE_Z = 3.0  # |Moran z| below which a residual has the stated noise's spatial structure


@dataclass
class NoiseStatement:
    """Whether the stated noise sd is consistent with the residual (:func:`check_noise_statement`)."""

    consistent: bool
    factor: float  # estimated sd / stated sd (1 when consistent)
    moran_z: float
    chi2_per_dof: float
    heterogeneity_z: float = 0.0  # how unevenly the residual spreads over the regions (metrics.region_heterogeneity)

    def summary(self, stated: np.ndarray) -> str:
        if self.consistent:
            return ""
        estimated = ", ".join(f"{v:.2g}" for v in self.factor * stated)
        return (
            f"The stated noise is inconsistent with the residual: it is {self.factor:.1f}x larger than stated "
            f"(chi^2/dof = {self.chi2_per_dof:.2f}) but has the stated noise's spatial structure (Moran's I "
            f"z = {self.moran_z:.1f}) and spreads evenly over the regions (z = {self.heterogeneity_z:.1f}); "
            f"the check continues with the estimated sd {estimated} (xx, yy, xy) instead of looking for a "
            "missing effect in it (give --noise-sd to state it)."
        )


def check_noise_statement(
    forward: ForwardModel, cal: Calibration, data: Data, membrane: MembraneRegions, max_iterations: int = 6
) -> tuple[Calibration, Data, NoiseStatement]:
    """Is a structured residual only noise larger than stated?

    A residual that is larger than the stated noise (PPC p < metrics.ALPHA) is put down to
    noise s times the stated sd (s from :func:`noise_factor`, the carried model error held as
    it is) when, under that scaled noise model, its spatial autocorrelation is the noise's
    (Moran |z| < NOISE_STRUCTURE_Z) and its mean square is as even over ``membrane``'s regions
    (under it, edges, corners, far field) as the noise model's (z < NOISE_STRUCTURE_Z): missing
    effects are smooth fields (large Moran z) or peak at the membrane's edges and corners. The
    calibration is then repeated with the scaled noise. (Both tests are scale-free without a
    model error; with one, noise and carried error weigh differently from point to point, so
    they are made under the scaled noise model, not the stated one.)
    """
    metrics = residual_metrics(cal, data)
    statement = NoiseStatement(True, 1.0, metrics.moran_z, metrics.chi2_per_dof)
    if not metrics.structured:
        return cal, data, statement
    factor = noise_factor(data, cal.model_fields, metrics.dof)
    scaled = data.with_noise_factor(factor)
    statement.moran_z = morans_i(scaled.standardised(cal.model_fields), scaled).z
    if abs(statement.moran_z) >= NOISE_STRUCTURE_Z:
        return cal, data, statement
    statement.heterogeneity_z = region_heterogeneity(cal, scaled, membrane)
    if statement.heterogeneity_z >= NOISE_STRUCTURE_Z:
        return cal, data, statement
    statement.consistent, statement.factor = False, factor
    log.info("the residual reads as noise %.2f times the stated sd: calibrating again with it", factor)
    return calibrate(forward, scaled, cal.x, cal.free, cal.label, max_iterations), scaled, statement


def noise_factor(data: Data, model_fields: np.ndarray, dof: int) -> float:
    """The factor on the stated noise sd at which the residual's chi^2 equals ``dof``, the
    carried model error held as it is: sqrt(chi^2/dof) without one; with one, the root of
    chi^2(s) = dof (chi^2 falls monotonically as the noise grows, and stays below its value
    without the model error, chi^2_noise / s^2). 1 when chi^2 <= dof."""
    chi2 = data.chi2_of_noise_factor(model_fields)
    at_stated = chi2(1.0)
    if at_stated <= dof:
        return 1.0
    if data.model_error is None:
        return math.sqrt(at_stated / dof)
    noise_only = data.with_model_error(None).chi2_of_noise_factor(model_fields)(1.0)
    upper = math.sqrt(max(noise_only, at_stated) / dof)
    if chi2(upper) >= dof:  # only by rounding, where the model error is zero at every point
        return upper
    return math.exp(optimize.brentq(lambda log_s: chi2(math.exp(log_s)) - dof, 0.0, math.log(upper), xtol=1e-4))


# -- diagnosis -------------------------------------------------------------------------------
@dataclass
class CandidateScore:
    """How well one candidate effect explains the residual of a calibrated model.

    The *score* fields come from the linearised test at the null effect (cheap, all
    candidates); the *fit* fields from actually calibrating the model with the effect added
    (the strongest candidates only), which also holds when the effect is too large for the
    linearisation. ``share_explained`` is the share of the excess residual chi^2 (above its
    noise expectation) that the effect removes; ``explains`` needs strong evidence and at
    least half of the excess. ``mesh_share`` is the share of the check mesh's own error (its
    two-mesh shift, beyond what re-tuning the calibrated parameters reproduces) that the
    effect's signature reproduces (:func:`mesh_shares`; None without a mesh-error estimate);
    ``mesh_like``: the effect would explain the residual, but reproduces at least
    ``MESH_LIKE`` of that error while it exceeds the noise, so it is not named.
    """

    effect: str
    description: str
    parameters: list[str]
    statistic: float  # efficient score T, chi^2_dof under "no effect"
    dof: int
    p_value: float
    delta_bic: float  # T - dof ln n: > 0 favours the effect
    share_explained: float
    confounding: float  # share of the fitted signature that skin-parameter re-tuning absorbs
    estimate: dict[str, float]  # one-step (linear) estimate of the effect's parameters
    fitted: bool = False  # delta_bic, share_explained, estimate come from a calibration
    explains: bool = False
    mesh_share: float | None = None
    mesh_like: bool = False

    def resembles_mesh_error(self) -> bool:
        """Its signature reproduces ``MESH_LIKE`` or more of the check mesh's own error."""
        return self.mesh_share is not None and self.mesh_share >= MESH_LIKE

    def summary(self) -> str:
        est = ", ".join(f"{k.split('.')[-1]} = {v:.3g}" for k, v in self.estimate.items())
        how = "fitted" if self.fitted else "linearised"
        return (
            f"{self.effect} (Delta BIC = {self.delta_bic:+.1f}, explains {self.share_explained:.0%} of the "
            f"excess residual, {self.confounding:.0%} confounded with the skin parameters; {how} estimate {est})"
        )


def signatures(
    forward: ForwardModel, cal: Calibration, data: Data, effects: list[str], rel_step: float = 0.02
) -> dict[str, np.ndarray]:
    """Whitened signatures (n, dim phi) of each effect: derivatives of the model at ``cal.x``.

    Exact (forward sensitivities, one run) when the forward model has derivatives; that run
    also gives the calibrated parameters' derivatives, so that a candidate's confirmation fit,
    which starts there, starts without a run of its own (the forward model's cache). Otherwise
    each parameter is moved ``rel_step`` of its prior range both ways, clipped to the range
    (a null value on a bound gives a one-sided difference); a side whose FE run failed is
    replaced by the calibrated point itself; if both fail the column is zero.
    """
    if forward.exact_jacobian:
        names = [q for name in effects for q in get_effect(name).qualified_names()]
        calibrated = [forward.names[i] for i in cal.free]
        (result,) = forward.evaluate_with_jacobian([cal.x], calibrated + names)
        if result is not None:
            columns = iter(data.whiten(result[1][..., len(calibrated) + i]) for i in range(len(names)))
            return {name: np.stack([next(columns) for _ in get_effect(name).parameters], 1) for name in effects}
    jobs = []  # (effect, parameter index, low value, high value)
    for name in effects:
        for i in forward.index(get_effect(name).qualified_names()):
            h = rel_step * np.ptp(forward.bounds[i])
            jobs.append((name, i, max(cal.x[i] - h, forward.bounds[i, 0]), min(cal.x[i] + h, forward.bounds[i, 1])))
    points = []
    for _, i, low, high in jobs:
        for value in (low, high):
            x = cal.x.copy()
            x[i] = value
            points.append(x)
    fields = forward.evaluate_many(points)
    columns: dict[str, list] = {name: [] for name in effects}
    for (name, i, low, high), f_low, f_high in zip(jobs, fields[::2], fields[1::2]):
        if f_low is None:
            f_low, low = cal.model_fields, cal.x[i]
        if f_high is None:
            f_high, high = cal.model_fields, cal.x[i]
        column = data.whiten(f_high - f_low) / (high - low) if high > low else np.zeros(data.n)
        columns[name].append(column)
    return {name: np.stack(cols, 1) for name, cols in columns.items()}


def excess_chi2(cal: Calibration, data: Data) -> float:
    """chi^2 of the residual above its expectation under noise alone (n - k)."""
    return cal.chi2 - (data.n - len(cal.free))


def fit_beyond(q: np.ndarray, S: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares fit of ``target`` (n,) by the part of the signature ``S`` (n, k) outside the
    span of the orthonormal columns ``q`` (n, m): (coefficients (k,), fitted vector (n,))."""
    S_perp = S - q @ (q.T @ S)
    beta, *_ = np.linalg.lstsq(S_perp, target, rcond=None)
    return beta, S_perp @ beta


def score_candidates(cal: Calibration, data: Data, sigs: dict[str, np.ndarray]) -> list[CandidateScore]:
    """Linearised score test, share explained, confounding and Delta BIC of each candidate."""
    r = stack(cal.whitened, data.masks)
    n = r.size
    q, _ = np.linalg.qr(cal.jac)  # what re-tuning the calibrated parameters can absorb
    excess = excess_chi2(cal, data)
    out = []
    for name, S in sigs.items():
        beta, fitted = fit_beyond(q, S, r)
        T = float(fitted @ fitted)
        raw = S @ beta
        dof = S.shape[1]
        cls = get_effect(name)
        out.append(
            CandidateScore(
                effect=name,
                description=cls.description,
                parameters=cls.qualified_names(),
                statistic=T,
                dof=dof,
                p_value=float(stats.chi2.sf(T, dof)),
                delta_bic=T - dof * math.log(n),
                share_explained=float(np.clip((T - dof) / excess, 0, 1)) if excess > 0 else 0.0,
                confounding=float(np.clip(1 - T / float(raw @ raw), 0, 1)) if raw @ raw > 0 else 1.0,
                estimate={qn: float(b) for qn, b in zip(cls.qualified_names(), beta)},
            )
        )
    return sorted(out, key=lambda s: -s.delta_bic)


def mesh_shares(
    cal: Calibration, data: Data, sigs: dict[str, np.ndarray], shift: np.ndarray, amplitude: int | None
) -> dict[str, float]:
    """Share of the mesh's own error that each candidate's signature reproduces.

    ``shift`` (n_obs, n_pts, 3): the two-mesh shift f_better - f_check, the shape of the check
    mesh's error; whitened like the residual, with what re-tuning ``cal``'s free parameters
    reproduces projected out (all but ``amplitude``, the index of the correction's amplitude,
    whose column is the shift itself). Returns, per candidate, the share of that remainder's
    squared norm that the least-squares fit of the candidate's whitened signature (its own
    part beyond the calibrated parameters) reproduces: 0 for a signature orthogonal to the
    mesh's error, 1 for one that reproduces all of it."""
    keep = [k for k, i in enumerate(cal.free) if i != amplitude]
    q, _ = np.linalg.qr(cal.jac[:, keep])
    d = data.whiten(shift)
    d -= q @ (q.T @ d)
    norm2 = float(d @ d)
    out = {}
    for name, S in sigs.items():
        _, fitted = fit_beyond(q, S, d)
        out[name] = float(fitted @ fitted / norm2) if norm2 > 0 else 0.0
    return out


def extend(forward: ForwardModel, cal: Calibration, data: Data, effect: str, **kwargs) -> Calibration:
    """Calibrate ``cal``'s model with ``effect``'s parameters freed (started at their null)."""
    added = forward.index(get_effect(effect).qualified_names())
    x0 = cal.x.copy()
    x0[added] = forward.null[added]
    return calibrate(forward, data, x0, cal.free + added, label=f"{cal.label} + {effect}", **kwargs)


@dataclass(frozen=True)
class LargerModelError:
    """The other explanation of a structured residual when a model error (the mesh's) is carried:
    that error is ``factor`` times its estimate (one parameter), with ``delta_bic`` against the
    estimate itself (:func:`larger_model_error`)."""

    factor: float
    delta_bic: float


def larger_model_error(cal: Calibration, data: Data) -> LargerModelError | None:
    """The multiple k of the carried model error that maximises the Gaussian likelihood of
    ``cal``'s residual, -2 ln L(k) = sum z^2 / (1 + k^2 mu) + log(1 + k^2 mu) + const
    (:meth:`Data.model_error_spectrum`), k in [0, ``MAX_MESH_FACTOR``], and its Delta BIC
    against k = 1 (one parameter; the skin parameters not refitted, so a lower bound). A
    candidate effect must beat it to be named. None when no model error is carried."""
    if data.model_error is None:
        return None
    z, mu = data.model_error_spectrum(cal.model_fields)

    def deviance(k: float) -> float:
        return float(np.sum(z**2 / (1.0 + k**2 * mu) + np.log1p(k**2 * mu)))

    best = optimize.minimize_scalar(deviance, bounds=(0.0, MAX_MESH_FACTOR), method="bounded")
    return LargerModelError(float(best.x), deviance(1.0) - float(best.fun) - math.log(len(z)))


@dataclass
class Diagnosis:
    """One diagnosis of a calibrated model (:func:`diagnose`): its residual's metrics, regions
    (ranked) and hotspot, the candidates' scores (best first), the confirmation fits by effect,
    the verdict's text, its FE runs and wall seconds, and the larger mesh error a candidate had
    to beat (None when the residual is consistent or no model error is carried)."""

    metrics: ResidualMetrics
    regions: list[RegionResidual]
    hotspot: Hotspot
    scores: list[CandidateScore]
    fits: dict[str, Calibration]
    text: str
    fe_runs: int
    seconds: float
    larger_model_error: LargerModelError | None = None

    @property
    def best(self) -> CandidateScore | None:
        """The named candidate (the first that explains the residual), or None."""
        return next((s for s in self.scores if s.explains), None)


def diagnose(
    forward: ForwardModel,
    cal: Calibration,
    data: Data,
    effects: list[str],
    membrane: MembraneRegions,
    confirm: int = 2,
    carried_sigma: float = 0.0,
    added: Sequence[str] = (),
    mesh_shift: np.ndarray | None = None,
    **fit_kwargs,
) -> Diagnosis:
    """Compare, locate and explain: metrics, ``membrane``'s regions, candidate ranking and the verdict.

    If the residual is structured, the ``confirm`` best candidates by linearised Delta BIC
    (only those with strong evidence) are calibrated for real, and their fitted Delta BIC and
    share of the excess residual replace the linearised ones (should the fits fall behind a
    strong candidate not yet fitted, it is fitted too, so that a named candidate is a fitted
    one); so are (``confirm`` > 0) the
    candidates whose linearised test is blind, more than ``CONFOUNDED`` of their signature
    absorbed by the skin parameters: a skin that compensates a stiffer muscle at the
    calibrated point leaves it no local signature, yet the effect, fitted, can explain more
    than the candidate the linearisation ranks first. ``carried_sigma``: RMS of the
    model error ``data`` carries (the mesh's, in noise sd; see :func:`verdict`). ``added``:
    effects ``cal`` already includes (a later round), kept in the verdict's ``--add`` advice.
    ``mesh_shift``: the two-mesh shift of the carried error's estimate; a candidate that
    reproduces ``MESH_LIKE`` of it (:func:`mesh_shares`) is neither fitted nor named while the
    carried error exceeds half the noise (it could be the mesh's own error).
    """
    start, runs0 = time.perf_counter(), forward.runs
    metrics = residual_metrics(cal, data)
    regions, hotspot = rank_regions(cal, data, membrane), residual_hotspot(cal, data)
    sigs = signatures(forward, cal, data, effects)
    scores = score_candidates(cal, data, sigs)
    if mesh_shift is not None:
        amplitude = forward.names.index(AMPLITUDE) if AMPLITUDE in forward.names else None
        shares = mesh_shares(cal, data, sigs, mesh_shift, amplitude)
        for s in scores:
            s.mesh_share = shares[s.effect]
    unresolved = carried_sigma > MESH_RESOLVED_SIGMA
    fits: dict[str, Calibration] = {}
    if metrics.structured:
        excess, n = excess_chi2(cal, data), metrics.n_data
        testable = [s for s in scores if not (unresolved and s.resembles_mesh_error())]
        strong = [s for s in testable if s.delta_bic > STRONG_EVIDENCE][:confirm]
        blind = [s for s in testable if confirm and s.confounding > CONFOUNDED and s not in strong]
        pending = strong + blind
        while pending:  # until the leading candidate is a fitted one (or none is strong)
            for s in pending:
                fits[s.effect] = _confirm(forward, cal, data, s, excess, n, **fit_kwargs)
            scores.sort(key=lambda s: -s.delta_bic)
            lead = next((s for s in scores if any(s is t for t in testable)), None)
            unfitted = confirm and lead is not None and not lead.fitted and lead.delta_bic > STRONG_EVIDENCE
            pending = [lead] if unfitted else []
    larger = larger_model_error(cal, data) if metrics.structured else None
    for s in scores:
        enough = (
            metrics.structured
            and s.delta_bic > max(STRONG_EVIDENCE, larger.delta_bic if larger else -math.inf)
            and s.share_explained >= MIN_SHARE
        )
        s.mesh_like = enough and unresolved and s.resembles_mesh_error()
        s.explains = enough and not s.mesh_like
    text = verdict(metrics, scores, regions, hotspot, carried_sigma, added, larger)
    runs, seconds = forward.runs - runs0, time.perf_counter() - start
    return Diagnosis(metrics, regions, hotspot, scores, fits, text, runs, seconds, larger)


def _confirm(
    forward: ForwardModel, cal: Calibration, data: Data, s: CandidateScore, excess: float, n: int, **fit_kwargs
) -> Calibration:
    """Calibrate candidate ``s`` for real and replace its linearised Delta BIC, share of the
    ``excess`` chi^2 (over ``n`` data) and estimate by the fitted ones; returns the fit."""
    fit = extend(forward, cal, data, s.effect, **fit_kwargs)
    drop = cal.chi2 - fit.chi2
    s.delta_bic = drop - s.dof * math.log(n)
    s.share_explained = float(np.clip((drop - s.dof) / excess, 0, 1)) if excess > 0 else 0.0
    s.estimate = {q: float(fit.x[forward.names.index(q)]) for q in s.parameters}
    s.fitted = True
    return fit


def verdict(
    metrics: ResidualMetrics,
    scores: list[CandidateScore],
    regions: list[RegionResidual],
    hotspot: Hotspot,
    carried_sigma: float = 0.0,
    added: Sequence[str] = (),
    larger: LargerModelError | None = None,
) -> str:
    """One paragraph: is the residual noise, where is it not, which candidate explains it.

    A carried discretisation error above half the noise (``carried_sigma`` > 0.5, RMS in noise
    sd) turns "something outside the registry is missing" into "rerun on a finer mesh first",
    with how many times its estimate the mesh's error would have to be to explain the residual
    (``larger``, :func:`larger_model_error`); a candidate that this larger error explains as well
    is said to be not enough, with that comparison."""
    if not metrics.structured:
        return (
            f"The residual is consistent with the noise (chi^2/dof = {metrics.chi2_per_dof:.2f}, "
            f"posterior-predictive p = {metrics.ppc_p:.2f}, Moran's I z = {metrics.moran_z:.1f}): "
            "no missing effect is needed."
        )
    worst = regions[0]
    text = (
        f"The residual is structured (chi^2/dof = {metrics.chi2_per_dof:.2f}, posterior-predictive "
        f"p = {metrics.ppc_p:.3f}, Moran's I z = {metrics.moran_z:.1f}); the worst region: "
        f"{worst.region} ({worst.rms_sigma:.1f} sigma RMS; noise and carried model error alone give 1), "
        f"peaking {hotspot.summary()}."
    )
    best = next((s for s in scores if s.explains), None)
    if best is None:
        text += " No candidate explains the residual." + unexplained(scores, carried_sigma, larger)
    else:
        text += named(best, scores, added)
    return text + mesh_like_text(scores)


def unexplained(scores: list[CandidateScore], carried_sigma: float, larger: LargerModelError | None) -> str:
    """The verdict's end when no candidate explains a structured residual: the best candidate and
    what it lacks, then whether the mesh's own error may be the cause or something outside the
    registry is missing."""
    scores = [s for s in scores if not s.mesh_like]  # said apart (mesh_like_text)
    lead = f" The best candidate, {scores[0].summary()}, is not enough." if scores else ""
    compared = bool(scores and larger and STRONG_EVIDENCE < scores[0].delta_bic <= larger.delta_bic)
    if compared:
        lead = lead[:-1] + (
            f": the carried model error at {larger.factor:.1f} times its estimate explains the residual "
            f"as well (Delta BIC = +{larger.delta_bic:.1f})."
        )
    if carried_sigma <= MESH_RESOLVED_SIGMA:
        return lead + " Something outside the registry is missing."
    factor = ""
    if larger and not compared:  # else the lead has said it
        factor = f" (it would take the mesh's error at {larger.factor:.1f} times its estimate)"
    return (
        lead + " The check's own discretisation error exceeds half the noise, so this structure may be the "
        f"mesh's{factor}: rerun on a finer mesh before concluding that something outside the registry is missing."
    )


def named(best: CandidateScore, scores: list[CandidateScore], added: Sequence[str]) -> str:
    """The verdict's end naming ``best``: its estimate, its confounding with the skin parameters,
    the other candidates that explain the residual too, and the ``--add`` advice."""
    text = f" Most likely missing: {best.summary()}."
    effect = get_effect(best.effect)
    text += " Estimated " + effect.describe({q.split(".", 1)[1]: v for q, v in best.estimate.items()})
    if best.confounding > CONFOUNDED:
        text += (
            " It is strongly confounded with the skin parameters: more load frames or membrane designs "
            "would separate them."
        )
    rivals = [s for s in scores if s.explains and s is not best]
    if rivals:
        text += " These explain it too, to compare with --add: " + "; ".join(rival_summary(s) for s in rivals) + "."
    return text + f" Add it with --add {' '.join([*added, best.effect])}."


def rival_summary(score: CandidateScore) -> str:
    """A candidate that explains the residual as well, short: name, Delta BIC, share of the excess."""
    how = "fitted" if score.fitted else "linearised"
    return f"{score.effect} ({how} Delta BIC = {score.delta_bic:+.1f}, {score.share_explained:.0%} of the excess)"


def mesh_like_text(scores: list[CandidateScore]) -> str:
    """The candidates that would explain the residual but resemble the mesh's own error (not
    named), with the largest share of that error any other candidate reproduces."""
    alike = [s for s in scores if s.mesh_like]
    if not alike:
        return ""
    others = [s.mesh_share for s in scores if not s.resembles_mesh_error() and s.mesh_share is not None]
    bound = f" (the other candidates at most {max(others):.0%})" if others else ""
    names = "; ".join(f"{rival_summary(s)} reproduces {s.mesh_share:.0%} of the check mesh's own error" for s in alike)
    return (
        f" Not named: {names}{bound}. While that error exceeds half the noise such an effect cannot be told from "
        "discretisation: test it on a finer mesh."
    )
