"""Synthetic truth of paper Sec. 4.1 (bayesreg.truth.contact): the constrained minimiser of the
strain energy with the skull as a frictionless obstacle."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bayesreg.truth.contact import constrained_shift
from bayesreg.fem.element import stiffness_matrix
from bayesreg.data.images import Image
from bayesreg.mesh.tetmesh import boundary_nodes
from conftest import box_mesh
from helpers import world_grid


PAPER_LAM = np.array([1e-6, 10.0, 30.0])  # CSF, GM, WM (paper Sec. 4.1)


PAPER_MU = np.array([1e-6, 1.0, 1.0])


def slab_case():
    """30 mm box, top face pushed, forbidden slab with voxel faces at z = -1.5 mm."""
    mesh = box_mesh(n=(3, 3, 3), size=(30, 30, 30))
    forb, aff, xyz = world_grid(-10.0, 40.0, 1.0)
    forb[xyz[..., 2] <= -2.0] = True
    pushed = np.flatnonzero(mesh.nodes[:, 2] == 30.0)
    return mesh, Image(forb.astype(np.uint8), aff), pushed


def direct_solve(mesh, lam, mu, fixed, u_fixed):
    """``K_ff u_f = -K_fc u_c`` with SciPy's sparse direct solver."""
    k = sp.csr_matrix(stiffness_matrix(mesh.nodes, mesh.tets, lam, mu))
    n = len(mesh.nodes)
    dc = (3 * np.asarray(fixed)[:, None] + np.arange(3)).ravel()
    df = np.setdiff1d(np.arange(3 * n), dc)
    u = np.zeros(3 * n)
    u[dc] = u_fixed.ravel()
    u[df] = spla.spsolve(sp.csc_matrix(k[df][:, df]), -(k[df][:, dc] @ u[dc]))
    return u.reshape(n, 3), k


def test_no_active_constraint_equals_direct_solve():
    mesh = box_mesh(n=(3, 3, 3), size=(30, 30, 30))
    lam = np.array([2.0, 10.0, 30.0])[mesh.tissue]
    mu = np.ones(len(mesh.tets))
    forb, aff, xyz = world_grid(-20.0, 50.0, 2.0)
    forb[np.all(xyz < -14.0, axis=-1)] = True  # a corner far from the mesh
    truth, info = constrained_shift(mesh, lam, mu, Image(forb, aff), shift_mm=3.0)

    # default pushed nodes: the 20 boundary nodes of largest z (16 on the top face)
    z = mesh.nodes[info["pushed"], 2]
    assert len(info["pushed"]) == 20 and np.sum(z == 30.0) == 16 and np.all(z >= 20.0)
    cog = np.array([15.0, 15.0, 15.0])
    p = np.asarray(info["pushed"])
    dirs = (cog - mesh.nodes[p]) / np.linalg.norm(cog - mesh.nodes[p], axis=1, keepdims=True)
    u_ref, k = direct_solve(mesh, lam, mu, p, 3.0 * dirs)
    np.testing.assert_allclose(truth.u[p], 3.0 * dirs, rtol=0, atol=1e-14)
    assert np.abs(truth.u - u_ref).max() <= 1e-8 * np.abs(u_ref).max()
    assert info["converged"] and info["n_active"] == 0 and info["n_forbidden_nodes"] == 0
    assert info["energy"] == pytest.approx(info["energy_unconstrained"], rel=1e-10)
    assert info["energy"] == pytest.approx(0.5 * u_ref.ravel() @ (k @ u_ref.ravel()), rel=1e-10)
    assert info["max_violation_mm"] < -5.0 and info["n_inverted"] == 0
    json.dumps(info)


