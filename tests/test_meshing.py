"""Meshing a label map (bayesreg.mesh.meshing): to a node count, and argument checks."""

from __future__ import annotations

import numpy as np
import pytest

from bayesreg.mesh import meshing
from bayesreg.data.images import Image
from bayesreg.mesh.tetmesh import Mesh, MeshError, mesh_quality
from bayesreg.mesh.meshing import mesh_brain_sized
from helpers import ball_labels


def _fake_mesher(counts):
    """A stand-in for fTetWild: ``counts(h) -> n`` nodes at edge length ``h``; records calls."""
    calls = []

    def mesh_brain(labels, *, edge_length_mm, **kwargs):
        calls.append((edge_length_mm, kwargs))
        n = int(counts(edge_length_mm))
        nodes = np.linspace(0.0, 150.0, n)[:, None] * np.ones(3)  # a brain 150 mm across
        return Mesh(nodes, np.zeros((1, 4), np.int64), np.zeros(1, np.int64), np.arange(4))

    return mesh_brain, calls


def test_sized_mesh_on_the_brain_is_within_tolerance_and_reports_its_attempts(brain):
    _, labels, _ = brain
    mesh, info = mesh_brain_sized(labels, 600, tolerance=0.1, edge_length_mm=20.0)
    n = len(mesh.nodes)
    assert abs(n - 600) <= 60 and info["within_tolerance"]
    assert info["attempts"][-1]["n_nodes"] == n
    assert info["edge_length_mm"] == info["attempts"][-1]["edge_length_mm"]
    assert info["attempts"][0]["edge_length_mm"] == 20.0
    q = mesh_quality(mesh)
    assert q["n_inverted"] == 0 and q["n_nodes"] == n
    # every miss moves the edge length the right way: longer for too many nodes
    first = info["attempts"][0]
    if len(info["attempts"]) > 1:
        assert np.sign(info["attempts"][1]["edge_length_mm"] - 20.0) == np.sign(first["n_nodes"] - 600)


def test_sized_mesh_converges_on_the_power_law_and_passes_the_mesher_options(monkeypatch):
    fake, calls = _fake_mesher(lambda h: 900.0 * (16.0 / h) ** 4)
    monkeypatch.setattr(meshing, "mesh_brain", fake)
    mesh, info = mesh_brain_sized("labels", 801, tolerance=0.01, edge_length_mm=16.0, epsilon=0.03)
    # exact law, exponent known: the second attempt lands on the target
    assert [a["n_nodes"] for a in info["attempts"]] == [900, 801]
    assert info["edge_length_mm"] == pytest.approx(16.0 * (900 / 801) ** 0.25, abs=1e-4)
    assert len(mesh.nodes) == 801 and info["within_tolerance"]
    assert all(kw == {"epsilon": 0.03} for _, kw in calls)


def test_sized_mesh_damps_scatter_and_keeps_the_closest_with_a_warning(monkeypatch):
    # counts alternate 20% above and below the law: no attempt is within 1%
    k = iter(range(100))
    fake, calls = _fake_mesher(lambda h: 801.0 * (16.0 / h) ** 4 * (1.2 if next(k) % 2 == 0 else 0.8))
    monkeypatch.setattr(meshing, "mesh_brain", fake)
    with pytest.warns(UserWarning, match="no mesh within 1% of 801 nodes in 6 attempts"):
        mesh, info = mesh_brain_sized("labels", 801, tolerance=0.01, max_attempts=6, edge_length_mm=16.0)
    counts = [a["n_nodes"] for a in info["attempts"]]
    assert len(counts) == 6 and not info["within_tolerance"]
    assert len(mesh.nodes) == min(counts, key=lambda n: abs(n - 801))
    # the mean over attempts settles the edge length near the law's 16 mm; chasing the last
    # attempt alone would swing by a factor (1.2 / 0.8)^(1/4) = 1.11 every time
    edges = [a["edge_length_mm"] for a in info["attempts"]]
    assert max(abs(np.diff(edges[2:]))) < 0.05 * 16.0
    assert abs(edges[-1] - 16.0) < 0.05 * 16.0


