import numpy as np
import pytest

from skinfem.config import Config
from skinfem.mesh import TAGS, build_mesh, graded_sizes, inplane_coordinates


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
    cfg = Config().with_changes(
        mesh={"h_membrane": 2.0, "h_far": 6.0, "muscle_layers": 2}, membrane={"model": "rigid"}
    )
    info = build_mesh(cfg, tmp_path / "r.msh")
    assert info.n_cells == 3 * info.n_skin_cells
