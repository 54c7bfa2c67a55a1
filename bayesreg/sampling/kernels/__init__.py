"""Kernel families, one a module (BlackJAX's layout): ``init``, ``build_kernel`` and
``as_algorithm``.

* :mod:`bayesreg.sampling.kernels.rwmh` - random-walk Metropolis-Hastings (the paper's kernel), in
  coordinate blocks, with an optional cached interior map and CG preconditioner, and its
  Robbins-Monro warm-up;
* :mod:`bayesreg.sampling.kernels.gibbs` - a gradient kernel (NUTS, HMC or MALA, BlackJAX's) on the
  boundary displacements in Gibbs with random-walk moves of the elastic parameters, over
  a :class:`bayesreg.sampling.kernels.target.Target`, with Stan's windowed warm-up
  (:mod:`bayesreg.sampling.kernels.adaptation`) and, for joint targets under the exact
  normaliser, surrogate transitions (:mod:`bayesreg.sampling.kernels.surrogate`).

Every ``build_kernel`` returns a :class:`bayesreg.sampling.kernels.base.Kernel` and every
``as_algorithm`` a :class:`bayesreg.sampling.kernels.base.SamplingAlgorithm` (the kernel with
its warm-up), which the one driver, :func:`bayesreg.sampling.driver.sample`, runs: warm-up,
chunks of draws mapped over the chains (:mod:`bayesreg.sampling.chains`), the stop rule,
checkpoints.  A new kernel family is one module here with an ``as_algorithm``, its name in
``sampler.kind`` (:mod:`bayesreg.config.models`) and its construction from the config in
:func:`bayesreg.inference.targets.sampling_algorithm`.
"""

from bayesreg.sampling.kernels.base import Kernel, Program, SamplingAlgorithm, Warmup

__all__ = ["Kernel", "Warmup", "Program", "SamplingAlgorithm"]