def test_active_constraint_slides_and_satisfies_kkt():
    mesh, forb, pushed = slab_case()
    lam = np.array([2.0, 10.0, 30.0])[mesh.tissue]
    mu = np.ones(len(mesh.tets))
    truth, info = constrained_shift(mesh, lam, mu, forb, shift_mm=5.0, pushed=pushed)
    u = truth.u
    y = mesh.nodes + u
    tol, c = info["tol_mm"], info["clearance_mm"]
    assert c == pytest.approx(0.5 * np.sqrt(3.0))
    assert info["converged"] and info["n_forbidden_nodes"] == 0 and info["n_inverted"] == 0
    assert info["max_violation_mm"] <= -c + tol
    assert info["energy"] >= info["energy_unconstrained"]
    # the unconstrained minimiser would put bottom nodes into the slab
    u_free, k = direct_solve(mesh, lam, mu, pushed, truth.u[pushed])
    assert (mesh.nodes + u_free)[:, 2].min() < -2.0
    assert info["energy_unconstrained"] == pytest.approx(
        0.5 * u_free.ravel() @ (k @ u_free.ravel()), rel=1e-10)

    # active nodes: on the level set z = -1.5 + c (d is exact for a face-aligned wall)
    active = np.flatnonzero(np.abs(y[:, 2] - (-1.5 + c)) <= tol)
    assert info["n_active"] == len(active) >= 4
    assert np.all(mesh.nodes[active, 2] == 0.0) and np.all(y[:, 2] >= -1.5 + c - tol)
    assert np.linalg.norm(u[active, :2], axis=1).max() > 0.5  # they slide along the wall

    # KKT: no force on free inactive nodes, frictionless contact (normal force only,
    # pointing out of the wall) on active ones
    f = (k @ u.ravel()).reshape(-1, 3)
    scale = np.abs(f[pushed]).max()
    free = np.setdiff1d(np.arange(len(mesh.nodes)), np.concatenate([pushed, active]))
    assert np.abs(f[free]).max() <= 1e-7 * scale
    assert np.abs(f[active, :2]).max() <= 1e-7 * scale
    assert np.all(f[active, 2] >= -1e-7 * scale) and f[active, 2].sum() > 1e-2 * scale


def test_paper_stiffness_ratio_converges():
    mesh, forb, pushed = slab_case()  # tissue by x thirds: CSF, GM, WM
    lam, mu = PAPER_LAM[mesh.tissue], PAPER_MU[mesh.tissue]
    truth, info = constrained_shift(mesh, lam, mu, forb, shift_mm=5.0, pushed=pushed)
    assert info["converged"] and info["n_inverted"] == 0 and info["n_forbidden_nodes"] == 0
    # every constrained node keeps its clearance (the full one, or its smaller rest distance)
    assert info["max_constraint_mm"] <= info["tol_mm"]
    assert info["max_violation_mm"] < 0
    assert info["n_active"] > 0 and info["energy"] >= info["energy_unconstrained"]
    f = stiffness_matrix(mesh.nodes, mesh.tets, lam, mu) @ truth.u.ravel()
    interior = np.setdiff1d(np.arange(len(mesh.nodes)), boundary_nodes(mesh.tets))
    assert np.abs(f.reshape(-1, 3)[interior]).max() <= 1e-9 * np.abs(f).max()


def test_load_stepping_keeps_every_node_on_its_side_of_a_skull_fin():
    """A 4 mm fin of skull under the box, open beyond x = 40 mm (the space below it is
    connected to the box's, as the two sides of the falx are).  The box, pushed 12 mm down,
    would rest below the fin at the unconstrained minimiser; solved in one step, the bottom
    nodes are pulled out of the fin on its far side (a lower energy that no continuous
    motion reaches); by load steps (the default, 12 here) they rest on the fin."""
    mesh = box_mesh(n=(3, 3, 3), size=(30, 30, 30))
    forb, aff, xyz = world_grid(-20.0, 60.0, 1.0)
    forb[xyz[..., 2] <= -16.0] = True
    forb[(xyz[..., 2] <= -2.0) & (xyz[..., 2] >= -6.0) & (xyz[..., 0] <= 40)] = True
    forb = Image(forb.astype(np.uint8), aff)
    pushed = np.flatnonzero(mesh.nodes[:, 2] == 30.0)
    lam, mu = np.array([2.0, 10.0, 30.0])[mesh.tissue], np.ones(len(mesh.tets))
    bottom = mesh.nodes[:, 2] == 0.0
    one, info1 = constrained_shift(mesh, lam, mu, forb, shift_mm=12.0, pushed=pushed, load_steps=1)
    assert info1["converged"] and info1["load_steps"] == 1
    assert (mesh.nodes + one.u)[bottom, 2].min() < -6.0  # tunnelled through the fin
    truth, info = constrained_shift(mesh, lam, mu, forb, shift_mm=12.0, pushed=pushed)
    assert info["converged"] and info["load_steps"] == 12 and info["load_factor"] == 1.0
    assert info["n_forbidden_nodes"] == 0 and info["n_inverted"] == 0
    y = mesh.nodes + truth.u
    assert y[:, 2].min() > -2.0 and info["n_active"] > 0
    np.testing.assert_allclose(truth.u[pushed], one.u[pushed], atol=1e-12)
    # every node's straight path from rest to the truth stays out of the skull
    ts = np.linspace(0.0, 1.0, 41)[:, None, None]
    path = (mesh.nodes[None] + ts * truth.u[None]).reshape(-1, 3)
    ijk = np.rint((path - aff[:3, 3]) / 1.0).astype(int)
    assert not forb.data[tuple(ijk.T)].any()
    assert info["energy"] > info1["energy"]


