"""The check's own discretisation error, measured before any physics is blamed.

At the calibrated parameters x the same DIC measurement is computed on the check's mesh
(size h) and on a better one, shift = f_ref(x) - f_h(x) at every measured point. If the better
mesh's error is a share r of the check mesh's, with the same shape, the error of f_h is
-shift / (1 - r) and that of f_ref -shift r / (1 - r). The better mesh is

- one refinement of the check's mesh (h/2 in plane, or only at the membrane edge; twice the
  layers through the thickness, :func:`refined_layers`): if the surface strain converges at
  order p, r = 2^-p. Two meshes do not tell p; the check uses the order measured for its
  element degree under these refinements (:data:`OBSERVED_ORDER`, docs/criticism.md §2); or
- a quadratic reference mesh (:data:`REFERENCES`: ``"quadratic"`` with 1 mm cells at the membrane
  edge, ``"converged"`` with 0.5 mm) for a linear mesh whose refinement would cost more than it
  and, with one skin layer, does not have the shape of its error (docs/criticism.md §11): r as
  measured for the paper mesh.

The check then

- **corrects** its model by a multiple of the shift (:class:`CorrectedForward`: f_h(x') + a
  shift for every x', a two-level correction that treats the shift as constant near x), with
  the amplitude a calibrated together with the skin parameters (a = 1 is the better mesh's
  field, a = 1 / (1 - r) the extrapolation, for a refinement Richardson's of order p; a
  refined mesh outside the asymptotic range needs more), and
- **carries** the remaining error, the better mesh's (sd = the local RMS of the shift within
  the larger h of the two meshes of the point, per component, times r / (1 - r)), correlated
  over the shift's own correlation length, as a model-form variance next to the noise
  (:class:`inference.criticism.data.ModelError`), so that a residual the mesh explains is not
  called a missing effect.

If the better mesh's error is still above the noise, the report says so and names the cell
size at the membrane edge (``mesh.h_edge``), where the error lives, that would bring it to half
the noise (error proportional to that size to the power p).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from inference.criticism.data import Data, ModelError
from inference.forward import ForwardModel, prestressing_parameters
from skinfem.config import Config
from skinfem.mesh import edge_cell_size
from skinfem.parallel import CollectiveError

# Observed order of convergence of the DIC surface strain under these refinements, by element
# degree (docs/criticism.md §2, benchmarks/results/dic_convergence.json): Q1 on `small`, uniform
# refinement, 39 % -> 16 % from the Q2 reference (1.3); Q2 under membrane-edge refinement
# 1 -> 0.5 -> 0.25 mm against the Richardson limit, 1.23 ("finer"; 2 -> 1 -> 0.5 mm said 1.53:
# the order falls as the edge cells shrink, so the check's 1 -> 0.5 mm step takes the lower one).
OBSERVED_ORDER = {1: 1.3, 2: 1.2}


@dataclass(frozen=True)
class Reference:
    """A quadratic reference mesh of a linear check mesh (Q2, two skin and four muscle layers,
    2 mm under the membrane graded to 4 mm far) and its error as a share of the paper mesh's.

    Attributes:
        h_edge: cell size at the membrane edge [mm].
        ratio: its error / the paper mesh's, both against the Richardson limit of the Q2 edge
            series 1 -> 0.5 -> 0.25 mm (benchmarks/results/dic_convergence.json, "finer"), the
            largest over the regions (all points, 8-12 mm band, far field); a coarser linear
            mesh's share is smaller.
    """

    h_edge: float
    ratio: float

    @property
    def mesh(self) -> dict[str, float | int]:
        return {"h_membrane": 2.0, "h_far": 4.0, "h_edge": self.h_edge, "skin_layers": 2, "muscle_layers": 4}


# Measured shares (band / all / far field, reference against paper mesh): 1 mm edge cells
# 10.9 / 34.2 %, 9.1 / 29.4 %, 3.3 / 25.8 %; 0.5 mm edge cells (the `converged` preset's mesh
# before its edge cells were graded; the paper mesh's checks were validated with this one)
# 4.8 / 34.2 %, 4.1 / 29.4 %, 1.9 / 25.8 %.
REFERENCES = {
    "quadratic": Reference(h_edge=1.0, ratio=0.32),  # 131,757 dofs on the paper block
    "converged": Reference(h_edge=0.5, ratio=0.14),  # 216,045 dofs
}
REFINEMENTS = ("uniform", "edge", *REFERENCES)
MESH_RESOLVED_SIGMA = 0.5  # a remaining mesh error below half the noise: the mesh is resolved
UNCONVERGED_AMPLITUDE = 2.5  # a correction beyond first-order extrapolation (2) and its usual sd
BETTER_MESH_FAILS = "the discretisation estimate's better mesh does not converge at the calibrated parameters"


class DiscretisationFailure(CollectiveError, ValueError):
    """A mesh of the two-mesh estimate has no solution at the calibrated parameters. Raised on
    every rank, as the forward model agrees on its failures across ranks, so that the command
    line prints it once and every rank ends with the same exit code."""


def richardson_limit(coarser: np.ndarray, finer: np.ndarray, order: float) -> np.ndarray:
    """Richardson extrapolation of two fields whose mesh sizes differ by a factor 2, converging
    at ``order``: finer + (finer - coarser) / (2^order - 1)."""
    return finer + (finer - coarser) / (2.0**order - 1.0)


def observed_order(config: Config) -> float:
    """The measured order p of :data:`OBSERVED_ORDER` for ``config``'s elements (the lowest
    measured one for a degree that was not measured: the most conservative)."""
    return OBSERVED_ORDER.get(config.solver.element_degree, min(OBSERVED_ORDER.values()))


def resolved_through_thickness(config: Config) -> bool:
    """Quadratic elements with two or more skin layers: refining through the skin no longer
    changes the DIC strain (:func:`refined_layers`), only the membrane edge does."""
    return config.solver.element_degree >= 2 and config.mesh.skin_layers >= 2


def refined_layers(config: Config) -> dict[str, int]:
    """Layer counts of the refined mesh: muscle and membrane layers doubled, skin layers too
    unless the mesh is quadratic with two or more skin layers. From the quadratic check mesh
    (Q2, 2/6 mm, s2 m2) doubling the muscle layers moves the DIC strain by 3.5 % (far field
    8.5 %), doubling the skin layers by 0.8 % (``benchmarks/dic_convergence.py refinements``):
    through the skin, two quadratic layers are converged, and a third and fourth would only
    make the refined run dearer (Q1 needs them: s2 -> s4 still moves it 9 %)."""
    m = config.mesh
    layers = {"muscle_layers": 2 * m.muscle_layers, "membrane_layers": 2 * m.membrane_layers}
    if not resolved_through_thickness(config):
        layers["skin_layers"] = 2 * m.skin_layers
    return layers


def default_refinement(config: Config) -> str:
    """``"edge"`` for a quadratic mesh or one refined at the membrane edge (uniform refinement
    would multiply its dofs by about 8); ``"converged"`` for a linear mesh with cells at the
    membrane edge finer than the ``"quadratic"`` reference's (the paper mesh: its uniform
    refinement has 348k dofs, the converged reference 216k. With the 132k ``"quadratic"`` one the
    paper mesh's checks named a spurious pre-stretch in 3 of 5 controls on data with 0.5 mm edge
    cells, with the converged one in none of 5 on data with 0.25 mm ones, docs/criticism.md
    §14-15); else ``"uniform"``."""
    if config.solver.element_degree >= 2 or config.mesh.edge_refined:
        return "edge"
    return "converged" if edge_cell_size(config.mesh) < REFERENCES["quadratic"].h_edge else "uniform"


def error_ratio(config: Config, refinement: str) -> tuple[float, str]:
    """(r, basis): the better mesh's error as a share of ``config``'s (see module doc), and what
    that share rests on, in words.

    Raises:
        ValueError: a quadratic reference for a mesh that is quadratic already.
    """
    if refinement in REFERENCES:
        if config.solver.element_degree >= 2:
            raise ValueError(
                f"the {refinement} reference is for linear (Q1) meshes; "
                "a quadratic mesh is refined at its edge (--refine edge)"
            )
        ratio = REFERENCES[refinement].ratio
        return ratio, f"the reference's error taken as {ratio:.0%} of the check mesh's, as measured for the paper mesh"
    order = observed_order(config)
    return 2.0**-order, f"order {order:g} assumed"


def refined_config(config: Config, refinement: str = "uniform") -> Config:
    """The mesh of the two-mesh estimate, with the layers of :func:`refined_layers`, and

    - ``"uniform"``: every in-plane size (membrane edge included) halved;
    - ``"edge"``: only the cells at the membrane edge halved (``mesh.h_edge``; from
      ``h_membrane`` if the mesh has no edge refinement), graded back to the mesh's own sizes.
      The in-plane error lives at the membrane edge (halving every in-plane size of a Q2 mesh
      moves the surface strain as much as halving only its edge cells: 16.4 % vs 16.5 %,
      docs/criticism.md), so this is the affordable refinement of a fine or quadratic mesh
      (uniform refinement multiplies its dofs by about 8);
    - ``"quadratic"``, ``"converged"``: not a refinement but a reference mesh of
      :data:`REFERENCES`, for a linear mesh (its material, membrane and solver settings kept).
    """
    m = config.mesh
    if refinement in REFERENCES:
        error_ratio(config, refinement)  # a linear mesh only
        return config.with_changes(
            mesh=REFERENCES[refinement].mesh, solver={"element_degree": 2, "quadrature_degree": 4}
        )
    layers = refined_layers(config)
    if refinement == "edge":
        return config.with_changes(mesh={"h_edge": edge_cell_size(m) / 2, **layers})
    if refinement != "uniform":
        raise ValueError(f"unknown refinement {refinement!r}; choose one of {', '.join(REFINEMENTS)}")
    return config.with_changes(
        mesh={"h_membrane": m.h_membrane / 2, "h_far": m.h_far / 2, "h_edge": m.h_edge / 2, **layers}
    )


def describe_mesh(config: Config) -> str:
    """One phrase for a configuration's mesh, e.g. "Q2, h = 2 mm under the membrane, 1 mm at its
    edge (6 mm far), 2 skin layers"."""
    m, degree = config.mesh, config.solver.element_degree
    edge = f", {m.h_edge:g} mm at its edge" if m.edge_refined else ""
    return (
        f"Q{degree}, h = {m.h_membrane:g} mm under the membrane{edge} ({m.h_far:g} mm far), "
        f"{m.skin_layers} skin layer{'s' if m.skin_layers > 1 else ''}"
    )


