"""The stages of a run, named in its messages: data, mesh, truth, posterior, starts, warm-up,
sampling, outputs.

:class:`Stages` tracks which stage a run is in, prints a line as each one ends (so the first
seconds of a run are not silent), and turns a failure deep inside a numerical library (a
LAPACK code, a non-finite array) into a :class:`StageError` that names the stage and what to
change.  bayesreg's own errors (bad input, a mesh that cannot be used) already say what is
wrong: they pass through with the stage put in front of their message, their type kept.
"""

from __future__ import annotations

import contextlib
import sys
import time

import numpy as np

__all__ = ["StageError", "Stages", "STAGES", "HINTS"]

#: The stages of a run, in order.
STAGES = ("data", "mesh", "truth", "posterior", "starts", "warm-up", "sampling", "outputs")

#: What to change when a numerical library fails in each stage.
HINTS = {
    "data": "check the images and the label map (data.*)",
    "mesh": "try another mesh.edge_length_mm or mesh.smoothing_sigma_mm, or give a mesh "
            "(mesh.file)",
    "truth": "try a smaller synthetic.shift_mm, stiffer CSF (synthetic.lam.csf, "
             "synthetic.mu.csf) or synthetic.truth: smooth",
    "posterior": "check the model's priors and temperatures (model.*)",
    "starts": "try init.method: perturb, another init.start, or fewer "
              "init.optimizer_iterations",
    "warm-up": "try smaller initial scales (sampler.step_size, sampler.sigma_*) or another "
               "sampler.kind",
    "sampling": "try another sampler.kind, or resume with --resume after fixing the cause",
    "outputs": "check the free space and permissions of the run directory; the draws are in "
               "its checkpoint (--resume writes the outputs again)",
}


class StageError(RuntimeError):
    """A stage of a run failed inside a numerical library.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES`.
    """

    def __init__(self, stage: str, message: str):
        super().__init__(f"{stage}: {message}; {HINTS.get(stage, '')}".rstrip("; "))
        self.stage = stage


def _library_failure(exc: BaseException) -> str | None:
    """What a numerical library's failure means, or ``None`` for bayesreg's own errors."""
    if isinstance(exc, np.linalg.LinAlgError):
        return (f"a dense factorisation failed (LAPACK: {exc}): the matrix is singular or not "
                "positive definite")
    if isinstance(exc, FloatingPointError):
        return f"a computation overflowed or produced NaN ({exc})"
    if type(exc).__module__.startswith(("jaxlib", "jax.")) and isinstance(exc, RuntimeError):
        return f"a JAX computation failed ({type(exc).__name__}: {exc})"
    return None


class Stages:
    """The stage a run is in (:meth:`stage`), its timings, and one line per finished stage.

    Parameters
    ----------
    progress : bool
        Print a line per finished stage to ``stream``.
    stream : file, optional
        Default ``sys.stderr``.
    """

    def __init__(self, progress: bool = False, stream=None):
        self.progress = progress
        self.stream = stream
        self.current: str | None = None
        self.done: list[str] = []
        self._t = time.perf_counter()
        self._detail: str | None = None

    @contextlib.contextmanager
    def stage(self, name: str):
        """Context of stage ``name``: a library failure inside becomes a :class:`StageError`
        (raised from it); bayesreg's own ``ValueError`` (and subclasses: bad input, a mesh
        error) gets ``"name: "`` in front of its message, its type kept; an interrupt passes
        through, :attr:`current` telling where it came."""
        self.current = name
        self._t = time.perf_counter()
        self._detail = None
        try:
            yield
        except StageError:
            raise
        except Exception as exc:
            name = self.current  # (switch may have moved on)
            meaning = _library_failure(exc)
            if meaning is not None:
                raise StageError(name, meaning) from exc
            if isinstance(exc, ValueError) and exc.args and isinstance(exc.args[0], str) \
                    and not exc.args[0].startswith(f"{name}: "):
                exc.args = (f"{name}: {exc.args[0]}",) + exc.args[1:]
            raise
        self._finish()

    def switch(self, name: str) -> None:
        """Inside :meth:`stage`, the current stage ends and ``name`` begins (the warm-up's
        end, seen by the sampler's callback)."""
        self._finish()
        self.current = name
        self._t = time.perf_counter()
        self._detail = None

    def tell(self, detail: str) -> None:
        """What the current stage made, printed on its line when it ends (``bayesreg: mesh
        done (0.9 s): 282 nodes (188 boundary), 1024 tets``)."""
        self._detail = detail

    def _finish(self) -> None:
        self.done.append(self.current)
        if self.progress:
            detail = f": {self._detail}" if self._detail else ""
            print(f"bayesreg: {self.current} done ({time.perf_counter() - self._t:.1f} s){detail}",
                  file=self.stream or sys.stderr, flush=True)
        self._detail = None
