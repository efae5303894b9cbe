"""Calibration of the forward model to the whitened measurements, with its Laplace posterior."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from inference.criticism.data import Data, stack
from inference.forward import ForwardModel
from skinfem.parallel import CollectiveError

log = logging.getLogger(__name__)

# a calibration stops once a step lowers chi^2 by less than this: a gap to the optimum well under
# 1 (one Laplace sd along the flattest direction) moves no verdict (Delta BIC threshold 6)
CHI2_TOLERANCE = 0.1


@dataclass(frozen=True)
class Estimate:
    """A calibrated parameter: its value and Laplace standard deviation (the parameter's unit)."""

    value: float
    sd: float


@dataclass
class Calibration:
    """A calibrated model version: point estimate, Laplace covariance, residuals.

    Attributes:
        names: all parameter names of the forward model; x: (p,) values (fixed ones included).
        free: indices of the calibrated parameters; cov: (k, k) their covariance.
        model_fields: (n_obs, n_pts, 3) fields at x; whitened: whitened residual.
        jac: (n, k) derivative of the stacked whitened *model* with respect to the free
            parameters (physical units).
        rejected: parameter points (p,) where the FE model did not converge (steps rejected).
        chi2_path: chi^2 at the start and after each accepted step.
    """

    names: list[str]
    x: np.ndarray
    free: list[int]
    cov: np.ndarray
    model_fields: np.ndarray
    whitened: np.ndarray
    jac: np.ndarray
    fe_runs: int
    seconds: float
    label: str = "baseline"
    rejected: list[np.ndarray] = field(default_factory=list)
    chi2_path: list[float] = field(default_factory=list)

    @property
    def free_names(self) -> list[str]:
        return [self.names[i] for i in self.free]

    @property
    def chi2(self) -> float:
        """Sum of squares of the whitened residual."""
        return float(np.nansum(self.whitened**2))

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    def estimates(self) -> dict[str, Estimate]:
        """The fitted value and Laplace sd of every free parameter, by qualified name."""
        sd = dict(zip(self.free_names, self.sd))
        return {
            n: Estimate(float(self.x[i]), float(sd.get(n, 0.0))) for i, n in enumerate(self.names) if i in self.free
        }


def _trial_outcome(chi2: float, chi2_new: float | None) -> str:
    """One progress line's words for a trial step from chi^2 ``chi2`` (None: the run failed)."""
    if chi2_new is None:
        return f"chi^2 {chi2:,.1f}, trial step rejected (the FE run did not converge)"
    return f"chi^2 {chi2:,.1f} -> {chi2_new:,.1f}" + ("" if chi2_new < chi2 else " (step rejected)")


def damped_step(A: np.ndarray, g: np.ndarray, moving: np.ndarray, damping: float) -> np.ndarray:
    """The Levenberg-Marquardt step dz (k,) of the parameters ``moving`` (k,) bool (0 for the
    others): (A + damping diag(A)) dz = -g over them, A = J^T J (k, k), g = J^T r (k,)."""
    dz = np.zeros(len(g))
    Am = A[np.ix_(moving, moving)]
    dz[moving] = np.linalg.solve(Am + damping * np.diag(np.diag(Am) + 1e-12 * np.trace(A)), -g[moving])
    return dz


def bounded_step(J: np.ndarray, r: np.ndarray, z: np.ndarray, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """(dz, held): the damped step in the unit box from z (k,) with the parameters ``held`` (k,)
    at the bound that the step would cross kept there (a projected Gauss-Newton step).

    Which are held is decided by the step itself, not by the gradient: starting with none,
    the parameters at a bound whose step leaves the box are held and the step is solved again
    over the others, until none leaves (at most k solves). A parameter pushed outward by the
    gradient alone may still move inward once the parameters it is confounded with move (a
    skin parameter at its bound when a pre-stretch is freed); holding it by the gradient's
    sign kept such fits crawling along the bound. Clipping the full step instead distorts the
    other parameters' step and makes Levenberg-Marquardt crawl as well."""
    A, g, held = J.T @ J, J.T @ r, np.zeros(len(z), dtype=bool)
    while True:
        dz = damped_step(A, g, ~held, damping)
        leaving = ((z <= 0) & (dz < 0)) | ((z >= 1) & (dz > 0))
        if not np.any(leaving & ~held):
            return dz, held
        held |= leaving


def gauss_newton_gain(J: np.ndarray, r: np.ndarray) -> float:
    """The chi^2 decrease |J dz|^2 that the undamped Gauss-Newton step dz = argmin |r + J dz|
    promises in the linearised model (the part of r in the range of J (n, k); solved on J, not
    on the normal equations, so that a weakly identified parameter still counts)."""
    if J.shape[1] == 0:
        return 0.0
    dz = np.linalg.lstsq(J, -r, rcond=None)[0]
    return float(np.sum((J @ dz) ** 2))


class CalibrationError(CollectiveError, ValueError):
    """The forward model has no solution at the calibration's starting point (a bad start is
    bad input: the command line reports it in one line). Raised on every rank, as the forward
    model agrees on its failures across ranks, so that rank 0 alone prints it."""


class _UnitBoxProblem:
    """Whitened residuals of the free parameters z in the unit box [0, 1]^k (helper of calibrate)."""

    def __init__(self, forward: ForwardModel, data: Data, x0: np.ndarray, free: list[int]):
        self.forward, self.data, self.free = forward, data, free
        self.lo, self.span = forward.bounds[free, 0], np.ptp(forward.bounds[free], axis=1)
        self.base = np.asarray(x0, dtype=float).copy()
        self.base[free] = np.clip(self.base[free], *forward.bounds[free].T)
        self.start = (self.base[free] - self.lo) / self.span
        self.rejected: list[np.ndarray] = []
        self.fields: dict[bytes, np.ndarray] = {}  # model fields of evaluated z (no rerun at the end)

    def point(self, z: np.ndarray) -> np.ndarray:
        """The parameters at z; at the start, the starting point bit for bit (not its round trip
        through the unit box), so that a run made there before, e.g. the diagnosis's signatures
        at a calibrated point, is found in the forward model's cache."""
        x = self.base.copy()
        if not np.array_equal(z, self.start):
            x[self.free] = self.lo + np.clip(z, 0, 1) * self.span
        return x

    def residuals(self, zs: list[np.ndarray]) -> list[np.ndarray | None]:
        """Stacked whitened residuals (n,) at each z; None (and recorded) where FE failed."""
        points = [self.point(z) for z in zs]
        return [self._residual(z, x, fields) for z, x, fields in zip(zs, points, self.forward.evaluate_many(points))]

    def _residual(self, z: np.ndarray, x: np.ndarray, fields: np.ndarray | None) -> np.ndarray | None:
        """The stacked whitened residual of fields at z (x: its parameter point); None, and x
        recorded as rejected, where the model has no solution or a non-finite one."""
        r = None if fields is None else stack(self.data.whitened_residual(fields), self.data.masks)
        if r is None or not np.all(np.isfinite(r)):
            self.rejected.append(x)
            return None
        self.fields[z.tobytes()] = fields
        return r

    def evaluate(self, z: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Residual r (n,) and Jacobian d r / d z (n, k) at z: exact in one run when the forward
        model has derivatives, else the Jacobian is left to :meth:`jacobian` (None)."""
        if not self.forward.exact_jacobian:
            return self.residuals([z])[0], None
        x = self.point(z)
        (result,) = self.forward.evaluate_with_jacobian([x], [self.forward.names[i] for i in self.free])
        r = self._residual(z, x, None if result is None else result[0])
        if r is None:
            return None, None
        J = np.stack([-self.data.whiten(result[1][..., i]) * s for i, s in enumerate(self.span)], 1)
        return r, J

    def jacobian(self, z: np.ndarray, r0: np.ndarray, step: float) -> np.ndarray:
        """(n, k) one-sided differences d r / d z; the other side where a run failed (0 if both)."""
        eye = np.eye(len(z))
        h = np.where(z + step <= 1, step, -step)
        columns = self.residuals([z + h[i] * eye[i] for i in range(len(z))])
        retry = [i for i, c in enumerate(columns) if c is None and 0 <= z[i] - h[i] <= 1]
        h[retry] *= -1
        for i, c in zip(retry, self.residuals([z + h[i] * eye[i] for i in retry])):
            columns[i] = c
        return np.stack([np.zeros_like(r0) if c is None else (c - r0) / h[i] for i, c in enumerate(columns)], 1)


def calibrate(
    forward: ForwardModel,
    data: Data,
    x0: np.ndarray,
    free: list[int],
    label: str = "baseline",
    max_iterations: int = 12,
    step: float = 1e-3,
    relative_tolerance: float = 0.0,
) -> Calibration:
    """Least-squares fit of the free parameters (within their prior box) to the whitened data.

    Levenberg–Marquardt in the unit box of the prior: parameters at a bound that the descent
    would cross are held for the step (:func:`bounded_step`), the rest clipped to the box. A trial
    point where the FE model does not converge is a rejected step: the damping grows (the
    step shrinks), the point is recorded in ``Calibration.rejected`` and the fit continues.
    Jacobians are exact when the forward model has derivatives (forward sensitivities: one
    run per trial point), else forward differences of ``step`` in the unit box (one run per
    free parameter, spread over MPI ranks by the forward model). The fit stops once a step
    lowers chi^2 by less than ``CHI2_TOLERANCE`` (or ``relative_tolerance`` chi^2 if larger:
    a fit that only needs to come near its optimum), or before a step when the undamped
    Gauss-Newton step promises less than that (:func:`gauss_newton_gain`: no run to find it
    out), or after ``max_iterations`` trial steps.
    Returns the Laplace posterior at the optimum. Longer than a screen: one Levenberg-Marquardt
    loop with its rejected-step bookkeeping, kept whole to read as the algorithm.

    Raises:
        CalibrationError: the model does not converge at the starting point.
    """
    start, runs0 = time.perf_counter(), forward.runs
    problem = _UnitBoxProblem(forward, data, x0, free)
    z = problem.start
    r, J = problem.evaluate(z)
    if r is None:
        at = ", ".join(f"{forward.names[i]} = {v:.4g}" for i, v in zip(free, problem.point(z)[free]))
        raise CalibrationError(f"the FE model does not converge at the calibration's starting point ({at})")
    J, damping = problem.jacobian(z, r, step) if J is None else J, 1e-3
    chi2_path = [float(r @ r)]
    for _ in range(max_iterations):
        if not np.any(J):  # no free parameter moves the fields (e.g. every difference failed)
            break
        dz, held = bounded_step(J, r, z, damping)
        tolerance = max(CHI2_TOLERANCE, relative_tolerance * float(r @ r))
        if gauss_newton_gain(J[:, ~held], r) < tolerance:  # even the full step would not be visible
            break
        z_new = np.clip(z + dz, 0, 1)
        if np.max(np.abs(z_new - z)) < 1e-8:
            break
        r_new, J_new = problem.evaluate(z_new)
        log.info("%s: %s", label, _trial_outcome(r @ r, None if r_new is None else r_new @ r_new))
        if r_new is None or not r_new @ r_new < r @ r:  # failed run, no decrease or NaN: a shorter step
            damping *= 10 if r_new is None else 4
            continue
        decrease = r @ r - r_new @ r_new
        z, r, damping = z_new, r_new, damping / 3
        chi2_path.append(float(r @ r))
        J = problem.jacobian(z, r, step) if J_new is None else J_new  # at the new point: its covariance
        if decrease < tolerance:  # chi^2 no longer moves by a statistically visible amount
            break
    x = problem.point(z)
    cov = np.linalg.pinv(J.T @ J, rcond=1e-12) * np.outer(problem.span, problem.span)
    fields = problem.fields[z.tobytes()]
    return Calibration(
        names=list(forward.names),
        x=x,
        free=list(free),
        cov=cov,
        model_fields=fields,
        whitened=data.whitened_residual(fields),
        jac=-J / problem.span,
        fe_runs=forward.runs - runs0,
        seconds=time.perf_counter() - start,
        label=label,
        rejected=problem.rejected,
        chi2_path=chi2_path,
    )
