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
    continuation.record(
        "mixed", ConvergedStates(x0, a_ref + B_ref @ x0, {t: a[t] + B[t] @ x0 for t in a}, sensitivities)
    )
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

    bounds = config.sweep.box
    g = np.linspace(-18, 18, 13)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    obs = [
        PointSet(np.array([0.05, -0.05]), 1.0, xy),
        PointSet(np.array([0.05, -0.05]), 0.5, xy),
        PointSet(np.array([-0.05, 0.05]), 1.0, xy),
    ]
    return FEForward(config, obs, bounds, mesh_dir, increments=2, comm=MPI.COMM_SELF, continuation=continuation)


@pytest.mark.slow
def test_continued_fields_and_jacobians_equal_ramped_ones(small_config, mesh_dir):
    """A calibration-like sequence of points (skin parameters, a pre-stretch that makes the
    reference pre-stressed, the muscle and bonding effects) evaluated by continuation from the
    previous point and, independently, by ramping the load from zero: fields and exact
    Jacobians agree to the Newton tolerance (1e-8 of their largest entry), and continuation was
    the route taken; a pre-stressed reference is solved on a fresh factorisation, never by
    GMRES on the kept one of a loaded frame."""
    from skinfem.model import Factorisation

    warm = two_design_forward(small_config, mesh_dir, continuation=True)
    ramped = two_design_forward(small_config, mesh_dir, continuation=False)
    model, newton, unloaded = warm.model, warm.model._newton, []  # policies of the unloaded solves

    def recording(policy):
        if float(model.alpha11.value) == float(model.alpha22.value) == 0.0:
            unloaded.append(policy)
        return newton(policy)

    model._newton = recording
    names = warm.names[:5] + ["pre_stretch.eps_xx", "pre_stretch.eps_xy", "muscle_stiffness.log_factor"]
    x = warm.null.copy()
    x[:5] = TRUTH
    moves = [
        {},
        {"mu": 1e-4, "theta": 5.0},
        {"k1": 1e-3, "kappa": -0.005, "pre_stretch.eps_xx": 0.04},
        {"pre_stretch.eps_xy": 0.02, "muscle_stiffness.log_factor": 0.3, "bonding.compliance": 5.0},
        {"k2": -1.0, "theta": 10.0},
    ]
    for move in moves:
        for name, step in move.items():
            x[warm.names.index(name)] += step
        ((f_warm, j_warm),) = warm.evaluate_with_jacobian([x], names)
        ((f_ramp, j_ramp),) = ramped.evaluate_with_jacobian([x], names)
        np.testing.assert_allclose(f_warm, f_ramp, atol=1e-8 * np.abs(f_ramp).max(), err_msg=str(move))
        np.testing.assert_allclose(j_warm, j_ramp, atol=1e-8 * np.abs(j_ramp).max(), err_msg=str(move))
    assert warm.continued == 2 * (len(moves) - 1) and ramped.continued == 0
    assert np.abs(f_ramp).max() > 0.03
    assert len(unloaded) >= 2 * 3 and min(unloaded) >= Factorisation.FIRST_STEP, unloaded


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


def test_transfer_between_meshes_is_exact_for_affine_fields():
    """States interpolated from a Q1 mesh into a Q2 space on another mesh of the same block:
    affine fields (which both spaces represent exactly) arrive unchanged."""
    from skinfem.continuation import transfer
    from skinfem.fenics import dolfinx

    def space(n, degree):
        mesh = dolfinx.mesh.create_box(
            MPI.COMM_SELF, [[-1.0, -1.0, -0.5], [1.0, 1.0, 0.0]], n, dolfinx.mesh.CellType.hexahedron
        )
        return dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (3,)))

    V_from, V_to = space([3, 4, 2], 1), space([5, 2, 3], 2)
    A = np.array([[0.1, -0.2, 0.3], [0.05, 0.0, -0.1], [0.2, 0.1, 0.0]])

    def affine(V, scale):
        u = dolfinx.fem.Function(V)
        u.interpolate(lambda x: scale * (A @ x + 0.01))
        return u.x.array.copy()

    states = ConvergedStates(
        np.ones(2), affine(V_from, 0.5), {1.0: affine(V_from, 1.0)}, {1: (None, {1.0: affine(V_from, 2.0)})}
    )
    moved = transfer(states, V_from, V_to)
    np.testing.assert_allclose(moved.reference, affine(V_to, 0.5), atol=1e-12)
    np.testing.assert_allclose(moved.frames[1.0], affine(V_to, 1.0), atol=1e-12)
    assert moved.sensitivities[1][0] is None
    np.testing.assert_allclose(moved.sensitivities[1][1][1.0], affine(V_to, 2.0), atol=1e-12)


