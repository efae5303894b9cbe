import dataclasses

import numpy as np
import pytest

from skinfem.config import Config
from skinfem.mesh import TAGS, build_mesh, capped_sizes, graded_sizes, inplane_coordinates


def test_graded_sizes_fill_length_and_grow_to_h_far():
    sizes = graded_sizes(15.0, 0.5, 2.0)
    assert sizes.sum() == pytest.approx(15.0, rel=1e-12)
    assert sizes[0] == pytest.approx(0.5, rel=0.05)
    assert abs(np.log(sizes[-1] / 2.0)) < 0.15
    assert np.all(np.diff(sizes) > 0)


def test_inplane_grid_is_symmetric_and_refined_under_membrane():
    x = inplane_coordinates(Config().mesh)
    np.testing.assert_allclose(x, -x[::-1], atol=1e-12)
    inside = np.diff(x)[(x[:-1] >= -10 - 1e-9) & (x[1:] <= 10 + 1e-9)]
    np.testing.assert_allclose(inside, 0.5, rtol=1e-9)
    assert x[0] == -25 and x[-1] == 25


def test_edge_refinement_grades_both_ways_from_the_membrane_edge():
    """h_edge: the two cells touching x = +-a are h_edge, neighbours grow by at most 1.3 towards
    the centre (to about h_membrane) and towards the block edge; the grid stays symmetric."""
    from skinfem.mesh import EDGE_GROWTH

    mesh = Config().mesh.__class__(h_membrane=2.0, h_far=6.0, h_edge=0.25)
    x = inplane_coordinates(mesh)
    np.testing.assert_allclose(x, -x[::-1], atol=1e-12)
    h = np.diff(x)
    edge = int(np.argmin(np.abs(x - 10.0)))
    assert x[edge] == pytest.approx(10.0, abs=1e-12)
    assert h[edge - 1] == pytest.approx(0.25, rel=0.05) and h[edge] == pytest.approx(0.25, rel=1e-9)
    growth = np.maximum(h[1:] / h[:-1], h[:-1] / h[1:])
    assert growth.max() <= EDGE_GROWTH + 1e-9
    assert 1.5 < h[len(h) // 2] <= 2.0 + 1e-9  # centre cells about h_membrane
    assert x[0] == -25 and x[-1] == 25
    unrefined = [inplane_coordinates(dataclasses.replace(mesh, h_edge=h)) for h in (0.0, 2.0)]
    np.testing.assert_array_equal(unrefined[0], unrefined[1])  # h_edge = h_membrane: no refinement


def test_graded_sizes_respect_a_largest_growth_ratio():
    sizes = graded_sizes(15.0, 0.25, 6.0, max_ratio=1.3)
    assert sizes.sum() == pytest.approx(15.0, rel=1e-12)
    assert np.all(sizes[1:] / sizes[:-1] <= 1.3 + 1e-9) and sizes[0] == pytest.approx(0.25, rel=0.05)
    assert graded_sizes(15.0, 0.5, 2.0, max_ratio=10.0) == pytest.approx(graded_sizes(15.0, 0.5, 2.0))


def test_capped_sizes_grow_geometrically_then_stay_uniform():
    """The first cell is h_start, each next one ``growth`` times larger until h_max, then equal
    cells of at most h_max fill the length exactly."""
    sizes = capped_sizes(15.0, 0.125, 4.0, 2.0)
    np.testing.assert_allclose(sizes[:5], [0.125, 0.25, 0.5, 1.0, 2.0], rtol=1e-12)
    assert sizes.sum() == pytest.approx(15.0, rel=1e-12) and sizes.max() <= 4.0 + 1e-12
    np.testing.assert_allclose(sizes[5:], sizes[-1], rtol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(200):  # neighbours within max(growth, 2), cells <= h_max, first cell exact
        growth, h0 = rng.uniform(1.1, 4.0), rng.uniform(0.01, 1.0)
        h_max = h0 * rng.uniform(1.5, 100)
        length = h_max * rng.uniform(3, 20)
        sizes = capped_sizes(length, h0, h_max, growth)
        ratio = np.maximum(sizes[1:] / sizes[:-1], sizes[:-1] / sizes[1:])
        assert sizes.sum() == pytest.approx(length, rel=1e-12) and sizes[0] == pytest.approx(h0, rel=1e-12)
        assert sizes.max() <= h_max * (1 + 1e-12) and ratio.max() <= max(growth, 2.0) * (1 + 1e-9)


def test_edge_growth_grades_geometrically_towards_the_membrane_edge():
    """mesh.edge_growth = 2: 0.125 mm cells at x = +-a, doubling away from it to h_membrane
    (inside) and h_far (outside) — fewer cells than the one-progression grading of the same
    edge size, symmetric, the block's ends kept."""
    mesh = Config().mesh.__class__(h_membrane=2.0, h_far=4.0, h_edge=0.125, edge_growth=2.0)
    x = inplane_coordinates(mesh)
    np.testing.assert_allclose(x, -x[::-1], atol=1e-12)
    h = np.diff(x)
    edge = int(np.argmin(np.abs(x - 10.0)))
    assert x[edge] == pytest.approx(10.0, abs=1e-12)
    np.testing.assert_allclose(h[edge - 4 : edge + 4], [1.0, 0.5, 0.25, 0.125, 0.125, 0.25, 0.5, 1.0], rtol=1e-9)
    assert h.max() <= 4.0 + 1e-9 and np.max(np.maximum(h[1:] / h[:-1], h[:-1] / h[1:])) <= 2.0 + 1e-9
    assert x[0] == -25 and x[-1] == 25
    assert len(x) < len(inplane_coordinates(dataclasses.replace(mesh, edge_growth=0.0)))


def test_small_mesh_counts_and_groups(tmp_path):
    import gmsh

    cfg = Config().with_changes(mesh={"h_membrane": 2.0, "h_far": 6.0, "muscle_layers": 2})
    info = build_mesh(cfg, tmp_path / "m.msh")
    n = len(inplane_coordinates(cfg.mesh)) - 1
    n_mem = 10
    assert info.n_skin_cells == n * n
    assert info.n_cells == n * n * 3 + n_mem * n_mem
    assert info.n_nodes == (n + 1) ** 2 * 4 + (n_mem + 1) ** 2
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(info.path))
        groups = {gmsh.model.getPhysicalName(d, t): (d, t) for d, t in gmsh.model.getPhysicalGroups()}
        for name in ("skin", "muscle", "membrane", "bottom", "sides", "top", "footprint"):
            assert groups[name][1] == TAGS[name]
        # every element is a hexahedron (gmsh type 5)
        types, _, _ = gmsh.model.mesh.getElements(3)
        assert list(types) == [5]
    finally:
        gmsh.finalize()


def test_rigid_membrane_mesh_has_no_membrane(tmp_path):
    cfg = Config().with_changes(mesh={"h_membrane": 2.0, "h_far": 6.0, "muscle_layers": 2}, membrane={"model": "rigid"})
    info = build_mesh(cfg, tmp_path / "r.msh")
    assert info.n_cells == 3 * info.n_skin_cells
