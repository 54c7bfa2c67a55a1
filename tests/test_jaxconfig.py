"""Process settings (:mod:`bayesreg.jaxconfig`): nothing changes at import; ``configure_jax``
sets float64, the XLA:CPU fusion flag and one BLAS thread, whatever was imported first, and
reports a backend started without the flag (each case in a fresh interpreter: XLA reads its
flags once per process)."""

import json
import os
import subprocess
import sys

import pytest

FLAG = "--xla_cpu_experimental_ynn_fusion_type="

PROBE = """
import json, os, sys, warnings
warnings.simplefilter("always")
with warnings.catch_warnings(record=True) as caught:
{body}
    import bayesreg
    bayesreg.configure_jax()
    import jax.numpy as jnp
    jnp.ones(2).sum().block_until_ready()
    import jax
print(json.dumps({{"flags": os.environ.get("XLA_FLAGS"), "x64": bool(jax.config.jax_enable_x64),
                  "blas": os.environ.get("OPENBLAS_NUM_THREADS"),
                  "warnings": [str(w.message) for w in caught if "bayesreg" in str(w.message)],
                  "where": [w.filename for w in caught if "bayesreg" in str(w.message)]}}))
"""


def _env(xla_flags=None):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "OPENBLAS_NUM_THREADS")}
    env["JAX_PLATFORMS"] = "cpu"
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    return env


def _run(code: str, xla_flags=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], env=_env(xla_flags), capture_output=True,
                          text=True, timeout=120)


def _probe(body: str, xla_flags: str | None = None) -> dict:
    code = PROBE.format(body="\n".join("    " + line for line in body.splitlines()) or "    pass")
    out = _run(code, xla_flags)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_every_module_changes_nothing_in_the_process():
    """Every module imports without touching the process: float32 stays JAX's default, no
    XLA or BLAS variable is set, and no JAX backend starts (so configure_jax can still set
    the flags afterwards)."""
    code = """
import importlib, json, os, pkgutil
import bayesreg
names = [m.name for m in pkgutil.walk_packages(bayesreg.__path__, "bayesreg.")]
for name in names:
    importlib.import_module(name)
import jax
from jax._src import xla_bridge
print(json.dumps({"n": len(names), "x64": bool(jax.config.jax_enable_x64),
                  "flags": os.environ.get("XLA_FLAGS"), "blas": os.environ.get("OPENBLAS_NUM_THREADS"),
                  "started": bool(xla_bridge.backends_are_initialized())}))
"""
    out = _run(code)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["n"] > 30
    assert res == {"n": res["n"], "x64": False, "flags": None, "blas": None, "started": False}


@pytest.mark.parametrize("first", ["", "import jax", "import arviz", "import bayesreg.pipeline"])
def test_configure_sets_everything_whatever_was_imported_first(first):
    """Importing JAX, ArviZ or bayesreg's modules before ``configure_jax`` still gets the flag:
    XLA reads XLA_FLAGS when its first backend starts, not at ``import jax``."""
    res = _probe(first)
    assert res["flags"] == FLAG
    assert res["x64"]
    assert res["blas"] == "1"
    assert res["warnings"] == []


def test_backend_started_without_the_flag_warns():
    """A JAX computation before ``configure_jax`` starts XLA:CPU without the flag: the flag
    is not added (too late) and a warning names it and the remedy."""
    res = _probe("import jax.numpy as jnp\njnp.zeros(1).block_until_ready()")
    assert res["flags"] is None
    assert len(res["warnings"]) == 1
    msg = res["warnings"][0]
    assert FLAG in msg and "Call bayesreg.configure_jax() before running any JAX computation" in msg
    # attributed to the caller of configure_jax (here the ``-c`` script), not to bayesreg
    assert res["where"] == ["<string>"]


def test_users_flag_kept():
    """A user's own setting of the flag (or XLA_FLAGS mentioning it) is left as it is, and a
    backend started with it is not reported."""
    mine = "--xla_cpu_enable_fast_math=false " + FLAG
    assert _probe("", xla_flags=mine)["flags"] == mine
    res = _probe("import jax.numpy as jnp\njnp.zeros(1).block_until_ready()", xla_flags=mine)
    assert res["flags"] == mine and res["warnings"] == []


def test_float32_is_refused_rather_than_computed():
    """Without ``configure_jax`` (float32 JAX) the posterior refuses to build, naming the
    remedy: its arrays would silently be float32."""
    code = """
import numpy as np
from bayesreg.data.images import Image
from bayesreg.mesh.tetmesh import Mesh, boundary_nodes, orient_tets
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import build_posterior
nodes = np.array([[0, 0, 0], [20, 0, 0], [0, 20, 0], [0, 0, 20]], float) + 10
tets = orient_tets(nodes, np.array([[0, 1, 2, 3]]))
mesh = Mesh(nodes, tets, np.zeros(1, np.int64), boundary_nodes(tets))
img = Image(np.zeros((40, 40, 40)), np.eye(4))
try:
    build_posterior(mesh, None, img, t_s=1.0, t_r=1.0, layout=ParamLayout(("all",), (), ()),
                    element_group=np.zeros(1, np.int64), prior={}, phi_ref=[])
except RuntimeError as exc:
    print("refused:", exc)
"""
    out = _run(code)
    assert out.returncode == 0, out.stderr
    assert "refused: build_posterior: JAX runs in float32" in out.stdout
    assert "bayesreg.configure_jax()" in out.stdout


def test_xla_reads_its_flags_when_the_backend_starts():
    """The premise of the above: XLA_FLAGS set after ``import jax`` but before the first
    computation is read (an unknown flag then aborts the process).  Should a JAX release
    read the flags at import instead, this fails and ``configure_jax`` needs revisiting."""
    code = ("import os, jax, jax.numpy as jnp\n"
            "os.environ['XLA_FLAGS'] = '--xla_bayesreg_no_such_flag=1'\n"
            "jnp.ones(1).block_until_ready()\n")
    out = _run(code)
    assert out.returncode != 0 and "xla_bayesreg_no_such_flag" in out.stderr
