"""Transition kernels, one a module (BlackJAX's layout): ``init`` and ``build_kernel``.

* :mod:`bayesreg.kernels.rwmh` - random-walk Metropolis-Hastings (the paper's kernel), in
  coordinate blocks, with an optional cached interior map and CG preconditioner;
* :mod:`bayesreg.kernels.gibbs` - a gradient kernel (NUTS, HMC or MALA, BlackJAX's) on the
  boundary displacements in Gibbs with random-walk moves of the elastic parameters, over
  a :class:`bayesreg.kernels.target.Target`;
* :mod:`bayesreg.kernels.adaptation` - the gradient kernels' windowed warm-up.

Every ``build_kernel`` returns a :class:`bayesreg.kernels.base.Kernel`.  Running chains of a
kernel is :mod:`bayesreg.chains`; warm-up, chunks and the stopping rule are
:mod:`bayesreg.sampler`.
"""

from bayesreg.kernels.base import Kernel

__all__ = ["Kernel"]