def test_edge_refinement_halves_only_the_edge_cells_and_doubles_the_layers(small_config):
    from inference.criticism.discretisation import refined_config

    m = small_config.mesh
    refined = refined_config(small_config, "edge").mesh
    assert (refined.h_membrane, refined.h_far, refined.h_edge) == (m.h_membrane, m.h_far, m.h_membrane / 2)
    assert (refined.skin_layers, refined.muscle_layers) == (2 * m.skin_layers, 2 * m.muscle_layers)
    twice = refined_config(small_config.with_changes(mesh={"h_edge": 0.5}), "edge").mesh
    assert twice.h_edge == 0.25
    with pytest.raises(ValueError, match="unknown refinement"):
        refined_config(small_config, "nowhere")


def test_a_quadratic_mesh_with_two_skin_layers_keeps_them_when_refined(small_config):
    """Two quadratic skin layers are converged through the thickness (doubling them moves the
    DIC strain 0.8 %, the muscle layers 3.5 %): the refined mesh doubles only the others."""
    from inference.criticism.discretisation import refined_config

    quadratic = small_config.with_changes(mesh={"skin_layers": 2}, solver={"element_degree": 2})
    for refinement in ("edge", "uniform"):
        m = refined_config(quadratic, refinement).mesh
        assert (m.skin_layers, m.muscle_layers, m.membrane_layers) == (2, 4, 2)
    one_layer = refined_config(quadratic.with_changes(mesh={"skin_layers": 1}), "edge").mesh
    assert one_layer.skin_layers == 2


@pytest.mark.slow
def test_a_refined_mesh_continued_from_the_check_mesh_equals_its_ramp(small_config, mesh_dir):
    """The discretisation estimate's refined mesh started from the check mesh's interpolated
    fields (not a load ramp) gives the refined mesh's own ramped fields."""
    from inference.criticism.discretisation import refined_config

    coarse = two_design_forward(small_config, mesh_dir, continuation=True)
    x = coarse.null.copy()
    x[:5] = TRUTH
    x[coarse.names.index("pre_stretch.eps_xx")] = 0.03
    coarse.evaluate_with_jacobian([x], coarse.names[:5])
    fine_config = refined_config(small_config, "edge")
    fine = two_design_forward(fine_config, mesh_dir, continuation=True)
    x[0] *= 1.05  # the estimate runs at the calibrated point, near the last one
    fine.continue_from(coarse, x)
    # the check mesh's factors are freed while the refined mesh runs: its factor is an empty one
    assert not coarse.model.problem.solver.getKSP().getPC().getFactorMatrix().assembled
    f_continued = fine(x)
    f_ramped = two_design_forward(fine_config, mesh_dir, continuation=False)(x)
    assert fine.continued == 2
    np.testing.assert_allclose(f_continued, f_ramped, atol=1e-8 * np.abs(f_ramped).max())
    # each transferred run is recorded: both designs continued, by Newton–LU
    assert [(r.design, r.continued) for r in fine.transferred_runs] == [(d, True) for d in fine.designs]
    assert all(r.factorizations >= 1 and r.seconds > 0 for r in fine.transferred_runs)
    assert all(r.far_starts[-1].converged for r in fine.transferred_runs)
    # the first frame's correction of its interpolated guess is carried to the second frame's
    # guess: one factorisation there instead of a second Newton–LU (4; measured: 7 and 6 in all)
    one_frame, two_frames = sorted(fine.transferred_runs, key=lambda r: r.design[0])
    assert two_frames.design == (0.05, -0.05)
    assert two_frames.factorizations <= one_frame.factorizations + 2


