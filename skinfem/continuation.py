"""Parameter continuation: start a simulation from the equilibria of nearby parameters.

A calibration evaluates the FE model at a sequence of close parameter vectors (Gauss–Newton
or Levenberg–Marquardt trial points). Ramping the load from zero at each of them repeats
~10 increments of Newton iterations; the equilibrium at the new point is instead one or two
Newton steps away from the previous point's, moved along its sensitivities:

    u(x) ~= u(x0) + sum_i du/dx_i (x - x0)_i,

a first-order predictor (zeroth order for parameters without a stored sensitivity).
:class:`Continuation` keeps, per membrane design, the last few converged states (the unloaded
reference of a pre-stressed model and every observed frame) with the sensitivities computed
there, and predicts the starting states of :meth:`skinfem.model.SkinModel.solve_frames` from
the kept states nearest to the new point.
Units: dof arrays in mm, sensitivities in mm per unit of x (theta per degree).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ConvergedStates:
    """Converged dof arrays of one simulation at parameters ``x`` (p,).

    Attributes:
        x: (p,) the parameter vector.
        reference: dofs of the unloaded equilibrium (None: not pre-stressed).
        frames: load fraction t -> dofs of the loaded equilibrium.
        sensitivities: parameter index -> (d reference / dx_i or None, {t: d frame / dx_i}).
    """

    x: np.ndarray
    reference: np.ndarray | None
    frames: dict[float, np.ndarray]
    sensitivities: dict[int, tuple[np.ndarray | None, dict[float, np.ndarray]]] = field(default_factory=dict)


class Continuation:
    """The last few converged states per design, and predictions from the nearest (see module doc).

    Args:
        scale: (p,) parameter scales (e.g. the prior box's widths) for the distance between
            parameter vectors; None: unscaled.
        keep: states kept per design. A check alternates fits of several candidate effects
            from one baseline: the nearest kept states, not the last, start the next one.
    """

    def __init__(self, scale: np.ndarray | None = None, keep: int = 4):
        self._kept: dict[Hashable, list[ConvergedStates]] = {}
        self.scale = None if scale is None else np.asarray(scale, float)
        self.keep = keep

    def record(self, design: Hashable, states: ConvergedStates) -> None:
        """Keep ``states`` for ``design``; without sensitivities of their own they inherit
        the previous states' (same frames), a first-order predictor from a nearby point."""
        kept = self._kept.setdefault(design, [])
        if not states.sensitivities and kept and kept[-1].frames.keys() == states.frames.keys():
            states.sensitivities = kept[-1].sensitivities
        kept.append(states)
        del kept[: -self.keep]

    def designs(self) -> list[Hashable]:
        """Designs with converged states."""
        return list(self._kept)

    def states(self, design: Hashable) -> ConvergedStates:
        """The last converged states of ``design``."""
        return self._kept[design][-1]

    def nearest(self, design: Hashable, x: np.ndarray, frames: Sequence[float]) -> ConvergedStates | None:
        """The kept states of ``design`` holding ``frames`` closest to ``x`` (the latest of equally
        close ones), or None."""
        usable = [s for s in reversed(self._kept.get(design, [])) if set(frames) <= s.frames.keys()]
        scale = 1.0 if self.scale is None else self.scale
        return min(usable, key=lambda s: float(np.linalg.norm((x - s.x) / scale)), default=None)

    def predict(
        self, design: Hashable, x: np.ndarray, frames: Sequence[float]
    ) -> tuple[np.ndarray | None, list[tuple[float, np.ndarray]]] | None:
        """(reference guess, [(t, guess)] for ``frames``) at parameters x from the nearest kept
        states, or None if this design has no converged states for these frames yet."""
        x = np.asarray(x, float)
        near = self.nearest(design, x, frames)
        if near is None:
            return None
        step = x - near.x
        reference = None if near.reference is None else near.reference.copy()
        guesses = {t: near.frames[t].copy() for t in frames}
        for i, (d_reference, d_frames) in near.sensitivities.items():
            if step[i] == 0.0:
                continue
            if reference is not None and d_reference is not None:
                reference += step[i] * d_reference
            for t in frames:
                guesses[t] += step[i] * d_frames[t]
        return reference, [(t, guesses[t]) for t in sorted(frames)]


def transfer(states: ConvergedStates, V_from, V_to) -> ConvergedStates:
    """``states`` (dof arrays of the serial space ``V_from``) interpolated into the serial space
    ``V_to`` on another mesh of the same block: a start for a simulation on another mesh (e.g.
    a refined one) instead of a load ramp."""
    from skinfem.fenics import dolfinx

    mesh = V_to.mesh
    cells = np.arange(mesh.topology.index_map(mesh.topology.dim).size_local, dtype=np.int32)
    data = dolfinx.fem.create_interpolation_data(V_to, V_from, cells, padding=1e-8)
    source, target = dolfinx.fem.Function(V_from), dolfinx.fem.Function(V_to)

    def moved(array):
        if array is None:
            return None
        source.x.array[:] = array
        target.interpolate_nonmatching(source, cells, data)
        return target.x.array.copy()

    sensitivities = {
        i: (moved(d_ref), {t: moved(d) for t, d in d_frames.items()})
        for i, (d_ref, d_frames) in states.sensitivities.items()
    }
    return ConvergedStates(
        states.x.copy(), moved(states.reference), {t: moved(u) for t, u in states.frames.items()}, sensitivities
    )
