"""The problem's data (bayesreg.model.problem): a run on a given mesh file."""

import jax.numpy as jnp
import meshio
import numpy as np
import pytest

from bayesreg.config import load_config
from bayesreg.model.problem import make_data


def test_a_run_on_a_given_mesh_gets_that_mesh_and_the_same_data(tmp_path):
    """``mesh.file``: the job's data on a run's written mesh are those of that run (mesh,
    tissues, boundary, synthetic truth, ``m``), which fTetWild alone cannot repeat; a mesh
    that reaches into the skull is reported, with the key named."""
    tiny = ["data.resolution_mm=3.0", "mesh.edge_length_mm=26"]
    first = make_data(load_config("configs/quickstart.yaml", overrides=tiny))
    mesh = first.mesh
    path = tmp_path / "mesh.vtu"  # as bayesreg.outputs.write writes it
    meshio.write(path, meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)],
                                   cell_data={"tissue": [mesh.tissue.astype(np.int32)]}))
    again = make_data(load_config("configs/quickstart.yaml", overrides=tiny + [f"mesh.file={path}"]))
    for a, b in zip(again.mesh, mesh):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(again.truth.u, first.truth.u)
    np.testing.assert_array_equal(again.m.data, first.m.data)
    np.testing.assert_array_equal(again.labels.data, first.labels.data)
    assert again.mesh_info["file"] == str(path) and len(again.mesh_info["sha256"]) == 64

    grown = tmp_path / "grown.vtu"  # 15% larger about its centre: nodes in the skull
    centre = mesh.nodes.mean(0)
    meshio.write(grown, meshio.Mesh(centre + 1.15 * (mesh.nodes - centre), [("tetra", mesh.tets)]))
    with pytest.warns(UserWarning, match=r"mesh.file .*grown.vtu: \d+ of its \d+ nodes lie in the "
                      r"skull region of the label map at rest"):
        make_data(load_config("configs/quickstart.yaml", overrides=tiny + [f"mesh.file={grown}"]))