@dataclass
class DiscretisationError:
    """The two-mesh estimate at the calibrated parameters (see module doc).

    Attributes:
        mesh, refined: descriptions of the check's mesh and of the better one (its refinement
            or a quadratic reference).
        radius: radius of the local error envelope [mm]: the larger in-plane size under the
            membrane of the two meshes.
        h_edge: its in-plane size at the membrane edge [mm], which governs the error.
        shift: (n_obs, n_pts, 3) f_better - f_check at the points [strain].
        order: the order of convergence of the check mesh's elements (:func:`observed_order`).
        ratio: the better mesh's error as a share of the check mesh's (:func:`error_ratio`).
        basis: what that share rests on, in words.
        relative: RMS of the check mesh's error (|shift| / (1 - ratio)) / RMS of the measured
            field.
        sigma: RMS of the check mesh's error in units of the stated noise sd.
        amplitude, amplitude_sd: the multiple of the shift the calibrated, corrected model uses
            (:class:`CorrectedForward`) and its Laplace sd; None before that calibration.
        quadratic: the check's mesh has quadratic elements and two or more skin layers already
            (its advice is then only a finer edge).
        drifts: the correction follows the parameters to first order (:func:`mesh_error_drift`).
        noise_factor: the sd of the noise the check uses over the stated sd (> 1 when the
            noise statement found the stated sd too small); whether the error is resolved is
            judged against the noise used.
    """

    mesh: str
    refined: str
    radius: float
    h_edge: float
    shift: np.ndarray
    order: float
    ratio: float
    basis: str
    relative: float
    sigma: float
    amplitude: float | None = None
    amplitude_sd: float | None = None
    quadratic: bool = False
    drifts: bool = False
    noise_factor: float = 1.0

    @property
    def remaining_factor(self) -> float:
        """The better mesh's error per unit shift, r / (1 - r): what the corrected model carries
        (for a refinement at order p, 1 / (2^p - 1))."""
        return self.ratio / (1.0 - self.ratio)

    @property
    def extrapolated(self) -> float:
        """The amplitude of the shift that extrapolates to the converged field, 1 / (1 - r)."""
        return 1.0 / (1.0 - self.ratio)

    @property
    def remaining_sigma(self) -> float:
        """RMS of the corrected model's remaining error in units of the stated noise sd."""
        return self.sigma * self.ratio

    @property
    def carried_sigma(self) -> float:
        """RMS of the corrected model's remaining error in units of the noise sd used."""
        return self.remaining_sigma / self.noise_factor

    @property
    def remaining_relative(self) -> float:
        """RMS of the corrected model's remaining error / RMS of the measured field."""
        return self.relative * self.ratio

    def sd(self, xy: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """(n_obs, n_pts, 3) sd of the corrected model's remaining error: the local RMS of the
        shift within :attr:`radius` of each point (xy (n_obs, n_pts, 2), masks (n_obs, n_pts))
        times :attr:`remaining_factor`.

        A local envelope, not |shift| itself: the shift changes sign where the two meshes' fields
        cross, and there |shift| ~ 0 would claim an exact model."""
        out = np.zeros_like(self.shift)
        for o, m in enumerate(masks):
            points = xy[o, m]
            near = cKDTree(points).query_ball_point(points, r=self.radius)
            squares = self.shift[o, m] ** 2
            out[o, m] = np.sqrt([squares[i].mean(axis=0) for i in near])
        return out * self.remaining_factor

    def model_error(self, xy: np.ndarray, masks: np.ndarray) -> ModelError:
        """The corrected model's remaining error as a correlated field: sd of :meth:`sd` and the
        correlation of the shift itself (:func:`correlation_fit`). Errors of one
        discretisation are smooth over a few cells; carried as independent per point they
        would make the calibrated parameters' Laplace sd too small."""
        sd = self.sd(xy, masks)
        standardised = np.divide(self.shift, sd, out=np.zeros_like(sd), where=sd > 0)
        return ModelError(sd, *correlation_fit(standardised, xy, masks, self.radius))

    @property
    def resolved(self) -> bool:
        """The corrected model's error is below half the noise used."""
        return self.carried_sigma <= MESH_RESOLVED_SIGMA

    def suggested_h_edge(self) -> float:
        """Membrane-edge cell size [mm] whose error would be half the noise used (convergence of
        order :attr:`order` in the edge size)."""
        return self.h_edge * (0.5 / max(self.sigma / self.noise_factor, 1e-12)) ** (1.0 / self.order)

    def _of_the_noise_used(self) -> str:
        """The carried error against the estimated noise, when the check uses one."""
        if self.noise_factor == 1.0:
            return ""
        return f" of the stated noise, {self.carried_sigma:.1f} of the estimated"

    def summary(self) -> str:
        text = (
            f"Discretisation error of the check's mesh ({self.mesh}) at the calibrated parameters: "
            f"{self.relative:.1%} of the field, {self.sigma:.1f} sigma RMS "
            f"(two-mesh estimate with {self.refined}); "
            f"the model is corrected by a fitted multiple of the shift"
            f"{' (which follows the parameters to first order)' if self.drifts else ''} and its remaining error "
            f"({self.remaining_sigma:.1f} sigma{self._of_the_noise_used()}, {self.basis}) is carried next to "
            "the noise."
        )
        if self.amplitude is not None:
            unconverged = f"; above {UNCONVERGED_AMPLITUDE:g}: the better mesh is itself far from converged"
            text += (
                f" The measurement puts the correction at {self.amplitude:.2f} ± {self.amplitude_sd:.2f} times "
                f"the shift (1: the better mesh's field; {self.extrapolated:.2f}: the extrapolation"
                f"{unconverged if self.amplitude > UNCONVERGED_AMPLITUDE else ''})."
            )
        if not self.resolved:
            text += (
                f" It exceeds half the noise: effects smaller than it cannot be told apart from discretisation. "
                f"The error lives at the membrane edge: at order {self.order:g} a mesh with cells of "
                f"mesh.h_edge <= {self.suggested_h_edge():.2g} mm there would resolve it"
            )
            text += (
                "."
                if self.quadratic
                else "; quadratic elements (solver.element_degree = 2) with two skin layers converge faster "
                "(`--config check`, docs/criticism.md)."
            )
        return text


def correlation_fit(field: np.ndarray, xy: np.ndarray, masks: np.ndarray, h: float) -> tuple[float, float]:
    """(length [mm], nugget) of the correlation (1 - nugget) exp(-d^2 / 2 length^2) of a
    standardised field (n_obs, n_pts, 3) at points xy, fitted by least squares to the
    empirical correlation of point pairs in distance bins of width h / 2 out to 4 h
    (length on a grid of 0 to 4 h; length 0 means independent points, nugget 1)."""
    edges = np.arange(0.0, 4 * h + 1e-9, h / 2)
    products, squares = np.zeros(len(edges) - 1), np.zeros(len(edges) - 1)
    for o, m in enumerate(masks):
        points, values = xy[o, m], field[o, m]
        pairs = cKDTree(points).query_pairs(edges[-1], output_type="ndarray")
        d = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
        k = np.searchsorted(edges, d, side="right") - 1
        inside = k < len(products)  # a pair exactly 4 h apart (points on a grid) lies on the last edge
        pairs, k = pairs[inside], k[inside]
        np.add.at(products, k, np.sum(values[pairs[:, 0]] * values[pairs[:, 1]], axis=1))
        np.add.at(squares, k, 0.5 * np.sum(values[pairs[:, 0]] ** 2 + values[pairs[:, 1]] ** 2, axis=1))
    used = squares > 0
    rho = products[used] / squares[used]
    centres = (0.5 * (edges[1:] + edges[:-1]))[used]
    best = (np.sum(rho**2), 0.0, 1.0)  # independent points
    for length in np.linspace(h / 20, 4 * h, 80):
        shape = np.exp(-(centres**2) / (2 * length**2))
        scale = float(np.clip(shape @ rho / (shape @ shape), 0.0, 1.0))  # = 1 - nugget
        best = min(best, (float(np.sum((rho - scale * shape) ** 2)), float(length), 1.0 - scale))
    return best[1], best[2]


def estimate(
    coarse: ForwardModel, fine: ForwardModel, x: np.ndarray, data: Data, refinement: str
) -> DiscretisationError:
    """Two-mesh estimate at x (p,); ``coarse``/``fine`` must measure the same points of ``data``;
    ``fine`` is ``coarse``'s mesh after ``refinement`` (:func:`refined_config`).

    Raises:
        DiscretisationFailure: the refined model does not converge at x.
    """
    f_coarse, f_fine = coarse(x), fine(x)
    if f_fine is None:
        raise DiscretisationFailure(BETTER_MESH_FAILS)
    shift = np.where(data.masks[..., None], f_fine - f_coarse, 0.0)
    m = data.masks
    measured_rms = float(np.sqrt(np.mean(data.fields[m] ** 2)))
    ratio, basis = error_ratio(coarse.config, refinement)
    error = shift[m] / (1.0 - ratio)
    return DiscretisationError(
        mesh=describe_mesh(coarse.config),
        refined=describe_mesh(fine.config),
        radius=max(coarse.config.mesh.h_membrane, fine.config.mesh.h_membrane),
        h_edge=edge_cell_size(coarse.config.mesh),
        shift=shift,
        order=observed_order(coarse.config),
        ratio=ratio,
        basis=basis,
        relative=float(np.sqrt(np.mean(error**2)) / measured_rms),
        sigma=float(np.sqrt(np.mean((error / data.noise.sd) ** 2))),
        quadratic=resolved_through_thickness(coarse.config),
    )


AMPLITUDE = "discretisation.amplitude"  # the multiple of the two-mesh shift the model is corrected by
AMPLITUDE_BOUNDS = (0.0, 4.0)


class CorrectedForward(ForwardModel):
    """``base`` corrected by a multiple ``a`` of the field ``shift`` (n_obs, n_pts, 3):
    f_h(x) + a shift, with ``a`` the last parameter (``AMPLITUDE``, in ``AMPLITUDE_BOUNDS``,
    null 1: the better mesh's field). Extrapolation puts the converged field at a = 1 / (1 - r)
    (Richardson's of order p for a refinement: 2^p / (2^p - 1), first order 2, high order 1); a
    better mesh that is itself outside the asymptotic range needs more. Calibrated with the skin
    parameters, ``a`` lets the measurement say how far the mesh is from converged along the
    direction the better mesh showed, so that a candidate effect must explain more than a larger
    or smaller discretisation error.

    The shift is fixed unless ``drift`` is given: (n_obs, n_pts, 3, n_base) its derivative by the
    base model's parameters at ``at`` (n_base,) (:func:`mesh_error_drift`); the shift then follows
    the parameters to first order, shift(x) = shift + drift (x - at). A candidate that moves the
    model far from ``at`` (a 1.5x thicker skin) changes the mesh's own error by more than the
    noise, and partly against its own signature (docs/criticism.md §23).
    """

    def __init__(
        self, base: ForwardModel, shift: np.ndarray, drift: np.ndarray | None = None, at: np.ndarray | None = None
    ):
        if (drift is None) != (at is None):
            raise ValueError("a drifting shift needs both its derivative and the point it was taken at")
        self.base, self.shift, self.drift, self.at = base, shift, drift, at
        self.names = [*base.names, AMPLITUDE]
        self.bounds = np.vstack([base.bounds, AMPLITUDE_BOUNDS])
        self.null = np.append(base.null, 1.0)

    @property
    def runs(self) -> int:
        return self.base.runs

    @property
    def exact_jacobian(self) -> bool:
        return self.base.exact_jacobian

    def shift_at(self, x: np.ndarray) -> np.ndarray:
        """(n_obs, n_pts, 3) the shift at the base model's parameters ``x`` (n_base,)."""
        return self.shift if self.drift is None else self.shift + self.drift @ (x - self.at)

    def evaluate_many(self, points: Sequence[np.ndarray]) -> list[np.ndarray | None]:
        fields = self.base.evaluate_many([x[:-1] for x in points])
        return [None if f is None else f + x[-1] * self.shift_at(x[:-1]) for x, f in zip(points, fields)]

    def evaluate_with_jacobian(
        self, points: Sequence[np.ndarray], names: Sequence[str]
    ) -> list[tuple[np.ndarray, np.ndarray] | None]:
        base_names = [n for n in names if n != AMPLITUDE]
        results = self.base.evaluate_with_jacobian([x[:-1] for x in points], base_names)
        out = []
        for x, result in zip(points, results):
            if result is None:
                out.append(None)
                continue
            fields, derivative = result
            shift = self.shift_at(x[:-1])
            if self.drift is not None and base_names:
                derivative = derivative + x[-1] * self.drift[..., self.base.index(base_names)]
            columns = iter(np.moveaxis(derivative, -1, 0))
            if names:
                derivative = np.stack([shift if n == AMPLITUDE else next(columns) for n in names], -1)
            out.append((fields + x[-1] * shift, derivative))
        return out


def mesh_error_drift(coarse: ForwardModel, fine: ForwardModel, x: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(n_obs, n_pts, 3, n) the derivative of the two-mesh shift f_fine - f_coarse by every
    parameter of ``coarse`` at x: both meshes' exact Jacobians (forward sensitivities, one run
    each), zero off ``masks`` (n_obs, n_pts). Their fields serve :func:`estimate` at x without
    another run. Zero, too, along the pre-stressing effects' parameters when x has none of them
    (:func:`~inference.forward.prestressing_parameters`): there every fiber sits at its
    tension-only switch, and the derivative does not describe a finite pre-stretch
    (docs/criticism.md §4, §23).

    Raises:
        DiscretisationFailure: either mesh does not converge at x.
    """
    names = list(coarse.names)
    (fine_result,) = fine.evaluate_with_jacobian([x], names)
    if fine_result is None:
        raise DiscretisationFailure(BETTER_MESH_FAILS)
    (coarse_result,) = coarse.evaluate_with_jacobian([x], names)
    if coarse_result is None:
        raise DiscretisationFailure("the check's mesh does not converge at its own calibrated parameters")
    drift = np.where(masks[..., None, None], fine_result[1] - coarse_result[1], 0.0)
    switch = coarse.index(prestressing_parameters(names))
    if not np.any(x[switch]):
        drift[..., switch] = 0.0
    return drift
