"""Shared fixtures: structured box meshes, a small real brain mesh, a small box posterior.

Plain helpers shared between test files (analytic images, posteriors of known form, toy
targets) are in ``helpers.py``.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

# One persistent JAX compilation cache for the whole session, shared by pytest-xdist's workers
# and the processes the tests start (notebook kernels): they inherit the environment set
# here, before JAX is imported.  Many tests build the same programs on the same fixtures
# (a resumed run, a variant against its reference), and a hit skips XLA's compilation.
# The executables are those a fresh compilation gives (the key is the program, the compile
# options and XLA_FLAGS), and `compilations()` still counts a hit: JAX logs "Finished XLA
# compilation" around the lookup.  A user's own JAX_COMPILATION_CACHE_DIR is kept (and not
# deleted); the session's temporary one is removed at the end.
_SESSION_CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _SESSION_CACHE = tempfile.mkdtemp(prefix="bayesreg-test-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _SESSION_CACHE
    # JAX's default threshold is 1 s; every program is worth caching here, down to the
    # single operations run eagerly on the shared fixtures (each ~30 ms of XLA on a 2-core
    # CPU, hundreds per fixture, else compiled again in every worker)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

import bayesreg  # noqa: E402

bayesreg.configure_jax()  # float64, XLA flags, BLAS threads: before any JAX computation
from bayesreg.mesh import tetmesh as mesh_mod  # noqa: E402
from bayesreg.mesh.tetmesh import Mesh, boundary_nodes, orient_tets  # noqa: E402


# Files of the longest tests (end-to-end runs, notebooks, a Dask cluster), collected first:
# pytest-xdist hands tests out in collection order, so that two workers then finish
# together instead of one running a two-minute test alone at the end.  The tiny runs of the
# same programs (the CLI's, the notebook's, the sweep's) share one worker (xdist_group
# "tiny_run"), in this order, so that the later ones find the first one's programs in the
# session's compilation cache instead of compiling them at the same time on another core.
_LONG_FIRST = ("test_cli.py", "test_sweep.py", "test_faults.py", "test_calibration.py",
               "pipeline.py", "test_gibbs.py", "test_normaliser.py", "test_rwmh.py")


def pytest_collection_modifyitems(config, items):
    """The files of :data:`_LONG_FIRST` first, in that order (a stable sort: each file's own
    order kept; the same order in every worker, as xdist requires)."""
    def rank(item):
        name = item.nodeid.split("::")[0].rsplit("/", 1)[-1]
        return _LONG_FIRST.index(name) if name in _LONG_FIRST else len(_LONG_FIRST)

    items.sort(key=rank)


def pytest_collection_finish(session):
    """Warn where ``--dist loadgroup`` does not group (a pytest-xdist worker whose items carry
    an ``xdist_group`` mark without the group in their node id, as with pytest 9.2 and
    pytest-xdist 3.8): each worker would then make the groups' shared runs again."""
    if not (os.environ.get("PYTEST_XDIST_WORKER") and session.config.getvalue("loadgroup")):
        return
    lost = [it.nodeid for it in session.items
            if any(True for _ in it.iter_markers("xdist_group")) and "@" not in it.nodeid]
    if lost:
        import warnings

        warnings.warn(pytest.PytestWarning(
            f"--dist loadgroup does not group {len(lost)} tests (e.g. {lost[0]}): this pytest "
            "and pytest-xdist do not work together (pytest-dev/pytest-xdist#1386)"))


def pytest_unconfigure(config):
    """Remove the session's compilation cache (in the process that created it: the controller,
    or the single process of ``-n 0``)."""
    if _SESSION_CACHE is not None:
        shutil.rmtree(_SESSION_CACHE, ignore_errors=True)


def box_mesh(n=(3, 3, 3), size=(30.0, 30.0, 30.0), origin=(0.0, 0.0, 0.0), tissue=None) -> Mesh:
    """Structured tetrahedral mesh of a box (:func:`bayesreg.mesh.tetmesh.box_mesh`)."""
    return mesh_mod.box_mesh(n, size, origin, tissue)


def centred_cube() -> Mesh:
    """A cube with one interior node: 8 boundary corners + centre, 12 tetrahedra."""
    corners = np.array(list(itertools.product((0.0, 20.0), repeat=3)))
    nodes = np.vstack([corners, [[10.0, 10.0, 10.0]]])
    faces = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    tets = []
    for a, b, c, d in faces:
        tets += [[a, b, c, 8], [a, c, d, 8]]
    tets = orient_tets(nodes, np.array(tets))
    return Mesh(nodes, tets, np.zeros(len(tets), np.int64), boundary_nodes(tets))


@pytest.fixture(scope="session")
def brain():
    """The MNI152 brain at 2 mm with labels and a coarse (~440 node) mesh."""
    from bayesreg.data.datasets import mni152
    from bayesreg.data.labels import labels_from_probabilities
    from bayesreg.mesh.meshing import carve_skull, mesh_brain

    t1, gm, wm, mask = mni152(2.0)
    labels = labels_from_probabilities(gm, wm, mask)
    mesh = mesh_brain(labels, edge_length_mm=20.0)
    labels, _ = carve_skull(labels, mesh)
    return t1, labels, mesh


_ROOT = Path(__file__).resolve().parents[1]

#: The tiny end-to-end runs' images and mesh size (the quickstart's brain at 3 mm, 26 mm edges).
TINY_DATA = ["data.resolution_mm=3.0", "mesh.edge_length_mm=26"]


@pytest.fixture(scope="session")
def tiny_mesh(tmp_path_factory) -> str:
    """One mesh file (``.vtu``) of :data:`TINY_DATA` for the whole session, every xdist worker
    included: fTetWild gives another mesh on each call, and one mesh lets the end-to-end runs
    share their compiled programs (the persistent cache above is keyed by array shapes).  The
    first worker to finish meshing publishes its file (an atomic hard link); the others use it.
    """
    import meshio

    from bayesreg.config import load_config
    from bayesreg.model.problem import make_data

    root = tmp_path_factory.getbasetemp()
    shared = (root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root) / "tiny_mesh.vtu"
    if not shared.exists():
        data = make_data(load_config(_ROOT / "configs" / "quickstart.yaml", overrides=TINY_DATA))
        mine = root / "tiny_mesh_own.vtu"
        meshio.write(mine, meshio.Mesh(data.mesh.nodes, [("tetra", data.mesh.tets)]))
        with contextlib.suppress(FileExistsError):
            os.link(mine, shared)
    return str(shared)


@pytest.fixture(scope="session")
def small():
    """A box posterior with weakly informative priors: ``(mesh, post, theta)``
    (:func:`helpers.box_posterior`; shared, so ``theta`` is read-only)."""
    from helpers import box_posterior

    prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    mesh, post, theta = box_posterior(prior, 3.0, np.array([1.0, 10.0, 30.0, 0.5, 1.0]))
    theta.setflags(write=False)  # shared by many tests: they work on copies
    return mesh, post, theta


@contextlib.contextmanager
def compilations():
    """Count XLA compilations by program name inside the block: ``{"jit(step)": 1, ...}``
    (from JAX's ``jax_log_compiles`` messages)."""
    import jax

    counts: dict[str, int] = {}

    class _Count(logging.Handler):
        def emit(self, record):
            m = re.match(r"Finished XLA compilation of (\S+) in", record.getMessage())
            if m:
                counts[m.group(1)] = counts.get(m.group(1), 0) + 1

    handler, logger = _Count(level=logging.DEBUG), logging.getLogger("jax")
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        with jax.log_compiles(True):
            yield counts
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)
