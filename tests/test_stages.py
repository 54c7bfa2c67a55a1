"""Stage lines and stage-named errors (bayesreg.stages)."""

from __future__ import annotations

import io

import numpy as np
import pytest

from bayesreg.stages import StageError, Stages


def test_each_finished_stage_prints_one_line_with_what_it_made():
    out = io.StringIO()
    stages = Stages(progress=True, stream=out)
    with stages.stage("mesh"):
        stages.tell("282 nodes (188 boundary), 1024 tets")
    with stages.stage("warm-up"):
        stages.switch("sampling")
        stages.tell("never printed: replaced below")
        stages.tell("40 draws")
    with stages.stage("outputs"):
        pass
    lines = out.getvalue().splitlines()
    assert len(lines) == 4 and stages.done == ["mesh", "warm-up", "sampling", "outputs"]
    assert lines[0].startswith("bayesreg: mesh done (") and lines[0].endswith(
        "s): 282 nodes (188 boundary), 1024 tets")
    assert lines[1].endswith("s)") and lines[2].endswith("s): 40 draws") and lines[3].endswith("s)")
    quiet = Stages(progress=False, stream=out)
    with quiet.stage("data"):
        quiet.tell("not printed")
    assert out.getvalue().count("\n") == 4


def test_a_library_failure_names_the_stage_and_bayesregs_own_errors_keep_their_type():
    stages = Stages()
    with pytest.raises(StageError, match=r"^truth: a dense factorisation failed .*synthetic\.shift_mm"):
        with stages.stage("truth"):
            np.linalg.cholesky(-np.eye(2))
    with pytest.raises(ValueError, match=r"^mesh: no mesh element"):
        with stages.stage("mesh"):
            raise ValueError("no mesh element is labelled ['csf']")
