"""Synthetic brain shift without the skull (bayesreg.truth.synthetic): the pushed nodes, the falloff
over the rest of the boundary, and the interior in equilibrium."""

import numpy as np
import pytest

from bayesreg.fem.element import stiffness_matrix
from bayesreg.truth.synthetic import brain_shift, centre_of_gravity, top_boundary
from conftest import box_mesh


def test_brain_shift_pushes_the_top_nodes_to_the_centre_and_the_interior_follows():
    """The ``n_pushed`` boundary nodes of largest z move ``shift_mm`` toward the volume
    centroid, the other boundary nodes toward it by the Gaussian falloff of their distance
    to the nearest pushed node, and the interior nodes carry no force (``K u = 0`` there)."""
    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    lam = np.array([2.0, 10.0, 30.0])[mesh.tissue]
    mu = np.ones(len(mesh.tets))
    cog = centre_of_gravity(mesh)
    np.testing.assert_allclose(cog, [15.0, 15.0, 15.0], atol=1e-12)  # a uniform box
    truth = brain_shift(mesh, lam, mu, shift_mm=4.0, n_pushed=16, falloff_mm=12.0)
    top = top_boundary(mesh, 16)
    np.testing.assert_array_equal(np.sort(mesh.boundary[top]), np.sort(truth.pushed))
    assert np.all(mesh.nodes[truth.pushed, 2] == 30.0)  # the 16 nodes of the top face
    pb = mesh.nodes[mesh.boundary]
    d = np.min(np.linalg.norm(pb[:, None] - pb[None, top], axis=2), axis=1)
    direction = (cog - pb) / np.linalg.norm(cog - pb, axis=1, keepdims=True)
    np.testing.assert_allclose(truth.u[mesh.boundary], 4.0 * np.exp(-0.5 * (d / 12.0) ** 2)[:, None] * direction,
                               rtol=0, atol=1e-12)
    f = (stiffness_matrix(mesh.nodes, mesh.tets, lam, mu) @ truth.u.ravel()).reshape(-1, 3)
    assert np.abs(f[mesh.interior]).max() <= 1e-9 * np.abs(f).max()
    np.testing.assert_array_equal(truth.lam_e, lam)
    for kwargs, match in (({"shift_mm": 0.0}, "shift_mm and falloff_mm must be > 0"),
                          ({"falloff_mm": -1.0}, "shift_mm and falloff_mm must be > 0"),
                          ({"n_pushed": 0}, r"n_pushed must lie in \[1, 56\], got 0")):
        with pytest.raises(ValueError, match=match):
            brain_shift(mesh, lam, mu, **kwargs)


def test_bump_field_is_a_gaussian_toward_the_centre_and_field_truth_samples_it_at_the_nodes():
    """``bump_field``: ``shift * exp(-|x - c|^2 / (2 r^2))`` along the unit vector from the
    top nodes' centroid ``c`` to the centre of gravity, at every voxel centre;
    ``field_truth``: the field at the nodes (trilinear), no Lamé parameters, the largest
    movers as ``pushed``; a bump that folds is refused."""
    from bayesreg.data.images import grid_points
    from bayesreg.truth.synthetic import bump_field, field_truth
    from helpers import smooth_image

    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    grid = smooth_image(shape=(36, 36, 36), origin=-3.0)
    field = bump_field(grid, mesh, shift_mm=5.0, n_pushed=16, radius_mm=10.0)
    c = np.array([15.0, 15.0, 30.0])  # the top face's 16 nodes
    pts = grid_points(grid)
    want = 5.0 * np.exp(-0.5 * np.sum((pts - c) ** 2, axis=1) / 100.0)[:, None] * [0.0, 0.0, -1.0]
    np.testing.assert_allclose(field.data.reshape(-1, 3), want, atol=1e-12)
    truth = field_truth(mesh, field, n_pushed=8)  # 4 top, 4 below: no ties
    at_nodes = 5.0 * np.exp(-0.5 * np.sum((mesh.nodes - c) ** 2, axis=1) / 100.0)
    # trilinear between voxel centres 1 mm apart: second-order error of the Gaussian
    np.testing.assert_allclose(truth.u[:, 2], -at_nodes, atol=0.02)
    assert truth.lam_e is None and truth.mu_e is None and not truth.made_by_model
    assert truth.field is field and len(truth.pushed) == 8
    assert set(truth.pushed) == set(np.argsort(-at_nodes)[:8])
    with pytest.raises(ValueError, match="folds the image"):
        bump_field(grid, mesh, shift_mm=20.0, radius_mm=10.0)