@pytest.mark.slow
def test_a_refined_mesh_continues_from_a_check_mesh_whose_fields_came_from_its_cache(small_config, mesh_dir, tmp_path):
    """In a resumed check the check mesh's fields come from ``cache_dir`` and it holds no
    converged states: it solves the point once (one run per design) and the refined mesh still
    continues from its fields instead of ramping; once the refined fields are cached as well, a
    resumed estimate solves nothing."""
    from inference.criticism.discretisation import refined_config

    def check_mesh():
        model = two_design_forward(small_config, mesh_dir, continuation=True)
        model.cache_dir = tmp_path
        return model

    first = check_mesh()
    x = first.null.copy()
    x[:5] = TRUTH
    first(x)  # the interrupted check wrote its cache
    coarse = check_mesh()
    coarse(x)
    assert coarse.reused == 2 and coarse.runs == 0  # the resumed model read both designs
    fine = two_design_forward(refined_config(small_config, "edge"), mesh_dir, continuation=True)
    fine.continue_from(coarse, x)
    assert coarse.runs == 2
    fine.cache_dir = tmp_path
    fine(x)
    assert fine.continued == 2
    # resumed again: the refined fields are in the cache too, so nothing is solved on either mesh
    coarse = check_mesh()
    again = two_design_forward(refined_config(small_config, "edge"), mesh_dir, continuation=True)
    again.cache_dir = tmp_path
    again.continue_from(coarse, x)
    np.testing.assert_array_equal(again(x), fine(x))
    assert (coarse.runs, again.runs, again.reused) == (0, 0, 2)


@pytest.mark.slow
def test_a_resumed_estimate_finds_the_refined_run_with_derivatives(small_config, mesh_dir, tmp_path):
    """With the drift of the mesh's error the refined mesh's fields at x come from its run with
    derivatives by every parameter: a resumed check reads them from ``cache_dir`` and solves
    nothing on either mesh (before, the check mesh solved x again to continue a run not needed)."""
    from inference.criticism.discretisation import refined_config

    fine_config = refined_config(small_config, "edge")
    fine = two_design_forward(fine_config, mesh_dir, continuation=True)
    fine.cache_dir = tmp_path
    x = fine.null.copy()
    x[:5] = TRUTH
    (with_derivatives,) = fine.evaluate_with_jacobian([x], fine.names)
    coarse = two_design_forward(small_config, mesh_dir, continuation=True)
    again = two_design_forward(fine_config, mesh_dir, continuation=True)
    again.cache_dir = tmp_path
    again.continue_from(coarse, x)
    assert (coarse.runs, again.runs, again.transferred) == (0, 0, False)
    np.testing.assert_array_equal(again(x), with_derivatives[0])
    assert again.runs == 0


