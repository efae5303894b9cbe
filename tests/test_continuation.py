"""Parameter continuation: equilibria reached from nearby parameters equal ramped ones."""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.continuation import Continuation, ConvergedStates

TRUTH = [1.2e-3, 0.017, 11.0, 0.285, 30.0]


def test_prediction_is_exact_for_states_linear_in_the_parameters():
    """u(x) = a + B x at two frames and the reference: the first-order predictor is exact; a
    parameter without a stored sensitivity keeps the state (zeroth order)."""
    rng = np.random.default_rng(0)
    a = {t: rng.normal(size=7) for t in (0.5, 1.0)}
    B = {t: rng.normal(size=(7, 3)) for t in (0.5, 1.0)}
    a_ref, B_ref = rng.normal(size=7), rng.normal(size=(7, 3))
    x0, x1 = rng.normal(size=3), rng.normal(size=3)
    continuation = Continuation()
    assert continuation.predict("mixed", x1, [1.0]) is None
    sensitivities = {i: (B_ref[:, i], {t: B[t][:, i] for t in a}) for i in (0, 2)}
    continuation.record("mixed", ConvergedStates(x0, a_ref + B_ref @ x0, {t: a[t] + B[t] @ x0 for t in a},
                                                 sensitivities))
    x1[1] = x0[1]  # no sensitivity stored for parameter 1: only 0 and 2 move
    reference, guesses = continuation.predict("mixed", x1, [1.0, 0.5])
    np.testing.assert_allclose(reference, a_ref + B_ref @ x1, atol=1e-12)
    assert [t for t, _ in guesses] == [0.5, 1.0]
    for t, guess in guesses:
        np.testing.assert_allclose(guess, a[t] + B[t] @ x1, atol=1e-12)
    assert continuation.predict("mixed", x1, [0.25]) is None  # a frame never solved


def test_states_without_sensitivities_inherit_the_previous_ones():
    continuation = Continuation()
    d = (None, {1.0: np.ones(3)})
    continuation.record(0, ConvergedStates(np.zeros(2), None, {1.0: np.zeros(3)}, {1: d}))
    continuation.record(0, ConvergedStates(np.ones(2), None, {1.0: np.full(3, 5.0)}))
    _, [(_, guess)] = continuation.predict(0, np.array([1.0, 3.0]), [1.0])
    np.testing.assert_allclose(guess, 7.0)


def two_design_forward(config, mesh_dir, continuation):
    """The serial FE forward model (all effects) at two designs and two load fractions."""
    from inference.forward import FEForward, PointSet

    bounds = np.array([config.sweep.bounds[n] for n in ("mu", "k1", "k2", "kappa", "theta")])
    g = np.linspace(-18, 18, 13)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    obs = [PointSet(np.array([0.05, -0.05]), 1.0, xy), PointSet(np.array([0.05, -0.05]), 0.5, xy),
           PointSet(np.array([-0.05, 0.05]), 1.0, xy)]
    return FEForward(config, obs, bounds, mesh_dir, increments=2, comm=MPI.COMM_SELF, continuation=continuation)


@pytest.mark.slow
def test_continued_fields_and_jacobians_equal_ramped_ones(small_config, mesh_dir):
    """A calibration-like sequence of points (skin parameters, a pre-stretch that makes the
    reference pre-stressed, the muscle and bonding effects) evaluated by continuation from the
    previous point and, independently, by ramping the load from zero: fields and exact
    Jacobians agree to the Newton tolerance (1e-8 of their largest entry), and continuation was
    the route taken."""
    warm = two_design_forward(small_config, mesh_dir, continuation=True)
    ramped = two_design_forward(small_config, mesh_dir, continuation=False)
    names = warm.names[:5] + ["pre_stretch.eps_xx", "pre_stretch.eps_xy", "muscle_stiffness.log_factor"]
    x = warm.null.copy()
    x[:5] = TRUTH
    moves = [{}, {"mu": 1e-4, "theta": 5.0}, {"k1": 1e-3, "kappa": -0.005, "pre_stretch.eps_xx": 0.04},
             {"pre_stretch.eps_xy": 0.02, "muscle_stiffness.log_factor": 0.3, "bonding.compliance": 5.0},
             {"k2": -1.0, "theta": 10.0}]
    for move in moves:
        for name, step in move.items():
            x[warm.names.index(name)] += step
        (f_warm, j_warm), = warm.evaluate_with_jacobian([x], names)
        (f_ramp, j_ramp), = ramped.evaluate_with_jacobian([x], names)
        np.testing.assert_allclose(f_warm, f_ramp, atol=1e-8 * np.abs(f_ramp).max(), err_msg=str(move))
        np.testing.assert_allclose(j_warm, j_ramp, atol=1e-8 * np.abs(j_ramp).max(), err_msg=str(move))
    assert warm.continued == 2 * (len(moves) - 1) and ramped.continued == 0
    assert np.abs(f_ramp).max() > 0.03


@pytest.mark.slow
def test_a_failed_continuation_falls_back_to_the_ramp(small_config, mesh_dir, monkeypatch):
    """If Newton from the predicted states fails, the point is ramped from zero: same fields as
    a forward model without continuation, and it is not counted as continued."""
    warm = two_design_forward(small_config, mesh_dir, continuation=True)
    ramped = two_design_forward(small_config, mesh_dir, continuation=False)
    x = warm.null.copy()
    x[:5] = TRUTH
    warm(x)
    monkeypatch.setattr(warm.model, "solve_frames", lambda *args, **kwargs: False)
    x[0] *= 1.2
    np.testing.assert_array_equal(warm(x), ramped(x))
    assert warm.continued == 0
