"""Meshing to a node count (bayesreg.mesh.mesh_brain_sized), argument checks, and a given
mesh read from a file (bayesreg.mesh.read_mesh, ``mesh.file``)."""

from __future__ import annotations

import numpy as np
import pytest

from bayesreg import mesh as M
from bayesreg import meshing
from bayesreg.mesh import Mesh, mesh_quality
from bayesreg.meshing import mesh_brain_sized


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


def _ball_labels(affine=None, shape=(16, 16, 16)):
    """A ball of grey matter (radius 5 voxels) in a 16^3 label map, 2 mm voxels."""
    from bayesreg import labels as L
    from bayesreg.images import Image

    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    data = np.where(np.linalg.norm(ijk - 7.5, axis=-1) < 5, L.GM, L.BACKGROUND).astype(np.uint8)
    return Image(data, np.diag([2.0, 2.0, 2.0, 1.0]) if affine is None else affine)


@pytest.mark.parametrize("kwargs, match", [
    ({"edge_length_mm": 0.0}, r"edge_length_mm must be a finite number > 0, got 0\.0"),
    ({"edge_length_mm": -5.0}, "edge_length_mm must be a finite number > 0"),
    ({"edge_length_mm": np.nan}, "edge_length_mm must be a finite number > 0, got nan"),
    ({"epsilon": 0.0}, r"epsilon must be a finite number > 0, got 0\.0"),  # before: std::bad_alloc
    ({"epsilon": -0.01}, "epsilon must be a finite number > 0"),
    ({"smoothing_sigma_mm": -1.0}, "smoothing_sigma_mm must be a finite number >= 0"),
    ({"smoothing_sigma_mm": np.nan}, "smoothing_sigma_mm must be a finite number >= 0"),
    ({"step_size": 0}, "step_size must be an integer >= 1, got 0"),
])
def test_mesh_brain_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        meshing.mesh_brain(_ball_labels(), **kwargs)
    if "edge_length_mm" not in kwargs:  # checked before any meshing, as mesh_brain's
        with pytest.raises(ValueError, match=match):
            mesh_brain_sized("labels", 800, **kwargs)


def test_mesh_brain_rejects_bad_label_maps_and_names_a_smoothing_that_removes_the_surface():
    from bayesreg.images import Image

    ball = _ball_labels()
    with pytest.raises(ValueError, match=r"labels must be 3D, got shape \(16, 16\)"):
        meshing.mesh_brain(Image(ball.data[:, :, 8], ball.affine))
    # before: "fTetWild returned 0 elements"
    with pytest.raises(ValueError, match="labels affine is singular"):
        meshing.mesh_brain(_ball_labels(np.diag([2.0, 2.0, 0.0, 1.0])))
    # before: scikit-image's "Surface level must be within volume data range"
    with pytest.raises(M.MeshError, match=r"smoothing_sigma_mm=200 removed the brain surface"):
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
    with pytest.raises(M.MeshError, match=r"edge_length_mm=1000 exceeds the largest extent of the "
                       r"intracranial surface \(1[5-9]\d mm"):
        meshing.mesh_brain(labels, edge_length_mm=1000.0)


def _box_in_ball():
    """A 3x3x3-cube box mesh, 12 mm wide, inside the ball of :func:`_ball_labels` (centre
    15 mm, radius 10 mm)."""
    from conftest import box_mesh

    return box_mesh((3, 3, 3), (12.0, 12.0, 12.0), origin=(9.0, 9.0, 9.0))