@pytest.mark.slow
def test_a_refined_run_that_cannot_continue_is_ramped_and_says_so(small_config, mesh_dir, monkeypatch, caplog):
    """A transfer whose pseudo-time (one step allowed) cannot converge falls back to the load
    ramp: the ramped fields, and a warning naming the design and how the solve went (the ramp
    is what makes a refined run slow)."""
    import skinfem.pseudo_time
    from inference.criticism.discretisation import refined_config

    coarse = two_design_forward(small_config, mesh_dir, continuation=True)
    x = coarse.null.copy()
    x[:5] = TRUTH
    fine_config = refined_config(small_config, "edge")
    fine = two_design_forward(fine_config, mesh_dir, continuation=True)
    fine.continue_from(coarse, x)
    monkeypatch.setattr(skinfem.pseudo_time, "BUDGET", 1)
    f_fine = fine(x)
    assert fine.continued == 0
    message = "design (-0.05, 0.05): the solve from another mesh's fields did not converge (pseudo-time 1 steps, "
    assert message in caplog.text and "; ramping the load" in caplog.text
    # the record counts the failed solve's two factorisations and the ramp's
    assert [r.continued for r in fine.transferred_runs] == [False, False]
    assert all(r.factorizations > 2 for r in fine.transferred_runs)
    # the unloaded reference (already at equilibrium: no step), then the frame's failure
    for run in fine.transferred_runs:
        reference, frame = run.far_starts
        assert (reference.converged, reference.steps) == (True, ())
        assert (frame.converged, len(frame.steps)) == (False, 1)
    f_ramped = two_design_forward(fine_config, mesh_dir, continuation=False)(x)
    np.testing.assert_allclose(f_fine, f_ramped, atol=1e-8 * np.abs(f_ramped).max())


def test_pseudo_time_reaches_the_ramped_equilibrium_where_newton_fails(small_model):
    """From zero displacement at the full load Newton capped at 4 iterations fails (the ramp's
    first increment, a tenth of the load, takes 4); pseudo-transient continuation, the solve of a
    far start (``EVERY_STEP``), reaches the ramped simulation's equilibrium from there to the
    Newton tolerance."""
    from skinfem.model import Factorisation
    from skinfem.params import Design, SkinParams

    params, design = SkinParams.from_array(TRUTH), Design(0.05, -0.05)
    small_model.simulate(params, design)
    ramped = small_model.u.x.array.copy()
    zero = [(1.0, np.zeros_like(ramped))]
    assert not small_model.solve_frames(params, design, zero, max_iterations=4, factorisation=Factorisation.FIRST_STEP)
    assert small_model.solve_frames(params, design, zero, max_iterations=4, factorisation=Factorisation.EVERY_STEP)
    np.testing.assert_allclose(small_model.u.x.array, ramped, atol=1e-8 * np.abs(ramped).max())
    (solve,) = small_model.far_starts
    assert solve.converged and solve.steps
    assert small_model.factorizations == solve.factorisations  # those of the steps that renewed it
    # the steps record the residual their linearisation predicted, |D du| / dt: on the plateau
    # where dt alone holds the flow back the two agree (a wrong formula would not, to 1 %)
    gaps = [abs(step.residual / step.predicted - 1) for step in solve.steps if step.accepted]
    assert min(gaps) < 1e-2


def test_pseudo_time_grows_dt_tenfold_after_two_linear_steps():
    """dt after a step: divided by 4 after a rejected one; 10x after two kept steps that did
    what their linearisation predicted (within 10 %); else twice the residual's fall, clipped to
    [2, 10]x — a rejected step in between, or one nonlinear step, keeps the slow growth."""
    from skinfem.pseudo_time import PseudoTimeStep, next_step

    def step(dt, residual, predicted, accepted=True):
        return PseudoTimeStep(dt, residual, predicted, accepted)

    linear, nonlinear = step(10.0, 1.05e-3, 1e-3), step(10.0, 1.2e-3, 1e-3)
    assert linear.linear and not nonlinear.linear
    assert next_step([linear, step(20.0, 0.9e-3, 0.95e-3)], norm=1e-3) == pytest.approx(200.0)
    assert next_step([linear, step(20.0, 1e-4, 1.05e-4)], norm=1.2e-3) == pytest.approx(200.0)
    assert next_step([nonlinear, step(20.0, 1.5e-3, 1.45e-3)], norm=1e-3) == pytest.approx(40.0)  # rose: 2x
    assert next_step([nonlinear, step(20.0, 2.5e-4, 1e-4)], norm=1e-3) == pytest.approx(160.0)  # twice a fall of 4
    assert next_step([nonlinear, step(20.0, 1e-6, 1e-9)], norm=1e-3) == pytest.approx(200.0)  # at most 10x
    rejected = step(40.0, 5e-3, 5e-3, accepted=False)
    assert not rejected.linear
    assert next_step([linear, rejected], norm=1e-3) == pytest.approx(10.0)
    assert next_step([rejected, step(10.0, 1.5e-3, 1.5e-3)], norm=1e-3) == pytest.approx(20.0)


