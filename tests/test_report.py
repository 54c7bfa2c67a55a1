"""Report tables and figures from fabricated run directories (bayesreg.report)."""

from __future__ import annotations

import json

import arviz as az
import meshio
import nibabel as nib
import numpy as np
import pandas as pd
import pytest

from bayesreg.sampling.diagnostics import coverage, to_datatree
from bayesreg.report import PAPER, load_run, table1, table2, write_report
from conftest import box_mesh

SPACING, ORIGIN, SHAPE = 2.0, -6.0, (22, 22, 22)  # grid -6 .. 36 mm; the mesh is [0, 30]^3
AFFINE = np.diag([SPACING, SPACING, SPACING, 1.0])
AFFINE[:3, 3] = ORIGIN
C, D = 2, 50
TRUTH = {"lam": {"csf": 1e-6, "gm": 10.0, "wm": 30.0}, "mu": {"csf": 1e-6, "gm": 1.0, "wm": 1.0}}
DIR = np.array([0.6, 0.8, 0.0])  # unit vector of the posterior-mean error
INIT_OFFSET = np.array([0.0, 0.0, 2.0])  # initial configuration error, mm
# posterior-mean error on the grid per label (CSF, GM, WM), mm: MSE_t = |offset_t|^2
GRID_OFFSET = {1: np.array([0.1, 0.0, 0.0]), 2: np.array([0.0, 0.2, 0.0]), 3: np.array([0.0, 0.0, 0.3])}


def _grid():
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in SHAPE], indexing="ij"), -1)
    return ijk * SPACING + ORIGIN  # world mm (I, J, K, 3)


def _true_field(x):
    """A smooth (linear) displacement, mm: a contraction towards the box centre."""
    return -0.05 * (x - 15.0) + np.array([0.5, -0.3, 0.2])


def _labels():
    x = _grid()
    lab = np.zeros(SHAPE, np.uint8)
    inside = np.all((x >= 0) & (x <= 30), axis=-1)
    lab[inside] = 1 + np.digitize(x[..., 0], [10.0, 20.0])[inside]  # CSF, GM, WM by x thirds
    lab[np.any((x <= -4) | (x >= 34), axis=-1)] = 4  # skull shell 4 mm outside the brain
    return lab


def _nii(path, data):
    nib.save(nib.Nifti1Image(np.asarray(data, np.float32), AFFINE), str(path))


def make_run(path, *, elastic="tissue", scale=1.0, init_scale=1.0, truth=True, seed=0,
             every_node=False):
    """A fabricated finished run with known errors.

    ``scale`` multiplies the posterior-mean offsets, ``init_scale`` the initial one;
    ``every_node``: ``posterior.nc`` holds draws of every node (``model.interior: sample``),
    the boundary's the same as without it.
    """
    rng = np.random.default_rng(seed)
    mesh = box_mesh()
    u_true = _true_field(mesh.nodes)
    b = mesh.boundary
    nb = len(b)
    r = scale * np.linspace(0.1, 1.0, nb)  # posterior-mean error per boundary node, mm
    noise = rng.normal(0.0, 0.3, (C, D, nb, 3))
    noise -= noise.mean(axis=(0, 1))  # exactly zero mean: E[u_b] = truth + r DIR
    u_b = u_true[b] + r[:, None] * DIR + noise
    groups = ["csf", "gm", "wm"] if elastic == "tissue" else ["all"]
    g = len(groups)
    mu = np.ones((C, D, g))
    lam = rng.uniform(1.0, 20.0, (C, D, g))
    nodes = b.astype(int)
    sampled = u_b
    if every_node:
        nodes = np.arange(len(u_true))
        sampled = u_true + np.random.default_rng(seed + 1).normal(0.0, 0.3, (C, D) + u_true.shape)
        sampled[:, :, b] = u_b
    tree = to_datatree({"u_b": sampled, "lam": lam, "mu": mu, "ratio": lam / mu},
                       dims={"u_b": ["node", "axis"], "lam": ["group"], "mu": ["group"],
                             "ratio": ["group"]},
                       coords={"node": nodes, "axis": ["x", "y", "z"], "group": groups})
    path.mkdir(parents=True)
    tree.to_netcdf(path / "posterior.nc")

    u_mean = u_true.copy()
    u_mean[b] = u_b.reshape(-1, nb, 3).mean(0)
    pd_ = {"u_mean": u_mean, "u_sd": np.full_like(u_true, 0.3), "u_norm_sd": np.zeros(len(u_true)),
           "u_norm_iqr": np.full(len(u_true), 0.2), "u_init": u_true + init_scale * INIT_OFFSET}
    if truth:
        pd_ |= {"u_true": u_true, "u_error": u_mean - u_true}
    meshio.write(path / "mesh.vtu", meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)], point_data=pd_,
                                                cell_data={"label": [mesh.tissue.astype(np.int32) + 1]}))

    x, lab = _grid(), _labels()
    inside = np.all((x >= 0) & (x <= 30), axis=-1)[..., None]
    d_true = np.where(inside, _true_field(x), 0.0)
    d_mean = d_true.copy()
    for t, off in GRID_OFFSET.items():
        d_mean[lab == t] += scale * off
    f = np.where(inside[..., 0], 100.0 + x[..., 0], 0.0)
    _nii(path / "f.nii.gz", f)
    _nii(path / "m.nii.gz", f)
    _nii(path / "labels.nii.gz", lab)
    _nii(path / "displacement_mean.nii.gz", d_mean)
    _nii(path / "displacement_sd.nii.gz", np.full(SHAPE + (3,), 0.1))
    _nii(path / "displacement_norm_iqr.nii.gz", np.where(inside[..., 0], 0.2, 0.0))
    if truth:
        _nii(path / "displacement_true.nii.gz", d_true)
        _nii(path / "displacement_init.nii.gz", d_true + init_scale * INIT_OFFSET * inside)
    info = {
        "name": path.name,
        "config": {"model": {"elastic": elastic, "quadrature_level": 1 if elastic == "tissue" else 0,
                             "skull_barrier_mm": 1.0, "prior_normaliser": "paper"},
                   "sampler": {"kind": "nuts" if elastic == "tissue" else "rwmh"}},
        "timings_s": {"sampling_s": 10.0, "total_before_outputs_s": 12.5},
        "sampler": {"chains": C, "draws_per_chain": D, "thinning": 10, "steps_per_chain": 10 * D,
                    "acceptance": [0.25, 0.3], "rhat_classic_max": 1.05, "converged": True,
                    "ess_bulk_min": 40.0, "steps_per_s_per_chain": 50.0},
        "mesh": {"n_nodes": len(mesh.nodes), "n_boundary_nodes": nb, "n_tets": len(mesh.tets)},
    }
    if elastic == "tissue":  # a NUTS run: its verdict and a failed per-chain check
        info["sampler"]["verdict"] = "verdict: converged: rank-normalised R-hat 1.004"
        info["sampler"]["health"] = {"warnings": ["3 divergent transitions (chain 1; up to 0.6% in chain 1)"]}
    if truth:
        info["truth"] = TRUTH
    (path / "run.json").write_text(json.dumps(info))
    return path, r, u_b, u_true[b]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    tissue = make_run(root / "tissue", elastic="tissue", scale=1.0, seed=1)
    uniform = make_run(root / "uniform", elastic="uniform", scale=2.0, seed=2)
    return {"three_compartment": tissue, "uniform": uniform}


