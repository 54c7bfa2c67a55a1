"""The problem's data (bayesreg.problem): a run on a given mesh file."""

import meshio
import numpy as np
import pytest

from bayesreg.config import load_config
from bayesreg.problem import make_data


def test_a_run_on_a_given_mesh_gets_that_mesh_and_the_same_data(tmp_path):
    """``mesh.file``: the job's data on a run's written mesh are those of that run (mesh,
    tissues, boundary, synthetic truth, ``m``), which fTetWild alone cannot repeat; a mesh
    that reaches into the skull is reported, with the key named."""
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
