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