def test_table1_known_errors(runs):
    t = table1({k: v[0] for k, v in runs.items()})
    assert list(t.index) == ["initial", "three_compartment", "uniform"]  # shared start
    assert list(t.columns) == ["median", "q95", "max"]
    np.testing.assert_allclose(t.loc["initial"], [2.0, 2.0, 2.0], rtol=1e-12)
    for k, scale in (("three_compartment", 1.0), ("uniform", 2.0)):
        r = runs[k][1]
        np.testing.assert_allclose(t.loc[k], [np.median(r), np.quantile(r, 0.95), r.max()],
                                   rtol=1e-9, atol=1e-9)
        assert np.isclose(t.loc[k, "max"], scale * 1.0)


def test_a_run_that_sampled_every_node_reports_its_surface_alone(runs, tmp_path):
    """``model.interior: sample`` writes every node's draws as ``u_b``: the report reads the
    surface's, so Table 1 and the coverage are those of the boundary as in any run."""
    path, _, u_b, _ = runs["three_compartment"]
    every = make_run(tmp_path / "every", elastic="tissue", scale=1.0, seed=1, every_node=True)[0]
    a, b = load_run(path), load_run(every)
    assert len(az.from_netcdf(every / "posterior.nc").posterior["node"]) > len(a.boundary)
    np.testing.assert_array_equal(b.boundary, a.boundary)
    np.testing.assert_array_equal(b.u_b, a.u_b)
    pd.testing.assert_frame_equal(table1({"x": every}), table1({"x": path}))


def test_initial_rows_per_run_when_starts_differ(runs, tmp_path):
    other = make_run(tmp_path / "other", elastic="uniform", init_scale=2.0, seed=3)[0]
    paths = {"three_compartment": runs["three_compartment"][0], "other": other}
    t = table1(paths)
    assert list(t.index) == ["initial (three_compartment)", "initial (other)",
                             "three_compartment", "other"]
    np.testing.assert_allclose(t.loc["initial (other)"], [4.0, 4.0, 4.0], rtol=1e-12)
    t2 = table2(paths)
    np.testing.assert_allclose(t2.loc["initial (other)"], 16.0, rtol=1e-6)


