"""The run's checkpoint (bayesreg.checkpoint): damaged files are named; a config saved
before later keys existed resumes as it ran; the warm-up's progress is kept until its end."""

import json

import numpy as np
import pytest

from bayesreg.checkpoint import Checkpoint
from bayesreg.config import load_config
from bayesreg.inference.initialisation import Initialisation
from bayesreg.sampling.driver import SamplerCheckpoint, WarmupCheckpoint


@pytest.mark.parametrize("damage", ["truncated", "emptied", "text"])
def test_a_damaged_checkpoint_file_is_an_error_that_names_it(tmp_path, damage):
    """``--resume`` of a run whose starts, state or draws were damaged (a full disk, a copy
    cut short) ends with the file named, not a zipfile or NumPy traceback."""
    ck = Checkpoint(tmp_path)
    ck.dir.mkdir(parents=True)
    ck.save_init(Initialisation(np.zeros((2, 5)), np.zeros(5), (np.ones(5),), False, {"a": 1}))
    state = SamplerCheckpoint([np.zeros((2, 5))], (np.ones(5),), np.array([0.3]), 1, [(10, 1.5)], {})
    ck.on_chunk(state, tuple(np.zeros((2, 10, 1)) for _ in range(8)))
    assert ck.load_init() is not None and ck.load_state()[1] is not None  # intact: read back
    files = [ck.dir / "init.npz", ck.dir / "state.npz", ck.draws_dir / "chunk_00000.npz"]
    intact = [p.read_bytes() for p in files]
    for path, data in zip(files, intact):
        if damage == "truncated":
            path.write_bytes(data[: len(data) // 2])
        elif damage == "emptied":
            path.write_bytes(b"")
        else:
            path.write_text("not an archive")
        load = ck.load_init if path.name == "init.npz" else ck.load_state
        with pytest.raises(ValueError, match=f"{path.name} is damaged or incomplete .* cannot be "
                           "resumed from it"):
            load()
        path.write_bytes(data)


def test_run_written_before_the_barrier_resumes_without_it(tmp_path):
    """A checkpointed config without ``model.skull_barrier_mm``, ``quadrature_level`` and
    ``moving_dtype`` (written by a version without those keys) resumes as it ran: with the
    hard constraint alone, the 4-point rule and ``m`` in float64, not today's defaults
    (1 mm, level 1, float32)."""
    cfg = load_config("configs/quickstart.yaml")
    raw = cfg.model_dump(mode="json")
    del raw["model"]["skull_barrier_mm"], raw["model"]["quadrature_level"], raw["model"]["moving_dtype"]
    (tmp_path / "checkpoint").mkdir()
    (tmp_path / "checkpoint" / "config.json").write_text(json.dumps(raw))
    resumed = Checkpoint(tmp_path).load_config().model
    assert resumed.skull_barrier_mm == 0.0 and resumed.quadrature_level == 0
    assert resumed.moving_dtype == "float64"  # m exactly as given, as such runs had it
    assert load_config(None).model.skull_barrier_mm == 1.0
    assert load_config(None).model.moving_dtype == "float32"


def test_the_warmup_is_kept_chunk_by_chunk_until_it_ends(tmp_path):
    """A warm-up checkpoint reads back as written (the leaves of the states and of the
    adaptation, its timings); the warm-up's end (the sampler's state) removes it, and so
    does a finished run; a damaged one is named."""
    ck = Checkpoint(tmp_path)
    ck.dir.mkdir(parents=True)
    assert ck.load_warmup() is None
    rng = np.random.default_rng(0)
    warm = WarmupCheckpoint([rng.normal(size=(2, 5)), np.arange(2)],
                            [rng.normal(size=(2, 5, 5)), np.asarray(3, np.int32)], 4,
                            np.array([0.3, 0.25]), {"first_chunk_incl_compile_s": 1.5, "warmup_s": 9.0})
    ck.on_warmup_chunk(warm)
    back = ck.load_warmup()
    assert back.chunks_done == 4 and ck.warmup_chunks_done == 4 and back.timings == warm.timings
    for a, b in zip(back.states + back.adaptation, warm.states + warm.adaptation):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    np.testing.assert_array_equal(back.warmup_acceptance, warm.warmup_acceptance)
    (ck.dir / "warmup.npz").write_bytes(b"")
    with pytest.raises(ValueError, match="warmup.npz is damaged or incomplete"):
        ck.load_warmup()
    ck.on_warmup_chunk(warm)
    ck.on_chunk(SamplerCheckpoint([np.zeros((2, 5))], (np.ones(5),), np.array([0.3]), 0, [], {}), None)
    assert ck.load_warmup() is None and ck.load_state() is not None
    ck.on_warmup_chunk(warm)
    ck.clear_progress()
    assert ck.load_warmup() is None and ck.load_state() is None
