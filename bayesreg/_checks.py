"""Validators shared by several modules (internal; public names).

Each raises ``ValueError`` with a message that names the argument and what it should be.
Array-shape checks are static: under ``jit`` the shapes are known, under ``vmap`` they are
those of one chain.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["check_affine", "count_nonfinite", "check_number", "check_shape", "check_last_axis",
           "as_index_array"]


def check_affine(affine, name: str = "image") -> np.ndarray:
    """``affine`` as a float64 ``(4, 4)`` array; ``ValueError`` unless finite and invertible."""
    affine = np.asarray(affine, dtype=np.float64)
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        got = f"shape {affine.shape}" if affine.shape != (4, 4) else "non-finite entries"
        raise ValueError(f"{name} affine must be a finite (4, 4) matrix, got {got}")
    if abs(np.linalg.det(affine[:3, :3])) < 1e-9:
        raise ValueError(f"{name} affine is singular")
    return affine


def count_nonfinite(data) -> int:
    """Number of NaN or infinite values in ``data`` (0 for integer and boolean arrays)."""
    data = np.asarray(data)
    return 0 if data.dtype.kind in "biu" else data.size - int(np.count_nonzero(np.isfinite(data)))


def check_number(value, name: str, *, positive: bool = True) -> float:
    """``value`` as a float; ``ValueError`` unless a finite real number ``> 0`` (``positive``)
    or ``>= 0``."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = np.nan
    ok = out > 0 if positive else out >= 0
    if isinstance(value, (bool, np.bool_)) or not (ok and np.isfinite(out)):
        shown = value.item() if isinstance(value, np.generic) else value
        raise ValueError(f"{name} must be a finite number {'>' if positive else '>='} 0, "
                         f"got {shown!r}")
    return out


def check_shape(name, value, expected, what):
    """Static check (shapes are known under ``jit``; under ``vmap`` they are those of one
    chain): ``value.shape == expected``."""
    shape = jnp.shape(value)
    if shape != expected:
        raise ValueError(f"{name} must have shape {expected} ({what}), got {shape}")


def check_last_axis(name, value, n, what):
    """``value`` is ``(..., n)`` (batched arrays allowed)."""
    shape = jnp.shape(value)
    if len(shape) < 1 or shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}) ({what}), got {shape}")


def as_index_array(a, name):
    """``a`` as int64 if it is an integer array or floats that are exactly integral."""
    a = np.asarray(a)
    if np.issubdtype(a.dtype, np.integer):
        return a.astype(np.int64)
    if np.issubdtype(a.dtype, np.floating) and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
        return a.astype(np.int64)
    raise ValueError(f"{name} must hold integer node indices (an integer dtype, or integral "
                     f"floats), got dtype {a.dtype}"
                     + (" with non-integral values" if np.issubdtype(a.dtype, np.floating) else ""))
