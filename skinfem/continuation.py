"""Parameter continuation: start a simulation from the equilibria of nearby parameters.

A calibration evaluates the FE model at a sequence of close parameter vectors (Gauss–Newton
or Levenberg–Marquardt trial points). Ramping the load from zero at each of them repeats
~10 increments of Newton iterations; the equilibrium at the new point is instead one or two
Newton steps away from the previous point's, moved along its sensitivities:

    u(x) ~= u(x0) + sum_i du/dx_i (x - x0)_i,

a first-order predictor (zeroth order for parameters without a stored sensitivity).
:class:`Continuation` keeps, per membrane design, the last converged states (the unloaded
reference of a pre-stressed model and every observed frame) with the sensitivities computed
there, and predicts the starting states of :meth:`skinfem.model.SkinModel.solve_frames`.
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
    """The last converged states per design, and predictions from them (see module doc)."""

    def __init__(self):
        self._last: dict[Hashable, ConvergedStates] = {}

    def record(self, design: Hashable, states: ConvergedStates) -> None:
        """Keep ``states`` for ``design``; without sensitivities of their own they inherit
        the previous states' (same frames), a first-order predictor from a nearby point."""
        previous = self._last.get(design)
        if not states.sensitivities and previous is not None and previous.frames.keys() == states.frames.keys():
            states.sensitivities = previous.sensitivities
        self._last[design] = states

    def designs(self) -> list[Hashable]:
        """Designs with converged states."""
        return list(self._last)

    def states(self, design: Hashable) -> ConvergedStates:
        return self._last[design]

    def predict(
        self, design: Hashable, x: np.ndarray, frames: Sequence[float]
    ) -> tuple[np.ndarray | None, list[tuple[float, np.ndarray]]] | None:
        """(reference guess, [(t, guess)] for ``frames``) at parameters x, or None if this
        design has no converged states for these frames yet."""
        last = self._last.get(design)
        if last is None or not set(frames) <= last.frames.keys():
            return None
        step = np.asarray(x, float) - last.x
        reference = None if last.reference is None else last.reference.copy()
        guesses = {t: last.frames[t].copy() for t in frames}
        for i, (d_reference, d_frames) in last.sensitivities.items():
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
