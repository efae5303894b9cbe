"""Forward sensitivities of the DIC strain against finite differences of full simulations."""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.params import Design, SkinParams

NAMES = ["mu", "k1", "theta", "muscle_stiffness.log_factor", "skin_thickness.log_factor"]
STEPS = {"mu": 1e-7, "k1": 1e-6, "theta": 1e-3, "muscle_stiffness.log_factor": 1e-4, "skin_thickness.log_factor": 1e-4}


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
    from inference.forward import FEForward, PointSet

    g = np.linspace(-16, 16, 9)
    obs = [PointSet(np.array([0.05, -0.05]), 1.0, np.stack(np.meshgrid(g, g), -1).reshape(-1, 2))]
    forward = FEForward(
        small_config, obs, small_config.sweep.box, mesh_dir, increments=2, comm=MPI.COMM_SELF, continuation=False
    )
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
    for k, (name, step) in enumerate([("mu", 1e-7), ("theta", 1e-3)]):
        dx = step * (np.array(forward.names) == name)
        difference = (forward(x + dx) - forward(x - dx)) / (2 * step)
        assert np.abs(difference).max() > 0
        np.testing.assert_allclose(jacobian[..., k], difference, atol=1e-5 * np.abs(difference).max(), err_msg=name)
