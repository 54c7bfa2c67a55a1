"""A given mesh read from a file (bayesreg.mesh.tetmesh.read_mesh, ``mesh.file``)."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

from bayesreg.mesh import tetmesh as M
from bayesreg.mesh.tetmesh import boundary_faces, label_elements, read_mesh
from conftest import box_mesh
from helpers import ball_labels


def _box_in_ball():
    """A 3x3x3-cube box mesh, 12 mm wide, inside the ball of :func:`_ball_labels` (centre
    15 mm, radius 10 mm)."""
    return box_mesh((3, 3, 3), (12.0, 12.0, 12.0), origin=(9.0, 9.0, 9.0))


@pytest.mark.parametrize("suffix, fmt", [(".vtu", None), (".msh", "gmsh22")])
def test_read_mesh_round_trips_a_written_mesh(tmp_path, suffix, fmt):
    """A mesh written by meshio comes back with its points, its elements (oriented), the
    boundary of its surface and tissues from the label map: a point no element uses is
    dropped, surface triangles and a ``tissue`` cell array in the file are ignored."""
    labels = ball_labels()
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
    labels = ball_labels()
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
    # a loose tetrahedron beside the box: two pieces, K singular
    loose = np.vstack([box.nodes, [[14.0, 14.0, 23.0], [15.0, 14.0, 23.0], [14.0, 15.0, 23.0],
                                   [14.0, 14.0, 24.0]]])
    n = len(box.nodes)
    two = write("two.vtu", loose, [("tetra", np.vstack([box.tets, [[n, n + 1, n + 2, n + 3]]]))])
    with pytest.raises(M.MeshError, match=r"is 2 pieces joined by no face \(elements 162, 1\)"):
        read_mesh(two, labels)
    # the same mesh in voxel coordinates of the label map (2 mm voxels): outside the ball
    voxels = write("voxels.vtu", box.nodes / 2.0 - 4.0, [("tetra", box.tets)])
    with pytest.raises(M.MeshError, match=r"only 0% of its element centroids lie in the "
                       r"intracranial tissues .* world coordinates in mm"):
        read_mesh(voxels, labels)


def test_mesh_pieces_joins_elements_by_faces_only():
    """Elements sharing a face are one piece; a tetrahedron touching the box at one node only
    is a piece of its own (it can turn about that node without strain); the largest piece
    is numbered 0 whatever the element order."""
    from bayesreg.mesh.tetmesh import mesh_pieces

    box = box_mesh((2, 2, 2), (10.0, 10.0, 10.0))
    assert np.array_equal(mesh_pieces(box.tets), np.zeros(len(box.tets), int))
    corner = int(np.argmax(box.nodes.sum(axis=1)))  # the node at (10, 10, 10)
    n = len(box.nodes)
    tets = np.vstack([[[corner, n, n + 1, n + 2]], box.tets])  # touches the box at one node
    piece = mesh_pieces(tets)
    assert piece[0] == 1 and np.all(piece[1:] == 0)