def test_random_field_is_a_smooth_gaussian_field_scaled_at_the_nodes():
    """``random_field``: the largest displacement at the nodes is ``shift_mm`` (``field_truth``
    samples the field there); each component's correlation between voxels ``d`` apart is
    the Gaussian ``exp(-d^2 / (4 L^2))`` of white noise smoothed by a Gaussian of sd ``L``
    (within 0.1); the seed fixes the field; a field that folds the image is refused."""
    from bayesreg.truth.synthetic import field_truth, random_field
    from helpers import smooth_image

    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    grid = smooth_image(shape=(40, 40, 40), origin=-5.0)
    field = random_field(grid, mesh, shift_mm=2.0, length_mm=3.0, seed=1)
    truth = field_truth(mesh, field)
    np.testing.assert_allclose(np.linalg.norm(truth.u, axis=1).max(), 2.0, rtol=0.02)
    u = field.data
    for lag in (1, 3, 6, 9):
        got = np.mean([np.corrcoef(np.moveaxis(u[..., c], a, 0)[:-lag].ravel(),
                                   np.moveaxis(u[..., c], a, 0)[lag:].ravel())[0, 1]
                       for c in range(3) for a in range(3)])
        assert abs(got - np.exp(-lag**2 / 36.0)) < 0.1, (lag, got)
    np.testing.assert_array_equal(random_field(grid, mesh, shift_mm=2.0, length_mm=3.0, seed=1).data, u)
    assert np.abs(random_field(grid, mesh, shift_mm=2.0, length_mm=3.0, seed=2).data - u).max() > 0.5
    with pytest.raises(ValueError, match="folds the image"):
        random_field(grid, mesh, shift_mm=15.0, length_mm=3.0)


def test_the_solenoidal_random_field_preserves_volume():
    """``random_field(solenoidal=True)``: the curl of a random potential, scaled at the nodes
    like the plain field; its divergence (NumPy's central differences on the voxel grid) is
    a small fraction of the plain field's, whose volume change is of the order of
    ``shift_mm / length_mm``; ``synthetic.solenoidal`` is refused for other truths."""
    from bayesreg.config import ConfigError, load_config
    from bayesreg.truth.synthetic import field_truth, random_field
    from helpers import smooth_image

    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    grid = smooth_image(shape=(40, 40, 40), origin=-5.0)

    def divergence(field):
        u = field.data
        return sum(np.gradient(u[..., c], axis=c) for c in range(3))[4:-4, 4:-4, 4:-4]

    plain = random_field(grid, mesh, shift_mm=2.0, length_mm=6.0, seed=3)
    curl = random_field(grid, mesh, shift_mm=2.0, length_mm=6.0, seed=3, solenoidal=True)
    np.testing.assert_allclose(np.linalg.norm(field_truth(mesh, curl).u, axis=1).max(), 2.0, rtol=0.02)
    assert np.abs(curl.data - plain.data).max() > 0.5
    assert np.abs(divergence(curl)).max() < 0.1 * np.abs(divergence(plain)).max()
    with pytest.raises(ConfigError, match="synthetic.solenoidal"):
        load_config("configs/mismatch_bump.yaml", overrides=["synthetic.solenoidal=true"])


