"""fTetWild in a process of its own: ``python _tetwild_worker.py IN.npz OUT.npz``.

Run as a script by :func:`bayesreg.mesh.meshing.tetrahedralize` (never imported by the package):
fTetWild's native library (Geogram) replaces the process's signal handlers, so that after a
call in the main process Ctrl-C no longer raises ``KeyboardInterrupt`` (the process dies of
the signal), and during a call it ends the process outright; it can also crash.  In a child
process none of that reaches the run.  ``IN.npz`` holds ``verts`` ``(V, 3)`` float64,
``faces`` ``(F, 3)`` int32, ``edge_length_abs``, ``epsilon`` and ``num_threads``; ``OUT.npz``
receives ``nodes`` ``(N, 3)`` and ``tets`` ``(M, 4)``.  Exit status 0 on success; anything
else, with the error on stderr, on failure.
"""

import sys


def main(src: str, dst: str) -> int:
    import numpy as np

    import pytetwild

    with np.load(src) as data:
        nodes, tets = pytetwild.tetrahedralize(
            data["verts"], data["faces"], edge_length_abs=float(data["edge_length_abs"]),
            epsilon=float(data["epsilon"]), num_threads=int(data["num_threads"]))
    np.savez(dst, nodes=np.asarray(nodes, np.float64), tets=np.asarray(tets, np.int64))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