def test_table2_known_mse(runs):
    t = table2({k: v[0] for k, v in runs.items()})
    lab = _labels()
    counts = {t_: np.sum(lab == t_) for t_ in (1, 2, 3)}
    for k, scale in (("three_compartment", 1.0), ("uniform", 2.0)):
        per = {t_: scale**2 * np.sum(o**2) for t_, o in GRID_OFFSET.items()}
        brain = sum(per[t_] * counts[t_] for t_ in per) / sum(counts.values())
        np.testing.assert_allclose(t.loc[k, ["csf", "gm", "wm"]], [per[1], per[2], per[3]], rtol=1e-5)
        np.testing.assert_allclose(t.loc[k, "brain"], brain, rtol=1e-5)
    np.testing.assert_allclose(t.loc["initial"], 4.0, rtol=1e-6)  # |(0, 0, 2)|^2 everywhere


def test_write_report_all_artefacts(runs, tmp_path):
    out = write_report({k: v[0] for k, v in runs.items()}, tmp_path / "report")
    names = ["table1.csv", "table2.csv", "coverage.csv", "ratios.csv", "fig2_dataset.png",
             "fig3_errors.png", "fig4_ratios.png", "fig5_boundary_node.png", "uncertainty.png",
             "report.md", "report.json"]
    for n in names:
        assert (out / n).is_file() and (out / n).stat().st_size > 0, n
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".report")]  # no staging left

    t1 = pd.read_csv(out / "table1.csv", index_col=0)
    pd.testing.assert_frame_equal(t1, table1({k: v[0] for k, v in runs.items()}),
                                  check_names=False)

    cov = pd.read_csv(out / "coverage.csv", index_col=0)
    for k, (_, _, u_b, truth_b) in runs.items():
        expect = coverage(u_b.reshape(C, D, -1), truth_b.ravel())
        np.testing.assert_allclose(cov.loc[k].to_numpy(), list(expect.values()))

    rep = json.loads((out / "report.json").read_text())
    assert rep["paper"]["table1_mm"]["initial"]["max"] == PAPER["table1_mm"]["initial"]["max"] == 15.08
    assert rep["runs"]["uniform"]["n_boundary"] == len(runs["uniform"][1])
    assert rep["fig5"]["run"] == "three_compartment"
    # the node closest to the skull: every box face is 4 mm from it; its limit is finite
    assert rep["fig5"]["skull_distance_mm"] <= 6.0
    assert any(v is not None for row in rep["fig5"]["skull_limits_mm"] for v in row)
    md = (out / "report.md").read_text()
    for s in ("Table 1", "Table 2", "0.160", "0.065", "fig5_boundary_node.png", "Coverage",
              "nuts, quadrature 32 pts/tet, barrier 1 mm, normaliser paper",
              "rwmh, quadrature 4 pts/tet, barrier 1 mm",
              "- **three_compartment**: converged: rank-normalised R-hat 1.004; sampler check: 3 "
              "divergent transitions (chain 1; up to 0.6% in chain 1)"):
        assert s in md, s


def test_existing_report_not_overwritten(runs, tmp_path):
    out = tmp_path / "report"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    paths = {"three_compartment": runs["three_compartment"][0]}
    with pytest.raises(FileExistsError, match="overwrite"):
        write_report(paths, out)
    # overwrite replaces a report, never a folder of other files
    with pytest.raises(FileExistsError, match="holds none of report.json, report.md"):
        write_report(paths, out, overwrite=True)
    assert (out / "keep.txt").exists() and not list(tmp_path.glob(".report.replaced-*"))
    (out / "keep.txt").unlink()
    write_report(paths, out)
    (out / "stale.txt").write_text("x")
    write_report(paths, out, overwrite=True)
    assert not (out / "stale.txt").exists() and (out / "report.md").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]  # nothing left beside it


def test_a_failing_overwrite_puts_the_old_report_back(runs, tmp_path, monkeypatch):
    """A report that fails while replacing another leaves the old one as it was, and nothing
    beside it (no empty directory, no hidden copy of the old report)."""
    import bayesreg.report.write as R

    out = tmp_path / "report"
    paths = {"three_compartment": runs["three_compartment"][0]}
    write_report(paths, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken(*args, **kwargs):
        raise RuntimeError("a figure failed")

    monkeypatch.setattr(R, "table2", broken)
    with pytest.raises(RuntimeError, match="a figure failed"):
        write_report(paths, out, overwrite=True)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_run_without_truth_raises(tmp_path):
    path = make_run(tmp_path / "real", truth=False)[0]
    with pytest.raises(ValueError, match="needs a synthetic truth.*real"):
        load_run(path)
    with pytest.raises(ValueError, match="needs a synthetic truth"):
        write_report({"x": path}, tmp_path / "report")
    assert not (tmp_path / "report").exists()


def test_missing_file_named(runs, tmp_path):
    import shutil

    src = runs["uniform"][0]
    path = tmp_path / "broken"
    shutil.copytree(src, path)
    (path / "displacement_mean.nii.gz").unlink()
    with pytest.raises(FileNotFoundError, match="displacement_mean.nii.gz"):
        load_run(path)
    (path / "displacement_true.nii.gz").unlink()
    shutil.copy(src / "displacement_mean.nii.gz", path)
    with pytest.raises(FileNotFoundError, match="displacement_true.nii.gz"):
        load_run(path)