def test_an_fe_truth_with_a_discrepancy_keeps_its_parameters_and_adds_the_field(tmp_path):
    """``with_discrepancy``: at every voxel centre inside the mesh the dense truth is the
    linear interpolation of the FE nodal field in its tetrahedron (barycentric coordinates
    computed here from the vertices) plus the added field, beyond it the inverse-square
    mean of the nearest boundary nodes' plus the field; at the nodes the FE values plus the
    field read there.  The Lamé parameters stay (``parameters_known``) while
    ``made_by_model`` is false; the checkpoint keeps both; a dense truth is refused; the
    config refuses ``discrepancy_mm`` on a dense truth and accepts ``solenoidal`` with it."""
    from bayesreg.checkpoint import Checkpoint
    from bayesreg.config import ConfigError, load_config
    from bayesreg.data.images import grid_points
    from bayesreg.data.registration import displacement_at
    from bayesreg.model.problem import ProblemData
    from bayesreg.truth.synthetic import field_truth, random_field, with_discrepancy
    from helpers import smooth_image

    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    lam = np.array([2.0, 10.0, 30.0])[mesh.tissue]
    mu = np.ones(len(mesh.tets))
    fe = brain_shift(mesh, lam, mu, shift_mm=3.0, n_pushed=16, falloff_mm=12.0)
    grid = smooth_image(shape=(40, 40, 40), origin=-5.0)
    extra = random_field(grid, mesh, shift_mm=1.5, length_mm=6.0, seed=4, solenoidal=True)
    truth = with_discrepancy(fe, mesh, extra)
    assert truth.parameters_known and not truth.made_by_model and fe.made_by_model
    np.testing.assert_array_equal(truth.lam_e, lam)
    np.testing.assert_array_equal(truth.pushed, fe.pushed)
    np.testing.assert_allclose(truth.u, fe.u + displacement_at(extra, mesh.nodes), atol=1e-12)
    pts = grid_points(grid)
    dense = truth.field.data.reshape(-1, 3) - extra.data.reshape(-1, 3)
    rng = np.random.default_rng(0)
    inside = np.all((pts > 0.5) & (pts < 29.5), axis=1)
    for p in rng.choice(np.flatnonzero(inside), 200, replace=False):
        for tet in mesh.tets:  # the element holding the voxel centre, by its barycentric coordinates
            x = mesh.nodes[tet]
            b = np.linalg.solve(np.vstack([x.T, np.ones(4)]), np.append(pts[p], 1.0))
            if b.min() >= -1e-9:
                np.testing.assert_allclose(dense[p], b @ fe.u[tet], atol=1e-9)
                break
        else:
            raise AssertionError(f"no element holds {pts[p]}")
    b = np.asarray(mesh.boundary)
    for p in rng.choice(np.flatnonzero(np.any((pts < -0.5) | (pts > 30.5), axis=1)), 200, replace=False):
        dist = np.linalg.norm(mesh.nodes[b] - pts[p], axis=1)  # beyond the mesh: 8 nearest
        k = np.argsort(dist)
        if dist[k[8]] - dist[k[7]] < 1e-6:  # a tie for the eighth nearest (the box's lattice)
            continue
        k = k[:8]
        np.testing.assert_allclose(dense[p], (fe.u[b[k]] / dist[k, None] ** 2).sum(0)
                                   / (1.0 / dist[k] ** 2).sum(), atol=1e-9)

    ckpt = Checkpoint(tmp_path)
    ckpt.save_problem(ProblemData(grid, grid, grid, mesh, truth, {"truth": "smooth"}, 1.0, 0, {}, None))
    back = ckpt.load_problem().truth
    assert back.parameters_known and not back.made_by_model
    np.testing.assert_array_equal(back.lam_e, lam)
    np.testing.assert_array_equal(back.field.data, truth.field.data)

    with pytest.raises(ValueError, match="adds to an FE truth"):
        with_discrepancy(field_truth(mesh, extra), mesh, extra)
    with pytest.raises(ConfigError, match="synthetic.discrepancy_mm adds to an FE truth"):
        load_config("configs/mismatch_bump.yaml", overrides=["synthetic.discrepancy_mm=2"])
    cfg = load_config("configs/quickstart.yaml", overrides=["synthetic.discrepancy_mm=2",
                                                           "synthetic.solenoidal=true"])
    assert cfg.synthetic.discrepancy_mm == 2.0 and cfg.synthetic.solenoidal