def test_pseudo_time_on_a_kept_factorisation_reaches_the_same_equilibrium_with_fewer(small_config, mesh_dir):
    """Pseudo-time steps solved by GMRES on an earlier step's factorisation (the default,
    ``solver.refactor_krylov`` 10) reach the ramped equilibrium as the steps factorised one by
    one (``refactor_krylov`` 0) do, in the same number of steps, with fewer factorisations; a
    step on a kept factorisation took at most ``KRYLOV_BUDGET`` GMRES iterations."""
    from skinfem.model import Factorisation, SkinModel
    from skinfem.params import Design, SkinParams
    from skinfem.pseudo_time import KRYLOV_BUDGET

    params, design = SkinParams.from_array(TRUTH), Design(0.125, -0.125)
    solves = {}
    for refactor in (0, 10):
        model = SkinModel(small_config.with_changes(solver={"refactor_krylov": refactor}), mesh_dir=mesh_dir)
        model.simulate(params, design)
        ramped = model.u.x.array.copy()
        zero = [(1.0, np.zeros_like(ramped))]
        assert model.solve_frames(params, design, zero, max_iterations=4, factorisation=Factorisation.EVERY_STEP)
        np.testing.assert_allclose(model.u.x.array, ramped, atol=1e-8 * np.abs(ramped).max())
        (solves[refactor],) = model.far_starts
        assert model.factorizations == solves[refactor].factorisations
    each, kept = solves[0].steps, solves[10].steps
    assert all(step.factorised for step in each) and len(kept) == len(each)
    assert 0 < sum(step.factorised for step in kept) < len(kept) / 2
    assert all(0 < step.krylov_iterations <= KRYLOV_BUDGET for step in kept if not step.factorised)


def test_a_non_finite_start_is_a_failed_solve_not_an_exception(small_model):
    """A starting field with a NaN (e.g. a transfer gone wrong) has no finite residual:
    pseudo-time takes no step and the solve reports failure (the caller then ramps the load)
    instead of raising, and says why without printing a NaN."""
    from skinfem.model import Factorisation
    from skinfem.params import Design, SkinParams

    start = np.zeros_like(small_model.u.x.array)
    start[5] = np.nan
    params, design = SkinParams.from_array(TRUTH), Design(0.05, -0.05)
    far = Factorisation.EVERY_STEP
    assert not small_model.solve_frames(params, design, [(1.0, start)], max_iterations=4, factorisation=far)
    (solve,) = small_model.far_starts
    assert (solve.converged, solve.steps, small_model.factorizations) == (False, (), 0)
    assert solve.describe() == "pseudo-time 0 steps, 0 factorisations (the start's residual is not finite)"


def test_a_far_start_describes_itself_in_one_line_without_a_nan():
    """The ramp warning's words: pseudo-time's steps and factorisations, the residual at the
    start and the one its last kept step reached, or that none was kept."""
    from skinfem.pseudo_time import FarStart, PseudoTimeStep

    steps = (PseudoTimeStep(10.0, 2e-3, 1e-3, True, 0, True), PseudoTimeStep(100.0, 9e-3, 1e-3, False, 4, False))
    assert FarStart(False, 0.0145, steps).describe() == "pseudo-time 2 steps, 1 factorisations (0.0145 -> 0.002 N)"
    none_kept = FarStart(False, 0.0145, steps[1:]).describe()
    assert none_kept == "pseudo-time 1 steps, 0 factorisations (0.0145 -> none kept)"
