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


def test_sensitivities_on_a_kept_factorisation_equal_direct_solves(small_config, mesh_dir):
    """du/dp of three equilibria (frames t = 0.5 and 1, then t = 1 at a 5 % softer skin: a
    calibration's next point), solved by GMRES on kept factorisations, equal those of one direct
    LU solve per state (refactor_krylov 0) to 1e-7 of the largest; the nearby point reuses the
    previous state's factorisation (the load doubling may not)."""
    from skinfem.krylov import KRYLOV_BUDGET
    from skinfem.model import SkinModel
    from skinfem.sensitivity import DisplacementSensitivity

    names = ["mu", "theta", "muscle_stiffness.log_factor"]
    design = Design(0.05, -0.05)
    points = [{"mu": 0.0012, "k1": 0.017, "k2": 11.0, "kappa": 0.2, "theta": 30.0}]
    points.append({**points[0], "mu": 0.95 * 0.0012})
    derivatives, factorisations = {}, {}
    for refactor_krylov in (0, 10):
        config = small_config.with_changes(solver={"increments": 2, "refactor_krylov": refactor_krylov})
        model = SkinModel(config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=["muscle_stiffness"])
        sensitivity = DisplacementSensitivity(model)
        states, counts = derivatives.setdefault(refactor_krylov, []), factorisations.setdefault(refactor_krylov, [])

        def record(t, last_only):
            if t == 1.0 or not last_only:
                states.append(np.concatenate([du.x.array for du in sensitivity(names)]))
                counts.append(sensitivity.factorisations)

        for k, params in enumerate(points):
            model.simulate(SkinParams(**params), design, on_frame=lambda t, last=k > 0: record(t, last))
        if refactor_krylov:
            assert 0 < sensitivity.krylov_iterations <= 2 * len(states) * len(names) * KRYLOV_BUDGET
    direct, kept = np.array(derivatives[0]), np.array(derivatives[10])
    assert direct.shape[0] == 3
    np.testing.assert_allclose(kept, direct, rtol=0, atol=1e-7 * np.abs(direct).max())
    assert factorisations[0] == [1, 2, 3]
    assert factorisations[10][-1] == factorisations[10][-2] <= 2
