"""Point files (CSV, 3D Slicer markups and fiducial lists) and draw selection of
:mod:`bayesreg.apply`; transforms and warps of a real run are tested end to end in
``test_cli.py``."""

import json

import numpy as np
import pytest

from bayesreg.apply import draw_indices, read_points

RAS = np.array([[10.0, -20.0, 30.0], [-1.5, 2.5, -3.5]])


def test_points_read_from_csv_markups_and_fcsv_in_world_ras(tmp_path):
    (tmp_path / "p.csv").write_text("name,x,y,z\na,10,-20,30\nb,-1.5,2.5,-3.5\n")
    names, pts = read_points(tmp_path / "p.csv")
    assert names == ["a", "b"]
    np.testing.assert_allclose(pts, RAS)

    lps = RAS * [-1, -1, 1]
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "controlPoints": [
        {"label": "a", "position": lps[0].tolist()}, {"label": "b", "position": lps[1].tolist()}]}]}
    (tmp_path / "p.mrk.json").write_text(json.dumps(doc))
    names, pts = read_points(tmp_path / "p.mrk.json")
    assert names == ["a", "b"]
    np.testing.assert_allclose(pts, RAS)  # Slicer's LPS converted to RAS

    fcsv = ("# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"
            "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
            + "".join(f"{k},{p[0]},{p[1]},{p[2]},0,0,0,1,1,1,0,{n},,\n"
                      for k, (n, p) in enumerate(zip("ab", lps))))
    (tmp_path / "p.fcsv").write_text(fcsv)
    names, pts = read_points(tmp_path / "p.fcsv")
    assert names == ["a", "b"]
    np.testing.assert_allclose(pts, RAS)


def test_point_files_without_points_or_coordinates_are_errors_naming_the_file(tmp_path):
    (tmp_path / "bad.csv").write_text("name,a,b\nx,1,2\n")
    with pytest.raises(ValueError, match="bad.csv: a points CSV needs columns x, y, z"):
        read_points(tmp_path / "bad.csv")
    (tmp_path / "empty.csv").write_text("x,y,z\n")
    with pytest.raises(ValueError, match="empty.csv: no points"):
        read_points(tmp_path / "empty.csv")


def test_draws_are_spread_evenly_over_the_chains():
    assert draw_indices(10, None).tolist() == list(range(10))
    assert draw_indices(10, 50).tolist() == list(range(10))
    assert draw_indices(9, 3).tolist() == [0, 4, 8]
    with pytest.raises(ValueError, match=">= 1"):
        draw_indices(10, 0)
