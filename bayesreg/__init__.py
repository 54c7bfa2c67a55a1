"""bayesreg: Bayesian estimation of deformation and elastic parameters in non-rigid registration.

A JAX implementation of Risholm, Samset & Wells (the paper in ``shared/paper.md``).
The layout follows the data flow::

    images -> labels -> mesh -> fem (K, E_r) -> solver (K_ii u_i = -K_ib u_b)
           -> similarity (E_s) -> posterior (log p) -> sampler (RW-MH) -> diagnostics / outputs

Conventions: nodes ``(N, 3)`` world mm, tets ``(M, 4)``, displacements ``(N, 3)`` mm,
DOF order node-major ``3*i + axis``, images carry their voxel-to-world affine.
"""

from bayesreg import _xla

_xla.configure()

from bayesreg.config import Config, load_config  # noqa: E402
from bayesreg.pipeline import prepare, run, sample_problem  # noqa: E402

__version__ = "0.1.0"
__all__ = ["Config", "load_config", "prepare", "run", "sample_problem", "__version__"]