@pytest.mark.parametrize("suffix, fmt", [(".vtu", None), (".msh", "gmsh22")])
def test_read_mesh_round_trips_a_written_mesh(tmp_path, suffix, fmt):
    """A mesh written by meshio comes back with its points, its elements (oriented), the
    boundary of its surface and tissues from the label map: a point no element uses is
    dropped, surface triangles and a ``tissue`` cell array in the file are ignored."""
    import meshio

    from bayesreg.mesh import boundary_faces, label_elements, read_mesh

    labels = _ball_labels()
    box = _box_in_ball()
    tets = box.tets.copy()
    tets[::2, 2], tets[::2, 3] = box.tets[::2, 3], box.tets[::2, 2]  # half of them inverted
    nodes = np.vstack([box.nodes, [[99.0, 99.0, 99.0]]])  # an unused point, last
    cells = [("triangle", boundary_faces(box.tets).astype(np.int64)), ("tetra", tets)]
    tags = [np.zeros(len(cells[0][1]), np.int32), np.full(len(tets), 2, np.int32)]
    # a Gmsh file carries its physical and geometrical tags, a VTU the tissue of a run
    cell_data = {"gmsh:physical": tags, "gmsh:geometrical": tags} if fmt else {"tissue": tags}
    path = tmp_path / f"given{suffix}"
    meshio.write(path, meshio.Mesh(nodes, cells, cell_data=cell_data), file_format=fmt)

    mesh = read_mesh(path, labels)
    np.testing.assert_array_equal(mesh.nodes, box.nodes)  # world mm, exactly, unused dropped
    assert np.all(M.signed_volumes(mesh.nodes, mesh.tets) > 0)
    np.testing.assert_array_equal(np.sort(mesh.tets, axis=1), np.sort(box.tets, axis=1))
    np.testing.assert_array_equal(mesh.boundary, box.boundary)
    # the label map decides (all grey matter here), not the file's tissue array (WM)
    np.testing.assert_array_equal(mesh.tissue, label_elements(labels, mesh.nodes, mesh.tets))
    assert np.all(mesh.tissue == 1)


def test_read_mesh_refuses_unusable_files_with_the_reason(tmp_path):
    import meshio

    from bayesreg.mesh import boundary_faces, read_mesh

    labels = _ball_labels()
    box = _box_in_ball()

    def write(name, nodes, cells):
        path = tmp_path / name
        meshio.write(path, meshio.Mesh(nodes, cells))
        return path

    with pytest.raises(FileNotFoundError, match="mesh file not found: .*nowhere.vtu"):
        read_mesh(tmp_path / "nowhere.vtu", labels)
    junk = tmp_path / "junk.vtu"
    junk.write_text("not a mesh")
    with pytest.raises(M.MeshError, match="cannot read mesh file .*junk.vtu"):
        read_mesh(junk, labels)
    surface = write("surface.vtu", box.nodes, [("triangle", boundary_faces(box.tets))])
    with pytest.raises(M.MeshError, match=r"holds no tetrahedra \(its cells: triangle\)"):
        read_mesh(surface, labels)
    hexa = write("mixed.vtu", box.nodes, [("tetra", box.tets), ("hexahedron", np.arange(8)[None])])
    with pytest.raises(M.MeshError, match="volume cells of type hexahedron: .*linear tetrahedra"):
        read_mesh(hexa, labels)
    flat = write("flat.vtu", box.nodes, [("tetra", np.vstack([box.tets, [[0, 1, 2, 2]]]))])
    with pytest.raises(M.MeshError, match=r"1 degenerate .* the first \[162\]"):
        read_mesh(flat, labels)
    # the same mesh in voxel coordinates of the label map (2 mm voxels): outside the ball
    voxels = write("voxels.vtu", box.nodes / 2.0 - 4.0, [("tetra", box.tets)])
    with pytest.raises(M.MeshError, match=r"only 0% of its element centroids lie in the "
                       r"intracranial tissues .* world coordinates in mm"):
        read_mesh(voxels, labels)


def test_a_run_on_a_given_mesh_gets_that_mesh_and_the_same_data(tmp_path):
    """``mesh.file``: the job's data on a run's written mesh are those of that run (mesh,
    tissues, boundary, synthetic truth, ``m``), which fTetWild alone cannot repeat; a mesh
    that reaches into the skull is reported, with the key named."""
    import meshio

    from bayesreg.config import load_config
    from bayesreg.problem import make_data

    tiny = ["data.resolution_mm=3.0", "mesh.edge_length_mm=26"]
    first = make_data(load_config("configs/quickstart.yaml", overrides=tiny))
    mesh = first.mesh
    path = tmp_path / "mesh.vtu"  # as bayesreg.outputs writes it
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
