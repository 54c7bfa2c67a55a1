"""Transition kernels, one a module (BlackJAX's layout): ``init`` and ``build_kernel``.

* :mod:`bayesreg.sampling.kernels.rwmh` - random-walk Metropolis-Hastings (the paper's kernel), in
  coordinate blocks, with an optional cached interior map and CG preconditioner;
* :mod:`bayesreg.sampling.kernels.gibbs` - a gradient kernel (NUTS, HMC or MALA, BlackJAX's) on the
  boundary displacements in Gibbs with random-walk moves of the elastic parameters, over
  a :class:`bayesreg.sampling.kernels.target.Target`;
* :mod:`bayesreg.sampling.kernels.adaptation` - the gradient kernels' windowed warm-up.

Every ``build_kernel`` returns a :class:`bayesreg.sampling.kernels.base.Kernel`.  Running chains of a
kernel is :mod:`bayesreg.sampling.chains`; warm-up, chunks and the stopping rule are
:mod:`bayesreg.sampling.driver`.
"""

from bayesreg.sampling.kernels.base import Kernel

__all__ = ["Kernel"]
