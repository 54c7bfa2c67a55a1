"""Whether the paper's experiment starts right on every given brain: the truth, the mode search
and the chains' start, without sampling.

Run from the repository root with the BrainWeb models (not part of the test suite)::

    BAYESREG_BRAINWEB_DIR=../shared/data/brainweb python benchmarks/starts.py
    python benchmarks/starts.py --subjects 5,6 --set model.interpolation=linear --out starts.json

For each subject, the three-compartment NUTS config (``configs/paper_three_compartment_nuts.yaml``)
on ``data.source: brainweb`` at 1 mm with the paper's constrained truth (extra ``--set``
overrides apply to every subject): the problem is made (data, mesh, truth; a truth that
fails is a row with its error), then the starts (:func:`bayesreg.inference.initialisation.initialise`,
the mode search).  One row per subject: nodes, the truth's active skull constraints, the
mode search's message and gain in ``log p``, the central start's distance to the truth
over the boundary nodes (median, 95th percentile and largest, mm, and how many nodes are
more than 1 mm from it; the sweep calls a run whose median exceeds 1 mm a bad start), the
chains' starts' too, the times.  Printed as a table and
written to ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
CONFIG = REPO / "configs" / "paper_three_compartment_nuts.yaml"
SUBJECTS = "5,6,18,20,38,41,42,43,44,45"


def one(subject: int, sets: list[str]) -> dict:
    from bayesreg.config import load_config
    from bayesreg.inference.initialisation import initialise
    from bayesreg.model.problem import prepare

    row: dict = {"subject": subject}
    cfg = load_config(CONFIG, overrides=["data.source=brainweb", "data.resolution_mm=1.0",
                                         f"data.subject={subject}", "output.progress=false", *sets])
    t = time.perf_counter()
    try:
        problem = prepare(cfg)
    except Exception as exc:  # a failed truth is a result
        row.update(stage="problem", error=f"{type(exc).__name__}: {exc}", problem_s=time.perf_counter() - t)
        return row
    row["problem_s"] = time.perf_counter() - t
    ti = problem.truth_info or {}
    row.update(nodes=len(problem.mesh.nodes), boundary=len(problem.mesh.boundary),
               truth_active=ti.get("n_active"), truth_converged=ti.get("converged"))
    t = time.perf_counter()
    try:
        init = initialise(problem, cfg)
    except Exception as exc:
        row.update(stage="starts", error=f"{type(exc).__name__}: {exc}", starts_s=time.perf_counter() - t)
        traceback.print_exc()
        return row
    row["starts_s"] = time.perf_counter() - t
    info = init.info
    nb3 = 3 * len(problem.mesh.boundary)
    u_true = np.asarray(problem.truth.u)[np.asarray(problem.mesh.boundary)]

    def dist(theta):
        return np.linalg.norm(np.asarray(theta)[:nb3].reshape(-1, 3) - u_true, axis=1)

    d_c = dist(init.center)
    d_x = np.concatenate([dist(x) for x in init.x0])
    row.update(message=info.get("message"), logp_start=info.get("logp_start"),
               logp_mode=info.get("logp_mode"), iterations=info.get("iterations"),
               center_median_mm=float(np.median(d_c)), center_q95_mm=float(np.quantile(d_c, 0.95)),
               center_max_mm=float(d_c.max()), center_over_1mm=int(np.sum(d_c > 1.0)),
               starts_median_mm=float(np.median(d_x)),
               phi_center=[float(v) for v in np.asarray(init.center)[nb3:]])
    return row


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--subjects", default=SUBJECTS)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    import bayesreg

    bayesreg.configure_jax()
    rows = []
    for s in [int(x) for x in args.subjects.split(",")]:
        t = time.perf_counter()
        row = one(s, args.set)
        row["total_s"] = time.perf_counter() - t
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.out:
            args.out.write_text(json.dumps({"sets": args.set, "rows": rows}, indent=1))
    print("| subject | nodes | truth active | mode search | start median / q95 / max mm (nodes > 1 mm) | chains' starts median mm | s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['subject']} | {r.get('nodes', '-')} | - | {r['stage']} failed: {r['error'][:80]} | - | - | {r['total_s']:.0f} |")
        else:
            print(f"| {r['subject']} | {r['nodes']} | {r['truth_active']} | {r['message']} ({r['logp_mode']:.6g}) | "
                  f"{r['center_median_mm']:.2f} / {r['center_q95_mm']:.2f} / {r['center_max_mm']:.2f} "
                  f"({r['center_over_1mm']}) | {r['starts_median_mm']:.2f} | {r['total_s']:.0f} |")
    return rows


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