@pytest.mark.parametrize("kwargs, match", [
    ({"target_nodes": 10}, "target_nodes"),
    ({"target_nodes": 800.5}, "target_nodes"),
    ({"target_nodes": 800, "tolerance": 0.0}, "tolerance"),
    ({"target_nodes": 800, "tolerance": 1.5}, "tolerance"),
    ({"target_nodes": 800, "max_attempts": 0}, "max_attempts"),
    ({"target_nodes": 800, "edge_length_mm": -1.0}, "edge_length_mm"),
])
def test_sized_mesh_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        mesh_brain_sized("labels", **kwargs)


@pytest.mark.parametrize("kwargs, match", [
    ({"edge_length_mm": 0.0}, r"edge_length_mm must be a finite number > 0, got 0\.0"),
    ({"edge_length_mm": -5.0}, "edge_length_mm must be a finite number > 0"),
    ({"edge_length_mm": np.nan}, "edge_length_mm must be a finite number > 0, got nan"),
    ({"epsilon": 0.0}, r"epsilon must be a finite number > 0, got 0\.0"),  # refused before fTetWild sees it
    ({"epsilon": -0.01}, "epsilon must be a finite number > 0"),
    ({"smoothing_sigma_mm": -1.0}, "smoothing_sigma_mm must be a finite number >= 0"),
    ({"smoothing_sigma_mm": np.nan}, "smoothing_sigma_mm must be a finite number >= 0"),
    ({"step_size": 0}, "step_size must be an integer >= 1, got 0"),
])
def test_mesh_brain_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        meshing.mesh_brain(ball_labels(), **kwargs)
    if "edge_length_mm" not in kwargs:  # checked before any meshing, as mesh_brain's
        with pytest.raises(ValueError, match=match):
            mesh_brain_sized("labels", 800, **kwargs)


def test_mesh_brain_rejects_bad_label_maps_and_names_a_smoothing_that_removes_the_surface():
    ball = ball_labels()
    with pytest.raises(ValueError, match=r"labels must be 3D, got shape \(16, 16\)"):
        meshing.mesh_brain(Image(ball.data[:, :, 8], ball.affine))
    with pytest.raises(ValueError, match="labels affine is singular"):
        meshing.mesh_brain(ball_labels(np.diag([2.0, 2.0, 0.0, 1.0])))
    # a smoothing that leaves no surface is named, as the cause
    with pytest.raises(MeshError, match=r"smoothing_sigma_mm=200 removed the brain surface"):
        meshing.mesh_brain(ball, smoothing_sigma_mm=200.0)
    with pytest.raises(ValueError, match=r"edge_length_mm must be a finite number > 0, got inf"):
        mesh_brain_sized("labels", 800, edge_length_mm=np.inf)


def test_sized_mesh_stops_at_the_brains_extent(monkeypatch):
    """A target below the coarsest mesh fTetWild makes (its counts stop falling once the
    edge nears the brain's size): the edge length grows to 0.9 of the brain's extent (150 mm
    here) and no further, and the search ends there with the closest mesh and a warning."""
    fake, calls = _fake_mesher(lambda h: max(180.0, 900.0 * (16.0 / h) ** 4))
    monkeypatch.setattr(meshing, "mesh_brain", fake)
    with pytest.warns(UserWarning, match="no mesh within 5% of 50 nodes"):
        mesh, info = mesh_brain_sized("labels", 50, max_attempts=12, edge_length_mm=100.0)
    edges = [h for h, _ in calls]
    assert edges == [100.0, pytest.approx(0.9 * 150.0)]  # 140 wanted, capped; then no more
    assert len(mesh.nodes) == 180 and len(info["attempts"]) == 2


def test_edge_longer_than_the_brain_is_refused_before_fTetWild(brain):
    _, labels, _ = brain
    with pytest.raises(MeshError, match=r"edge_length_mm=1000 exceeds the largest extent of the "
                       r"intracranial surface \(1[5-9]\d mm"):
        meshing.mesh_brain(labels, edge_length_mm=1000.0)
