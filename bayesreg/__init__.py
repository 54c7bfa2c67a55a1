"""bayesreg: Bayesian estimation of deformation and elastic parameters in non-rigid registration.

A JAX implementation of Risholm, Samset & Wells (the paper in ``shared/paper.md``).  The
subpackages follow the data flow::

    data (images, labels, sources) -> mesh (mesh, FE map on grids, skull) -> fem (K, solve)
         -> truth (synthetic truths) -> model (similarity, parameters, posterior log p)
         -> sampling (kernels, driver, convergence) -> inference (targets, mode, starts)
         -> outputs, report;  interop: fields as ITK/ANTs/Slicer files;  experiments:
            calibration, sweeps

with the run shell around them: ``config``, ``rundir``, ``checkpoint``, ``pipeline`` (the
main job), ``apply`` (a finished run's posterior on new data) and ``cli``.

:func:`run` is the main job (a config in, a run directory out); :func:`open_run` reopens a
finished run directory as the result :func:`run` returned.  Importing the package
changes nothing in the process; :func:`configure_jax` (float64, XLA flags, BLAS threads) is
called by the CLI and :func:`run`, and by a notebook before it uses the lower-level modules.

Conventions: nodes ``(N, 3)`` world mm, tets ``(M, 4)``, displacements ``(N, 3)`` mm,
DOF order node-major ``3*i + axis``, images carry their voxel-to-world affine.
"""

from bayesreg.config import Config, load_config
from bayesreg.jaxconfig import configure_jax
from bayesreg.pipeline import run, sample_problem
from bayesreg.model.problem import prepare
from bayesreg.outputs.result import open_run

__version__ = "0.1.0"
__all__ = ["Config", "load_config", "configure_jax", "prepare", "run", "open_run",
           "sample_problem", "__version__"]