def test_constrained_shift_bad_arguments():
    mesh, forb, pushed = slab_case()
    lam = mu = np.ones(len(mesh.tets))
    with pytest.raises(ValueError, match="shift_mm"):
        constrained_shift(mesh, lam, mu, forb, shift_mm=0.0)
    with pytest.raises(ValueError, match="n_pushed"):
        constrained_shift(mesh, lam, mu, forb, n_pushed=0)
    with pytest.raises(ValueError, match="load_steps"):
        constrained_shift(mesh, lam, mu, forb, load_steps=0)
    centre = int(np.flatnonzero(np.all(mesh.nodes == 10.0, axis=1))[0])
    with pytest.raises(ValueError, match=rf"\[{centre}\] are not boundary"):
        constrained_shift(mesh, lam, mu, forb, pushed=[pushed[0], centre])
    with pytest.raises(ValueError, match="shape"):
        constrained_shift(mesh, lam[:-1], mu, forb)
    block, aff, xyz = world_grid(-10.0, 40.0, 1.0)
    block[np.linalg.norm(xyz - 15.0, axis=-1) < 5.0] = True  # around the centre of gravity
    with pytest.raises(ValueError, match="target of pushed node"):
        constrained_shift(mesh, lam, mu, Image(block, aff), shift_mm=15.0, pushed=pushed)


def test_brain_paper_truth(brain):
    _, labels, mesh = brain
    lam, mu = PAPER_LAM[mesh.tissue], PAPER_MU[mesh.tissue]
    skull = Image(labels.data == 4, labels.affine)
    truth, info = constrained_shift(mesh, lam, mu, skull, shift_mm=15.0)
    json.dumps(info)
    assert info["converged"] and info["n_forbidden_nodes"] == 0 and info["n_inverted"] == 0
    # every constrained node keeps its clearance (the full one, or its smaller rest distance)
    assert info["max_constraint_mm"] <= info["tol_mm"]
    assert info["max_violation_mm"] < 0
    assert info["n_active"] > 0 and info["energy"] > info["energy_unconstrained"]
    np.testing.assert_allclose(np.linalg.norm(truth.u[truth.pushed], axis=1), 15.0)


def crush_case():
    """A 60 mm column, its top 10 mm soft (CSF), squeezed 15 mm from both ends toward its
    centre (top and bottom faces pushed): the stiff part resists, the soft layer (1e-6)
    resists nothing, so without the volume constraint it is crushed through zero volume."""
    base = box_mesh(n=(3, 3, 6), size=(30, 30, 60))
    cent = base.nodes[base.tets].mean(1)
    mesh = box_mesh(n=(3, 3, 6), size=(30, 30, 60), tissue=np.where(cent[:, 2] > 50.0, 0, 1))
    forb, aff, xyz = world_grid(-20.0, 80.0, 2.0)
    forb[np.all(xyz < -15.0, axis=-1)] = True  # a corner far from the mesh
    pushed = np.flatnonzero((mesh.nodes[:, 2] == 60.0) | (mesh.nodes[:, 2] == 0.0))
    return mesh, Image(forb.astype(np.uint8), aff), pushed


def test_no_element_shrinks_below_its_minimum_volume_ratio():
    mesh, forb, pushed = crush_case()
    lam, mu = PAPER_LAM[mesh.tissue], PAPER_MU[mesh.tissue]
    from bayesreg.mesh.tetmesh import signed_volumes

    v0 = signed_volumes(mesh.nodes, mesh.tets)
    # the bound is active: the crushed layer would go through zero volume without it
    _, loose = constrained_shift(mesh, lam, mu, forb, shift_mm=15.0, pushed=pushed, min_volume_ratio=0.0)
    assert abs(loose["min_volume_ratio"]) <= 1e-3 and loose["n_volume_active"] > 0
    energy = loose["energy"]
    for q in (0.05, 0.2):
        truth, info = constrained_shift(mesh, lam, mu, forb, shift_mm=15.0, pushed=pushed, min_volume_ratio=q)
        ratio = signed_volumes(mesh.nodes + truth.u, mesh.tets) / v0
        assert info["converged"] and info["n_inverted"] == 0 and info["n_forbidden_nodes"] == 0
        assert info["min_volume_ratio"] == pytest.approx(ratio.min())
        # the bound holds to the tolerance (g_e = h_e (q - ratio) <= tol_mm, h_e = V0^(1/3))
        assert ratio.min() >= q - info["tol_mm"] / np.cbrt(v0).min()
        assert info["n_volume_active"] > 0 and np.all(mesh.tissue[ratio < q + 0.01] == 0)
        assert info["energy"] >= energy * (1 - 1e-9)  # a tighter bound costs energy
        energy = info["energy"]
    with pytest.raises(ValueError, match="min_volume_ratio"):
        constrained_shift(mesh, lam, mu, forb, min_volume_ratio=1.0)
