"""Candidate effects: each one equals an independent route to the same physics.

Muscle stiffness, compressibility and bonding must equal the baseline with the changed
configuration value; skin thickness must equal the baseline on a mesh with the thicker skin
(the effect maps the mesh's skin layer instead); pre-stretch must respect the mirror symmetry
of the block and, without shear, leave the unloaded in-plane state undisplaced (a homogeneous
pre-stress is then in equilibrium with the rollers). All at the final load of one design, 2 increments (the
equilibrium does not depend on the load path; checked below).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from mpi4py import MPI

from skinfem.effects import EFFECTS, prestretch_log_strain, principal_prestretch
from skinfem.params import Design, SkinParams

PARAMS = SkinParams(0.0012, 0.017, 11.0, 0.285, 30.0)
DESIGN = Design(0.05, -0.05)


def final_strain(model, params=PARAMS, design=DESIGN):
    return model.simulate(params, design).strain[-1]


@pytest.fixture(scope="module")
def fast_config(small_config):
    return small_config.with_changes(solver={"increments": 2})


@pytest.fixture(scope="module")
def effects_model(fast_config, mesh_dir):
    from skinfem.model import SkinModel

    return SkinModel(fast_config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=list(EFFECTS))


@pytest.fixture(scope="module")
def baseline(small_model):
    return final_strain(small_model)


def reset(model):
    model.set_effects({name: get_null(name) for name in model.effect_constants})


def get_null(qualified: str) -> float:
    effect, name = qualified.split(".")
    return next(q.null for q in EFFECTS[effect].parameters if q.name == name)


def test_registry_declares_parameters_with_null_inside_the_prior():
    for cls in EFFECTS.values():
        assert cls.description and cls.parameters
        for q in cls.parameters:
            assert q.low <= q.null <= q.high and q.low < q.high and q.unit


def test_reports_state_a_log_factor_as_the_factor_on_the_assumed_quantity():
    for name, quantity in [("muscle_stiffness", "muscle shear modulus"), ("skin_thickness", "skin thickness")]:
        assert EFFECTS[name].describe({"log_factor": math.log(2.0)}) == f"{quantity} 2.00 times the assumed one."
    assert EFFECTS["compressibility"].describe({"log_factor": -0.544}).endswith(" 0.58 times the assumed one.")
    assert EFFECTS["pre_stretch"].describe(prestretch_log_strain(1.08, 1.02, 30.0)) == (
        "pre-stretch 1.080 x 1.020, major axis at 30 deg."
    )


def test_prestretch_parametrisation_round_trips():
    eps = prestretch_log_strain(1.08, 1.02, 30.0)
    l1, l2, angle = principal_prestretch(eps["eps_xx"], eps["eps_yy"], eps["eps_xy"])
    assert (l1, l2, angle) == pytest.approx((1.08, 1.02, 30.0), rel=1e-12)


def test_null_effects_are_the_baseline_and_path_independent(effects_model, baseline):
    reset(effects_model)
    # the baseline used 10 increments, this model 2: same equilibrium
    assert np.abs(final_strain(effects_model) - baseline).max() < 1e-10


def test_scalar_effects_equal_the_changed_configuration(effects_model, fast_config, mesh_dir):
    from skinfem.model import SkinModel

    a, b, c = 0.5, 1.0, 30.0
    m = fast_config.membrane
    changed = fast_config.with_changes(
        muscle={"mu": fast_config.muscle.mu * math.exp(a)},
        skin={"bulk_ratio": fast_config.skin.bulk_ratio * math.exp(b)},
        membrane={"G13": 1 / (1 / m.G13 + c), "G23": 1 / (1 / m.G23 + c)},
    )
    reference = final_strain(SkinModel(changed, MPI.COMM_SELF, mesh_dir=mesh_dir))
    reset(effects_model)
    effects_model.set_effects(
        {"muscle_stiffness.log_factor": a, "compressibility.log_factor": b, "bonding.compliance": c}
    )
    got = final_strain(effects_model)
    reset(effects_model)
    assert np.abs(got - reference).max() < 1e-9 * np.abs(reference).max() + 1e-12
    assert np.abs(got - final_strain(effects_model)).max() > 1e-3  # the effects do change the field


def test_skin_thickness_effect_equals_a_thicker_skin_mesh(effects_model, fast_config, mesh_dir):
    from skinfem.model import SkinModel

    s = 0.3
    thicker = fast_config.with_changes(mesh={"skin_thickness": fast_config.mesh.skin_thickness * math.exp(s)})
    model = SkinModel(thicker, MPI.COMM_SELF, mesh_dir=mesh_dir)
    reference = final_strain(model)
    assert np.allclose(model.strain_sampler.xy, effects_model.strain_sampler.xy)
    reset(effects_model)
    effects_model.set_effects({"skin_thickness.log_factor": s})
    got = final_strain(effects_model)
    reset(effects_model)
    assert np.abs(got - reference).max() < 1e-8


def test_principal_prestretch_along_the_fibers_is_a_homogeneous_unloaded_state(effects_model):
    """Principal axes along x, y and fibers along x: no shear stress, so the rollers hold the
    homogeneous pre-stressed state and only the thickness adjusts."""
    reset(effects_model)
    effects_model.set_effects({"pre_stretch.eps_xx": math.log(1.08), "pre_stretch.eps_yy": math.log(1.02)})
    final_strain(effects_model, SkinParams(*PARAMS.as_array()[:4], 0.0))
    reset(effects_model)
    u_ref = effects_model.u_ref.x.array.reshape(-1, 3)
    assert np.abs(u_ref[:, :2]).max() < 1e-9
    assert np.abs(u_ref[:, 2]).max() > 1e-4  # the skin changes thickness: the pre-stress is real


def test_prestretch_is_mirror_symmetric(effects_model):
    eps = prestretch_log_strain(1.08, 1.02, 30.0)
    reset(effects_model)
    effects_model.set_effects({f"pre_stretch.{k}": v for k, v in eps.items()})
    plus = final_strain(effects_model)
    mirrored = {**eps, "eps_xy": -eps["eps_xy"]}
    effects_model.set_effects({f"pre_stretch.{k}": v for k, v in mirrored.items()})
    minus = final_strain(effects_model, SkinParams(*PARAMS.as_array()[:4], -PARAMS.theta))
    reset(effects_model)
    xy = effects_model.strain_sampler.xy
    key = {tuple(np.round(p, 6)): i for i, p in enumerate(xy)}
    partner = np.array([key[(round(x, 6), round(-y, 6) + 0.0)] for x, y in xy])
    assert np.abs(minus[partner, :2] - plus[:, :2]).max() < 1e-9
    assert np.abs(minus[partner, 2] + plus[:, 2]).max() < 1e-9
    assert np.abs(plus - final_strain(effects_model)).max() > 1e-3


def test_bad_effect_names_and_values_are_refused(effects_model, fast_config, mesh_dir):
    from skinfem.model import SkinModel

    with pytest.raises(ValueError, match="unknown effect parameter 'pre_stretch.lambda1'.*pre_stretch.eps_xx"):
        effects_model.set_effects({"pre_stretch.lambda1": 1.1})
    with pytest.raises(ValueError, match="must be finite"):
        effects_model.set_effects({"bonding.compliance": float("nan")})
    with pytest.raises(ValueError, match="unknown effect 'prestretch'; known effects: pre_stretch"):
        SkinModel(fast_config, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=["prestretch"])
