"""The "How to add an effect" example of docs/architecture.md runs and does what it says.

Its ```python block is executed with the effect registry replaced by a copy, so the example
never stays registered for other tests. Checked: the effect is registered with its parameter,
unit, prior bounds and null value and describes itself for reports; and on a tiny FE model
(5 mm cells under the membrane, one muscle layer, 2 load increments; the equilibrium does not
depend on the load path): at its null value the field is the baseline's, loaded it equals
``pre_stretch`` with eps_xx = eps_yy = eps, eps_xy = 0 (an independent UFL route to the same
F0) and differs from the baseline, and with fibers along x its unloaded pre-stressed state is
homogeneous in plane (no shear stress, so the rollers hold it) while the skin changes thickness.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from skinfem import effects
from skinfem.params import Design, SkinParams

DOC = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
SECTION = "## How to add an effect"
PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)

PARAMS = SkinParams(0.0012, 0.017, 11.0, 0.285, 30.0)  # mu, k1 [MPa], k2, kappa [-], theta [deg]
DESIGN = Design(0.05, -0.05)
EPS = math.log(1.05)  # log pre-strain [-]


def example_source() -> str:
    """The first ```python block of the section."""
    text = DOC.read_text(encoding="utf-8")
    assert SECTION in text, f"{DOC.name} has no '{SECTION}' section"
    match = PYTHON_BLOCK.search(text.split(SECTION, 1)[1])
    assert match, f"{DOC.name}: no ```python block under '{SECTION}'"
    return match.group(1)


def register_example(monkeypatch: pytest.MonkeyPatch) -> dict:
    """Run the example against a copy of the registry (undone with ``monkeypatch``); its namespace."""
    monkeypatch.setattr(effects, "EFFECTS", dict(effects.EFFECTS))
    namespace = {"__name__": "architecture_example"}
    exec(compile(example_source(), str(DOC), "exec"), namespace)
    return namespace


def test_example_registers_an_effect_with_its_bounds_and_report_sentence(monkeypatch):
    original = effects.EFFECTS
    namespace = register_example(monkeypatch)
    cls = effects.get_effect("skin_tension")
    assert cls is namespace["SkinTension"] and issubclass(cls, effects.Effect)
    assert list(effects.EFFECTS) == [*original, "skin_tension"]
    (q,) = cls.parameters
    assert (q.name, q.unit, q.low, q.high, q.null) == ("eps", "-", -0.15, 0.15, 0.0)
    assert cls.prestressed and cls.description
    assert effects.effect_parameters(["skin_tension"]) == [("skin_tension.eps", q)]
    assert cls.describe({"eps": EPS}) == "equibiaxial skin pre-stretch 1.050."
    monkeypatch.undo()
    assert effects.EFFECTS is original and "skin_tension" not in original
    with pytest.raises(ValueError, match="unknown effect 'skin_tension'"):
        effects.get_effect("skin_tension")


@pytest.fixture(scope="module")
def models(small_config, mesh_dir):
    """(baseline, model with pre_stretch and the example) on the coarsest mesh the configuration
    allows around the membrane: 5 mm cells (4 across it), 15 mm at the block edge."""
    from skinfem.model import SkinModel

    tiny = small_config.with_changes(
        mesh={"h_membrane": 5.0, "h_far": 15.0, "muscle_layers": 1}, solver={"increments": 2}
    )
    with pytest.MonkeyPatch.context() as monkeypatch:
        register_example(monkeypatch)
        model = SkinModel(tiny, MPI.COMM_SELF, mesh_dir=mesh_dir, effects=["pre_stretch", "skin_tension"])
    return SkinModel(tiny, MPI.COMM_SELF, mesh_dir=mesh_dir), model


def final_strain(model, values: dict[str, float], params: SkinParams = PARAMS) -> np.ndarray:
    """Skin log strain [-] (n_cells, 3) at full load; effect parameters not in ``values`` are 0 (null)."""
    model.set_effects({name: 0.0 for name in model.effect_constants} | values)
    return model.simulate(params, DESIGN).strain[-1]


def test_example_acts_as_an_equibiaxial_pre_stretch(models):
    baseline, model = models
    null = final_strain(model, {})
    assert np.abs(null - final_strain(baseline, {})).max() < 1e-10
    tension = final_strain(model, {"skin_tension.eps": EPS})
    same = final_strain(model, {"pre_stretch.eps_xx": EPS, "pre_stretch.eps_yy": EPS})
    assert np.abs(tension - same).max() < 1e-10
    assert np.abs(tension - null).max() > 0.01 * np.abs(null).max()  # the effect changes the field by > 1 % of its peak


def test_example_unloaded_state_is_homogeneous_with_fibers_along_x(models):
    _, model = models
    final_strain(model, {"skin_tension.eps": EPS}, SkinParams(*PARAMS.as_array()[:4], 0.0))
    u_ref = model.u_ref.x.array.reshape(-1, 3)  # unloaded equilibrium [mm]
    assert np.abs(u_ref[:, :2]).max() < 1e-9
    assert np.abs(u_ref[:, 2]).max() > 1e-4  # the pre-stress is real: the skin changes thickness
