"""Process settings of :mod:`bayesreg._xla`: the XLA:CPU fusion flag reaches XLA whatever
was imported first, and a backend started without it is reported (each case in a fresh
interpreter: XLA reads its flags once per process)."""

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
    import bayesreg  # noqa: F401
    import jax.numpy as jnp
    jnp.ones(2).sum().block_until_ready()
    import jax
print(json.dumps({{"flags": os.environ.get("XLA_FLAGS"), "x64": bool(jax.config.jax_enable_x64),
                  "warnings": [str(w.message) for w in caught if "bayesreg" in str(w.message)],
                  "where": [w.filename for w in caught if "bayesreg" in str(w.message)]}}))
"""


def _probe(body: str, xla_flags: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    code = PROBE.format(body="\n".join("    " + line for line in body.splitlines()) or "    pass")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("first", ["", "import jax", "import arviz"])
def test_flag_set_before_the_backend_starts(first):
    """Importing JAX or ArviZ (which imports JAX) before bayesreg still gets the flag: XLA
    reads XLA_FLAGS when its first backend starts, not at ``import jax``."""
    res = _probe(first)
    assert res["flags"] == FLAG
    assert res["x64"]
    assert res["warnings"] == []


def test_backend_started_without_the_flag_warns():
    """A JAX computation before ``import bayesreg`` starts XLA:CPU without the flag: the
    flag is not added (too late) and a warning names it and the remedy."""
    res = _probe("import jax.numpy as jnp\njnp.zeros(1).block_until_ready()")
    assert res["flags"] is None
    assert len(res["warnings"]) == 1
    msg = res["warnings"][0]
    assert FLAG in msg and "Import bayesreg before running any JAX computation" in msg
    # attributed to the user's ``import bayesreg`` (here the ``-c`` script), not to bayesreg
    assert res["where"] == ["<string>"]


def test_users_flag_kept():
    """A user's own setting of the flag (or XLA_FLAGS mentioning it) is left as it is, and a
    backend started with it is not reported."""
    mine = "--xla_cpu_enable_fast_math=false " + FLAG
    assert _probe("", xla_flags=mine)["flags"] == mine
    res = _probe("import jax.numpy as jnp\njnp.zeros(1).block_until_ready()", xla_flags=mine)
    assert res["flags"] == mine and res["warnings"] == []


def test_xla_reads_its_flags_when_the_backend_starts():
    """The premise of the above: XLA_FLAGS set after ``import jax`` but before the first
    computation is read (an unknown flag then aborts the process).  Should a JAX release
    read the flags at import instead, this fails and ``_xla.configure`` needs revisiting."""
    code = ("import os, jax, jax.numpy as jnp\n"
            "os.environ['XLA_FLAGS'] = '--xla_bayesreg_no_such_flag=1'\n"
            "jnp.ones(1).block_until_ready()\n")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode != 0 and "xla_bayesreg_no_such_flag" in out.stderr