def test_a_truth_the_model_did_not_make_from_data_to_errors(tmp_path):
    """``synthetic.truth: bump``: a dense field the FE model cannot make: ``m`` is ``f``
    moved by it (``m(x + u(x)) ~= f(x)``), the truth has no Lamé parameters (no parameter
    truth to compare), survives the checkpoint, and the error table compares the
    posterior mean, the start and a reference field over the brain's voxels and gives the
    coverage where the tissue moves.  A random field, and an FE truth plus one
    (``synthetic.discrepancy_mm``: dense, yet its Lamé parameters known), on the same mesh."""
    from types import SimpleNamespace

    from bayesreg import configure_jax
    from bayesreg.checkpoint import Checkpoint
    from bayesreg.outputs.fields import node_slots
    from bayesreg.data.images import grid_points, interpolate_numpy
    from bayesreg.data.labels import TISSUE_LABELS
    from bayesreg.outputs.write import error_table
    from bayesreg.model.problem import assemble
    from bayesreg.mesh.warp import interpolation_matrix

    configure_jax()
    tiny = ["data.resolution_mm=3.0", "mesh.edge_length_mm=26", "synthetic.truth=bump",
            "synthetic.lam=null", "synthetic.mu=null", "synthetic.shift_mm=6", "synthetic.falloff_mm=20"]
    cfg = load_config("configs/quickstart.yaml", overrides=tiny)
    data = make_data(cfg)
    truth = data.truth
    assert truth.field is not None and not truth.made_by_model and truth.lam_e is None
    assert data.truth_info["truth"] == "bump" and "lam" not in data.truth_info
    # m(y) = f(x) with x + u(x) = y at the brain's voxels the bump moves (x by the fixed
    # point x <- y - u(x), u through registration.displacement_at)
    from bayesreg.data.registration import displacement_at

    u = truth.field.data.reshape(-1, 3)
    moved = np.isin(data.labels.data.ravel(), TISSUE_LABELS) & (np.linalg.norm(u, axis=1) > 1.0)
    y = grid_points(data.f)[moved]
    x = y.copy()
    for _ in range(60):
        x = y - displacement_at(truth.field, x)
    assert np.abs(x + displacement_at(truth.field, x) - y).max() < 1e-6
    from bayesreg.model.problem import SYNTHETIC_ORDER

    np.testing.assert_allclose(data.m.data.ravel()[moved],
                               interpolate_numpy(data.f, x, order=SYNTHETIC_ORDER), atol=1e-5)
    assert np.abs(data.m.data.ravel()[moved] - data.f.data.ravel()[moved]).mean() > 0.01  # it moved

    # the same field from a file (ITK/ANTs form, LPS float32) on the same mesh: the same truth
    from bayesreg.interop.transforms import save_displacement

    field_file = save_displacement(truth.field.data, truth.field.affine, tmp_path / "u.nii.gz")
    mesh_file = tmp_path / "mesh.vtu"
    meshio.write(mesh_file, meshio.Mesh(data.mesh.nodes, [("tetra", data.mesh.tets)]))
    again = make_data(load_config("configs/quickstart.yaml", overrides=[
        "data.resolution_mm=3.0", f"mesh.file={mesh_file}", "synthetic.truth=field",
        f"synthetic.field={field_file}", "synthetic.lam=null", "synthetic.mu=null",
        "synthetic.shift_mm=null", "synthetic.falloff_mm=null"]))
    assert again.truth_info["truth"] == "field" and len(again.truth_info["sha256"]) == 64
    np.testing.assert_allclose(again.truth.u, truth.u, atol=1e-5)
    np.testing.assert_allclose(again.m.data, data.m.data, atol=1e-4)
    # a smooth random field on the same mesh (2 mm: the 5 mm margin of these labels holds it)
    from bayesreg.model.problem import _make_truth, _truth_line

    rand_cfg = load_config("configs/mismatch_random.yaml", overrides=["synthetic.shift_mm=2"])
    rand, info = _make_truth(rand_cfg, data.mesh, data.labels)
    assert info["truth"] == "random" and info["length_mm"] == 30.0 and not rand.made_by_model
    np.testing.assert_allclose(np.linalg.norm(rand.u, axis=1).max(), 2.0, rtol=0.02)
    assert _truth_line(info, rand.u).startswith("random (not made by the model), smoothing sd 30 mm")
    # the FE truth plus a volume-preserving random field: a dense truth with known ratios
    fe_cfg = load_config("configs/mismatch_discrepancy.yaml", overrides=[
        "data.resolution_mm=3.0", "synthetic.shift_mm=2", "synthetic.discrepancy_mm=1.5"])
    plus, info = _make_truth(fe_cfg, data.mesh, data.labels)
    assert info["truth"] == "smooth" and info["discrepancy"]["solenoidal"] and info["n_inverted"] == 0
    assert plus.parameters_known and not plus.made_by_model and plus.field is not None
    fe_only, _ = _make_truth(load_config("configs/quickstart.yaml", overrides=[
        "data.resolution_mm=3.0", "synthetic.shift_mm=2"]), data.mesh, data.labels)
    added = np.linalg.norm(plus.u - fe_only.u, axis=1)
    np.testing.assert_allclose(added.max(), 1.5, rtol=0.02)
    assert _truth_line(info, plus.u).endswith("plus a volume-preserving random field of 1.5 mm "
                                              "(smoothing sd 30 mm, not made by the model)")
    assert assemble(fe_cfg, data._replace(truth=plus)).phi_true is not None

    ckpt = Checkpoint(tmp_path)
    ckpt.save_problem(data)
    back = ckpt.load_problem().truth
    assert back.lam_e is None and back.field is not None
    np.testing.assert_array_equal(back.field.data, truth.field.data)
    np.testing.assert_array_equal(back.u, truth.u)

    problem = assemble(cfg, data)
    assert problem.phi_true is None
    # draws as from a calibrated posterior: centred on truth + delta, delta of their own sd
    rng = np.random.default_rng(0)
    b, i = node_slots(problem)
    c, d, s = 2, 400, 0.5
    centre = truth.u + rng.normal(0.0, s, truth.u.shape)
    nodal = centre + rng.normal(0.0, s, (c, d, *truth.u.shape))
    phi = np.broadcast_to(problem.phi_init, (c, d, len(problem.phi_init)))
    result = SimpleNamespace(positions=np.concatenate([nodal[:, :, b].reshape(c, d, -1), phi], -1),
                             interior=nodal[:, :, i])
    w, in_mesh = interpolation_matrix(problem.mesh, problem.f)
    errors = error_table(problem, result, np.zeros_like(truth.u), grid=(w, in_mesh),
                         reference=truth.field)
    assert all("true" not in r for r in errors["ratio"].values())
    cm = errors["coverage_moving"]
    k = cm["n_components"]
    assert k == 3 * int(np.sum(np.linalg.norm(truth.u, axis=1) >= 1.0)) > 30
    assert abs(cm["0.9"] - 0.9) < 4 * np.sqrt(0.09 / k) + 0.01, cm
    mse = errors["brain"]["mse_mm2"]
    assert mse["reference"] == 0.0 and errors["boundary_reference_mm"]["max"] < 1e-9
    assert 0.0 < mse["posterior_mean"] < mse["start"]
    # the mesh's best fit to the dense truth: nearer it than the draws' mean, near the
    # truth at the nodes (the bump varies slowly within an element), printed with its coverage
    best = errors["mesh_best_fit"]
    assert best["brain_mse_mm2"] < mse["posterior_mean"]
    # the images' term at the truth's nodal u and at the draws' mean (0.5 mm of noise off it):
    # -E_s / T_s of the posterior's own SSD, and the mean fits the images worse than the truth
    from bayesreg.model.posterior import energies
    from bayesreg.outputs.fields import nodal_mean

    fit, post = errors["image_fit"], problem.posterior
    for key, u in (("truth", truth.u), ("posterior_mean", nodal_mean(problem, result))):
        e_s = float(energies(post, jnp.asarray(u), jnp.asarray(problem.phi_init))[0])
        np.testing.assert_allclose(fit[key], -e_s * float(post.inv_t_s), rtol=1e-10)
    assert fit["gain_nats"] == fit["posterior_mean"] - fit["truth"] < 0
    assert 0.0 < best["nodes_from_truth_mm"]["median"] < 0.5
    assert 0.5 < best["coverage_moving"]["0.9"] <= 1.0
    from bayesreg.outputs.printed import format_report

    sampler = {"converged": True, "rhat_classic_max": 1.0, "rhat_classic_split_max": 1.0,
               "rhat_rank_max": 1.0, "ess_bulk_min": 800.0, "ess_tail_min": 800.0,
               "stuck_chains": [], "draws_per_chain": d, "blocks": ["u_b"], "acceptance": [0.8],
               "thinning": 1, "chains": c, "cg_iterations_per_step_mean": 1.0,
               "solve_failures": 0, "steps_per_s_per_chain": 1.0}
    report = format_report(errors, {"sampler": sampler}).splitlines()
    line = next(x for x in report if "best fit" in x)
    assert f"90% coverage of it {best['coverage_moving']['0.9']:.2f}" in line
    line = next(x for x in report if "images' term" in x)
    assert f"truth {fit['truth']:.1f}, posterior mean {fit['posterior_mean']:.1f}" in line
