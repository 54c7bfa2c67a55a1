"""The output stage's statistics over chunks of draws (bayesreg.outputs, bayesreg.synthetic).

A run of the paper's size stores 3 x 25,000 draws; the displacement statistics are
accumulated chunk by chunk and must equal those of all draws held at once.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bayesreg import fields, outputs
from bayesreg.convergence import gelman_rubin
from bayesreg.diagnostics import coverage
from bayesreg.images import Image
from bayesreg.rundir import RunDirectory
from bayesreg.warp import grid_moments, grid_moments_from, interpolation_matrix
from conftest import box_mesh


def _fake_run(seed=0, c=3, d=23):
    """A mesh, a problem stand-in (boundary first, interior after, ``perm`` to node order)
    and a sampler result with correlated draws."""
    rng = np.random.default_rng(seed)
    mesh = box_mesh(n=(2, 2, 2), size=(20.0, 20.0, 20.0))
    n = len(mesh.nodes)
    boundary = np.asarray(mesh.boundary)
    interior = np.setdiff1d(np.arange(n), boundary)
    order = np.concatenate([boundary, interior])  # [u_b, u_i][:, k] is node order[k]
    perm = np.argsort(order)  # full[:, j] = [u_b, u_i][:, perm[j]]
    nb = len(boundary)
    base = rng.normal(0.0, 2.0, (n, 3))
    draws = base + rng.normal(0.0, 0.3, (c, d, n, 3)) * rng.uniform(0.2, 1.0, (n, 1))
    n_par = 2
    positions = np.concatenate([draws[:, :, boundary].reshape(c, d, 3 * nb),
                                rng.uniform(1, 2, (c, d, n_par))], axis=-1)
    problem = SimpleNamespace(mesh=mesh, posterior=SimpleNamespace(n_boundary=nb, perm=perm))
    result = SimpleNamespace(positions=positions, interior=draws[:, :, interior])
    return mesh, problem, result, draws.reshape(c * d, n, 3)


@pytest.mark.parametrize("chunk", [1, 7, 4096])
def test_nodal_statistics_over_chunks_equal_all_draws(monkeypatch, chunk):
    mesh, problem, result, draws = _fake_run()
    monkeypatch.setattr(fields, "CHUNK_DRAWS", chunk)
    np.testing.assert_array_equal(fields.nodal_draws(problem, result, slice(None)), draws)
    np.testing.assert_array_equal(fields.nodal_draws(problem, result, slice(5, None, 9)),
                                  draws[5::9])
    mean = fields.nodal_mean(problem, result)
    np.testing.assert_allclose(mean, draws.mean(0), rtol=1e-13, atol=1e-13)
    cov, sd, norm_sd, norm_iqr = fields.nodal_spread(problem, result, mean, block=5)
    centred = draws - draws.mean(0)
    for a in range(3):
        np.testing.assert_allclose(cov[a], centred[:, :, a].T @ centred[:, :, a] / len(draws),
                                   rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(sd, draws.std(0), rtol=1e-12)
    norm = np.linalg.norm(draws, axis=2)
    np.testing.assert_allclose(norm_sd, norm.std(0), rtol=1e-12)
    np.testing.assert_allclose(norm_iqr, np.subtract(*np.quantile(norm, [0.75, 0.25], axis=0)),
                               rtol=1e-12)


def test_grid_moments_equal_the_moments_of_interpolated_draws():
    """``w^T Cov w`` per voxel is the variance of the FE-interpolated draws (linearity)."""
    mesh, _, _, draws = _fake_run(seed=1)
    affine = np.array([[2.5, 0, 0, -1.0], [0, 2.6, 0, -0.5], [0, 0, 3.1, 0.3], [0, 0, 0, 1]])
    grid = Image(np.zeros((9, 8, 7)), affine)  # voxels in and outside the 20 mm box
    w, inside = interpolation_matrix(mesh, grid)
    assert inside.sum() > 100
    interp = np.stack([w @ x for x in draws])  # (S, voxels, 3)
    mean, sd = grid_moments(mesh, grid, draws)
    np.testing.assert_allclose(mean.reshape(-1, 3), interp.mean(0), atol=1e-12)
    np.testing.assert_allclose(sd.reshape(-1, 3), interp.std(0), rtol=1e-9, atol=1e-12)
    assert np.all(sd.reshape(-1, 3)[~inside.ravel()] == 0.0)
    centred = draws - draws.mean(0)
    cov = np.stack([centred[:, :, a].T @ centred[:, :, a] for a in range(3)]) / len(draws)
    m2, s2 = grid_moments_from(mesh, grid, draws.mean(0), cov)
    np.testing.assert_array_equal(m2, mean)
    np.testing.assert_array_equal(s2, sd)
    with pytest.raises(ValueError, match="cov"):
        grid_moments_from(mesh, grid, draws.mean(0), cov[:2])


@pytest.mark.parametrize("block", [1, 3, 1000])
def test_blocked_coverage_and_rhat_equal_whole(block):
    rng = np.random.default_rng(3)
    x = rng.normal(size=(3, 200, 40)) + rng.normal(0.0, 0.3, (3, 1, 40))
    view = np.concatenate([x, rng.normal(size=(3, 200, 5))], axis=-1)[..., :40]  # strided
    truth = rng.normal(0.0, 1.2, 40)
    ref = coverage(x.reshape(-1, 40), truth, block=10**6)
    assert coverage(view, truth, block=block) == ref
    for split in (False, True):  # equal up to the order of summation
        np.testing.assert_allclose(gelman_rubin(view, split=split, block=block),
                                   gelman_rubin(x, split=split, block=10**6), rtol=1e-14)
    two = gelman_rubin(x.reshape(3, 200, 8, 5), block=block)
    assert two.shape == (8, 5)
    np.testing.assert_allclose(two.ravel(), gelman_rubin(x, block=block), rtol=1e-14)


def test_run_directory_overwrite_replaces_only_a_run_and_rollback_puts_it_back(tmp_path, monkeypatch):
    """``overwrite`` never hides a folder bayesreg did not write; a failed start undoes itself."""
    import os

    monkeypatch.chdir(tmp_path)
    data = tmp_path / "data"
    data.mkdir()
    (data / "f.nii.gz").write_text("the user's input")
    with pytest.raises(FileExistsError, match="not empty"):
        RunDirectory(data)
    with pytest.raises(FileExistsError, match="holds none of run.json, checkpoint"):
        RunDirectory(data, overwrite=True)
    assert (data / "f.nii.gz").read_text() == "the user's input"
    with pytest.raises(NotADirectoryError, match="is a file"):
        RunDirectory(data / "f.nii.gz" / "run")
    with pytest.raises(FileExistsError, match="working directory"):
        (tmp_path / "run.json").write_text("{}")
        RunDirectory(tmp_path, overwrite=True)
    (tmp_path / "run.json").unlink()

    old = tmp_path / "run"
    old.mkdir()
    (old / "run.json").write_text('{"old": true}')
    rd = RunDirectory(old, overwrite=True)  # the old run moves aside at once
    hidden = rd.replaced
    assert hidden.is_dir() and hidden.name.startswith(f".run.replaced-{os.getpid()}-")
    assert not any(old.iterdir())
    (old / "checkpoint").mkdir()
    rd.rollback()  # a start that failed: the old run is back, nothing of the new one
    assert (old / "run.json").read_text() == '{"old": true}' and not hidden.exists()
    assert sorted(p.name for p in old.iterdir()) == ["run.json"]

    rd = RunDirectory(old, overwrite=True)
    rd.file("run.json").write_text('{"new": true}')
    rd.commit()  # a run that finished: the old one is gone
    assert (old / "run.json").read_text() == '{"new": true}' and not rd.replaced
    assert not list(tmp_path.glob(".run.replaced-*"))

    # a run interrupted after its sampling started keeps the run it replaced aside, and so
    # does a second one in the same process (a notebook: before, its aside folder had the
    # first one's name and the move failed); the resumed run's commit deletes them
    for _ in range(2):
        RunDirectory(old, overwrite=True)
        (old / "checkpoint").mkdir()
        (old / "checkpoint" / "config.json").write_text("{}")
    assert len(list(tmp_path.glob(".run.replaced-*"))) == 2
    resumed = RunDirectory(old, resume=True)
    resumed.file("run.json").write_text('{"resumed": true}')
    resumed.commit()
    assert not list(tmp_path.glob(".run.replaced-*"))
    assert (old / "run.json").read_text() == '{"resumed": true}'

    # the aside folders of another run are not this one's, whatever its name's glob says
    (tmp_path / ".exp1.replaced-1-0").mkdir()
    odd = RunDirectory(tmp_path / "exp[1]")
    odd.file("run.json").write_text("{}")
    odd.commit()
    assert (tmp_path / ".exp1.replaced-1-0").is_dir()

    # a run without checkpoints killed while writing its outputs leaves only its staging
    # folder: that is a directory bayesreg wrote, which --overwrite may replace
    partial = tmp_path / "partial"
    (partial / ".outputs-partial").mkdir(parents=True)
    RunDirectory(partial, overwrite=True).rollback()
    assert (partial / ".outputs-partial").is_dir()

    fresh = tmp_path / "fresh"
    RunDirectory(fresh).rollback()
    assert not fresh.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    RunDirectory(empty).rollback()
    assert empty.is_dir() and not any(empty.iterdir())


def test_writes_are_flushed_to_disk_before_their_rename(tmp_path, monkeypatch):
    """Checkpoints, text and NIfTI files, and a run's commit flush each file's data before
    the rename and the folder's entry after it (a power loss leaves the old file or the new
    one, never an empty one under the final name)."""
    import os

    from bayesreg import _files
    from bayesreg.checkpoint import savez_atomic
    from bayesreg.images import save_nifti

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(_files.os, "fsync", lambda fd: (events.append(("fsync", os.readlink(
        f"/proc/self/fd/{fd}"))), real_fsync(fd))[1])
    monkeypatch.setattr(_files.os, "replace", lambda a, b: (events.append(("replace", str(b))),
                                                            real_replace(a, b))[1])

    savez_atomic(tmp_path / "a.npz", x=np.arange(3))
    np.testing.assert_array_equal(np.load(tmp_path / "a.npz")["x"], np.arange(3))
    assert [e[0] for e in events] == ["fsync", "replace", "fsync"]
    assert events[0][1].endswith("a.npz.tmp.npz") and events[2][1] == str(tmp_path)
    events.clear()
    save_nifti(Image(np.zeros((2, 2, 2), np.float32), np.eye(4)), tmp_path / "b.nii.gz")
    assert [e[0] for e in events] == ["fsync", "replace", "fsync"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.nii.gz"]  # no temporaries

    events.clear()
    rd = RunDirectory(tmp_path / "run")
    rd.file("summary.csv").write_text("x\n")
    _files.write_text_atomic(rd.file("run.json"), "{}")
    events.clear()
    rd.commit()
    synced = [e[1] for e in events if e[0] == "fsync"]
    staged = tmp_path / "run" / ".outputs-partial"
    assert synced == [str(staged / "run.json"), str(staged / "summary.csv"), str(tmp_path / "run")]
    assert (tmp_path / "run" / "run.json").read_text() == "{}" and not staged.exists()


@pytest.mark.parametrize("parts", [1, 2, 3, 7])
def test_summary_in_threads_equals_one_arviz_call(parts):
    """The run's summary table, ``u_b`` in threads over blocks of nodes, is ArviZ's own
    table of all the variables in one call: the same rows in the same order, the same values."""
    import warnings

    import arviz as az

    from bayesreg.diagnostics import arviz_fast_ess, to_datatree

    rng = np.random.default_rng(4)
    c, d, n = 3, 150, 7
    ub = np.cumsum(rng.normal(size=(c, d, n, 3)), axis=1) * 0.1 + rng.normal(size=(c, d, n, 3))
    lam = rng.uniform(1, 2, (c, d, 3))
    mu = np.concatenate([rng.uniform(0.5, 1, (c, d, 2)), np.ones((c, d, 1))], axis=-1)  # a fixed one
    tree = to_datatree({"u_b": ub, "lam": lam, "mu": mu, "ratio": lam / mu},
                       dims={"u_b": ["node", "axis"], "lam": ["group"], "mu": ["group"],
                             "ratio": ["group"]},
                       coords={"node": np.arange(10, 10 + n), "axis": ["x", "y", "z"],
                               "group": ["csf", "gm", "wm"]})
    with warnings.catch_warnings():  # the fixed mu: zero variance, NaN R-hat
        warnings.simplefilter("ignore", RuntimeWarning)
        with arviz_fast_ess():
            ref = az.summary(tree, var_names=["lam", "mu", "ratio", "u_b"], ci_prob=0.9, ci_kind="eti")
            got = outputs.summary_table(tree, ["lam", "mu", "ratio"], "u_b", "node", parts=parts)
    assert list(got.index) == list(ref.index) and list(got.columns) == list(ref.columns)
    np.testing.assert_array_equal(got.to_numpy(float), ref.to_numpy(float))


def test_nodal_statistics_in_one_thread_when_memory_is_short(monkeypatch):
    """Above the accumulators' byte budget the covariances are summed in one thread; the
    figures are those of the threaded sum."""
    _, problem, result, _ = _fake_run()
    monkeypatch.setattr(fields, "CHUNK_DRAWS", 7)
    monkeypatch.setattr(fields, "available_cores", lambda: 3)  # three threads whatever the machine
    mean = fields.nodal_mean(problem, result)
    threaded = fields.nodal_spread(problem, result, mean)
    monkeypatch.setattr(fields, "SPREAD_MAX_BYTES", 1)
    single = fields.nodal_spread(problem, result, mean)
    for a, b in zip(threaded, single):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("damage", ["truncated", "emptied", "text"])
def test_a_damaged_checkpoint_file_is_an_error_that_names_it(tmp_path, damage):
    """``--resume`` of a run whose starts, state or draws were damaged (a full disk, a copy
    cut short) ends with the file named, not a zipfile or NumPy traceback."""
    from bayesreg.checkpoint import Checkpoint
    from bayesreg.initialisation import Initialisation
    from bayesreg.sampler import SamplerCheckpoint

    ck = Checkpoint(tmp_path)
    ck.dir.mkdir(parents=True)
    ck.save_init(Initialisation(np.zeros((2, 5)), np.zeros(5), (np.ones(5),), False, {"a": 1}))
    state = SamplerCheckpoint([np.zeros((2, 5))], (np.ones(5),), np.array([0.3]), 1, [(10, 1.5)], {})
    ck.on_chunk(state, tuple(np.zeros((2, 10, 1)) for _ in range(8)))
    assert ck.load_init() is not None and ck.load_state()[1] is not None  # intact: read back
    files = [ck.dir / "init.npz", ck.dir / "state.npz", ck.draws_dir / "chunk_00000.npz"]
    intact = [p.read_bytes() for p in files]
    for path, data in zip(files, intact):
        if damage == "truncated":
            path.write_bytes(data[: len(data) // 2])
        elif damage == "emptied":
            path.write_bytes(b"")
        else:
            path.write_text("not an archive")
        load = ck.load_init if path.name == "init.npz" else ck.load_state
        with pytest.raises(ValueError, match=f"{path.name} is damaged or incomplete .* cannot be "
                           "resumed from it"):
            load()
        path.write_bytes(data)
