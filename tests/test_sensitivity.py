"""Forward sensitivities of the DIC strain against finite differences of full simulations."""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.params import Design, SkinParams

NAMES = ["mu", "k1", "theta", "muscle_stiffness.log_factor", "skin_thickness.log_factor"]
STEPS = {"mu": 1e-7, "k1": 1e-6, "theta": 1e-3, "muscle_stiffness.log_factor": 1e-4, "skin_thickness.log_factor": 1e-4}


def mixed_design_forward(config, mesh_dir):
    """The serial FE forward model (all effects, no continuation) of the last frame of the
    mixed design on a 4 mm grid of DIC points over +-16 mm."""
    from inference.forward import FEForward, PointSet

    g = np.linspace(-16, 16, 9)
    obs = [PointSet(np.array([0.05, -0.05]), 1.0, np.stack(np.meshgrid(g, g), -1).reshape(-1, 2))]
    return FEForward(config, obs, config.sweep.box, mesh_dir, increments=2, comm=MPI.COMM_SELF, continuation=False)


def assert_columns_are_central_differences(forward, x, jacobian, steps: dict[str, float]):
    """Column k of ``jacobian`` (..., k) equals (f(x + h e) - f(x - h e)) / 2h of two full
    simulations for the k-th (name, h) of ``steps``, to 1e-5 of the difference's largest entry."""
    for k, (name, step) in enumerate(steps.items()):
        dx = step * (np.array(forward.names) == name)
        difference = (forward(x + dx) - forward(x - dx)) / (2 * step)
        assert np.abs(difference).max() > 0
        np.testing.assert_allclose(jacobian[..., k], difference, atol=1e-5 * np.abs(difference).max(), err_msg=name)


@pytest.mark.slow
def test_dic_strain_sensitivities_equal_central_differences(small_config, mesh_dir):
    """K du/dp = -dR/dp (UFL derivative of the energy), measured by the linearised DIC gauge,
    equals (E(p + h) - E(p - h)) / 2h of two full simulations each, for skin and effect
    parameters (1e-5 of the largest derivative; observed 1e-8 to 3e-7)."""
    from skinfem.dic import StrainGauge, SurfaceStrainGauge
    from skinfem.model import SkinModel
    from skinfem.sensitivity import DisplacementSensitivity

    config = small_config.with_changes(solver={"increments": 2})
    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=["muscle_stiffness", "skin_thickness"])
    g = np.linspace(-16, 16, 9)
    gauge = SurfaceStrainGauge(model.u, np.stack(np.meshgrid(g, g), -1).reshape(-1, 2), StrainGauge(1.0))
    sensitivity = DisplacementSensitivity(model)
    design = Design(0.05, -0.05)
    base = {"mu": 0.0012, "k1": 0.017, "k2": 11.0, "kappa": 0.2, "theta": 30.0}
    exact = {}

    def at_last_frame(t):
        if t == 1.0:
            exact.update(zip(NAMES, gauge.derivatives(sensitivity(NAMES))))

    model.simulate(SkinParams(**base), design, on_frame=at_last_frame)
    for name in NAMES:
        fields = []
        for sign in (1, -1):
            params, effects = dict(base), {n: 0.0 for n in NAMES[3:]}
            (params if name in params else effects)[name] = (base.get(name, 0.0)) + sign * STEPS[name]
            model.set_effects(effects)
            model.simulate(SkinParams(**params), design)
            fields.append(gauge())
        model.set_effects({n: 0.0 for n in NAMES[3:]})
        difference = (fields[0] - fields[1]) / (2 * STEPS[name])
        scale = np.abs(difference).max()
        assert scale > 0
        np.testing.assert_allclose(exact[name], difference, atol=1e-5 * scale, err_msg=name)


@pytest.mark.slow
def test_without_pre_stretch_only_its_parameters_move_the_reference(small_config, mesh_dir):
    """At zero pre-stretch the unloaded reference is u = 0 whatever the skin parameters: the
    forward model solves reference sensitivities for the pre-stretch's parameters only. Its
    Jacobian equals the one with every reference sensitivity solved (1e-12), and the skin
    parameters' columns equal central differences of full simulations (1e-5 of the largest).
    (The pre-stretch's own columns are one-sided here: at zero pre-stretch every fiber sits at
    the tension-only switch, Ebar = 0.)"""
    forward = mixed_design_forward(small_config, mesh_dir)
    names = ["mu", "theta", "pre_stretch.eps_xx", "pre_stretch.eps_xy"]
    x = forward.null.copy()
    x[:5] = [0.0012, 0.017, 11.0, 0.2, 30.0]
    assert forward.moving_reference(x, names) == [2, 3]
    assert forward.moving_reference(x + 0.01 * (np.array(forward.names) == "pre_stretch.eps_yy"), names) == [0, 1, 2, 3]
    solved = []
    solve = forward.sensitivity.__call__
    forward.sensitivity = lambda requested: solved.append(list(requested)) or solve(requested)
    ((fields, jacobian),) = forward.evaluate_with_jacobian([x], names)
    assert solved == [names[2:], names]  # the reference, then the frame
    forward.moving_reference = lambda x, names: list(range(len(names)))
    forward._cache.clear()
    ((fields_all, jacobian_all),) = forward.evaluate_with_jacobian([x], names)
    assert solved[2:] == [names, names]
    np.testing.assert_array_equal(fields, fields_all)
    np.testing.assert_allclose(jacobian, jacobian_all, rtol=0, atol=1e-12 * np.abs(jacobian_all).max())
    assert_columns_are_central_differences(forward, x, jacobian[..., :2], {"mu": 1e-7, "theta": 1e-3})


@pytest.mark.slow
def test_pre_stretch_sensitivities_equal_central_differences_under_a_pre_stretch(small_config, mesh_dir):
    """Away from zero pre-stretch (every fiber of the unloaded skin in tension, off the
    tension-only switch) the pre-stretch's own columns and a skin parameter's, through the
    pre-stressed reference and the loaded state, equal central differences of full
    simulations (1e-5 of the largest; a step of 1e-4, as at 1e-5 the difference carries the Newton
    tolerance's noise, up to 5e-7 of entries of 0.017)."""
    forward = mixed_design_forward(small_config, mesh_dir)
    steps = {"pre_stretch.eps_xx": 1e-4, "pre_stretch.eps_yy": 1e-4, "pre_stretch.eps_xy": 1e-4, "mu": 1e-7}
    x = forward.null.copy()
    x[:5] = [0.0012, 0.017, 11.0, 0.2, 30.0]
    x[forward.index(list(steps)[:3])] = [0.05, 0.03, 0.02]
    ((_, jacobian),) = forward.evaluate_with_jacobian([x], list(steps))
    assert_columns_are_central_differences(forward, x, jacobian, steps)


@pytest.mark.slow
def test_at_zero_pre_stretch_its_columns_are_the_compressive_side(small_config, mesh_dir):
    """At zero pre-stretch every fiber of the unloaded skin sits at the tension-only switch
    (Ebar = 0, the fiber energy's second derivative jumps): the pre-stretch's columns are the
    compressive side's derivative (fibers off). One-sided differences from below converge to
    them (1e-4 of the largest at h = 1e-5); from above, where the fibers take load, they stay
    more than 5 % away. So at every fiber angle: at 25.2 deg, where a0 . a0 rounds above 1, the
    side was the tensile one before the switch counted rounding as slack (FIBER_SLACK)."""
    forward = mixed_design_forward(small_config, mesh_dir)
    for theta, name in ((30.0, "pre_stretch.eps_xx"), (30.0, "pre_stretch.eps_xy"), (25.2, "pre_stretch.eps_xx")):
        x = forward.null.copy()
        x[:5] = [0.0012, 0.017, 11.0, 0.2, theta]
        ((fields, jacobian),) = forward.evaluate_with_jacobian([x], [name])
        column, dx = jacobian[..., 0], 1e-5 * (np.array(forward.names) == name)
        below, above = (fields - forward(x - dx)) / 1e-5, (forward(x + dx) - fields) / 1e-5
        scale = np.abs(column).max()
        assert np.abs(below - column).max() < 1e-4 * scale, name
        assert np.abs(above - column).max() > 0.05 * scale, name


def test_sensitivities_replace_the_newton_solvers_factorisation(small_config, mesh_dir):
    """The sensitivities factorise the tangent in the Newton solver's own preconditioner instead
    of holding a second factorisation (on ``check``'s edge refinement each takes 4.1 GB in
    MUMPS): a run with derivatives at every frame makes one symbolic factorisation (a second one
    would be a second factor), and its fields, solved by Newton on the sensitivities'
    factorisations after the first frame, equal the run's without derivatives (1e-8 of the
    largest strain)."""
    from skinfem.dic import StrainGauge, SurfaceStrainGauge
    from skinfem.model import SkinModel
    from skinfem.sensitivity import DisplacementSensitivity
    from skinfem.solver_work import event_count, start_counting

    config = small_config.with_changes(solver={"increments": 4})
    model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir)
    gauge = SurfaceStrainGauge(model.u, np.array([[0.0, 0.0], [9.0, 3.0], [14.0, -12.0]]), StrainGauge(1.0))
    sensitivity = DisplacementSensitivity(model)
    params, design = SkinParams(0.0012, 0.017, 11.0, 0.2, 30.0), Design(0.05, -0.05)
    start_counting()
    symbolic = event_count("MatLUFactorSym")
    with_derivatives, without = [], []
    model.simulate(params, design, on_frame=lambda t: with_derivatives.append((gauge(), sensitivity(["mu"]))))
    assert event_count("MatLUFactorSym") - symbolic == 1
    model.simulate(params, design, on_frame=lambda t: without.append(gauge()))
    scale = np.abs(without[-1]).max()
    for (fields, _), reference in zip(with_derivatives, without, strict=True):
        np.testing.assert_allclose(fields, reference, rtol=0, atol=1e-8 * scale)
