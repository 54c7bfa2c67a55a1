"""Checkpoints of a run in progress: draws written chunk by chunk, the sampler state after each.

Layout inside the run directory (every file written atomically and durably: a temporary
name, flushed to disk, then ``os.replace``; :mod:`bayesreg._files`)::

    checkpoint/config.json      the resolved config of the run
    checkpoint/config.sha256    the SHA-256 of config.json as written (a resume refuses an edit)
    checkpoint/problem.npz      images, mesh and truth (:meth:`Checkpoint.save_problem`)
    checkpoint/init.npz         chain starts and initial jumping kernels
    checkpoint/warmup.npz       :class:`bayesreg.sampling.driver.WarmupCheckpoint` after the last
                                warm-up chunk (while the warm-up goes)
    checkpoint/state.npz        :class:`bayesreg.sampling.driver.SamplerCheckpoint` after the last chunk
    checkpoint/draws/chunk_00000.npz ...  the stored draws of each sampling chunk

A chunk file is written before the state that counts it, so the state never refers to a
missing chunk; a chunk beyond the state (killed in between) is ignored and rewritten.  When
the run finishes, the draws and the state are removed (``posterior.nc`` holds the draws);
the config, problem and starts stay, so a finished run can be rebuilt in a notebook.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import zipfile
import zlib
from pathlib import Path

import jax
import numpy as np

from bayesreg._files import dumps_json, replace_durably, write_text_atomic, writing
from bayesreg.config import Config, ConfigError, format_errors
from bayesreg.data.images import Image
from bayesreg.inference.initialisation import Initialisation
from bayesreg.mesh.tetmesh import Mesh
from bayesreg.model.problem import ProblemData
from bayesreg.sampling.driver import SamplerCheckpoint, WarmupCheckpoint
from bayesreg.truth.synthetic import Truth

__all__ = ["Checkpoint", "savez_atomic"]

_OUT_NAMES = ("positions", "interior", "logdensity", "acceptance", "cg_iterations", "solve_failures",
              "grad_evals", "divergences", "tree_depth", "energy")


def savez_atomic(path: Path, *, compressed: bool = False, **arrays) -> None:
    """``np.savez`` (or ``savez_compressed``) to a temporary name, then renamed over ``path``
    (:func:`bayesreg._files.replace_durably`: flushed to disk, atomic).

    Raises
    ------
    OSError
        The file could not be written (named in the message, e.g. a full disk); the file
        that was there before is left as it was.
    """
    tmp = Path(path).with_name(Path(path).name + ".tmp.npz")
    try:
        with writing(path):
            (np.savez_compressed if compressed else np.savez)(tmp, **arrays)
            replace_durably(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _numbered(prefix: str, arrays) -> dict:
    """``{prefix_0: arrays[0], ...}``: a list of arrays as the entries of an ``.npz``."""
    return {f"{prefix}_{j}": np.asarray(a) for j, a in enumerate(arrays)}


def _read_numbered(z, prefix: str) -> list:
    """The list :func:`_numbered` wrote under ``prefix`` into the ``.npz`` ``z``."""
    return [z[f"{prefix}_{j}"] for j in range(sum(1 for k in z.files if k.startswith(prefix + "_")))]


@contextlib.contextmanager
def _reading(path):
    """Errors of reading a damaged ``.npz`` (truncated, emptied, overwritten) as one
    ``ValueError`` that names the file, in place of NumPy's and zipfile's tracebacks."""
    try:
        yield
    except (zipfile.BadZipFile, EOFError, KeyError, ValueError, zlib.error) as exc:
        raise ValueError(f"{path} is damaged or incomplete ({type(exc).__name__}: {exc}): the "
                         "run cannot be resumed from it; start it again (--overwrite)") from exc


class Checkpoint:
    """The ``checkpoint/`` folder of a run directory ``run_dir``.

    Its readers raise ``ValueError`` naming the file when a file is damaged or incomplete.
    """

    def __init__(self, run_dir):
        self.dir = Path(run_dir) / "checkpoint"
        self.draws_dir = self.dir / "draws"
        self.chunks_done: int | None = None  # sampling chunks saved by on_chunk (None: warm-up)
        self.warmup_chunks_done = 0  # warm-up chunks saved by on_warmup_chunk

    # ---- config, problem, starts ----
    @property
    def config_path(self) -> Path:
        return self.dir / "config.json"

    @property
    def problem_path(self) -> Path:
        return self.dir / "problem.npz"

    @property
    def digest_path(self) -> Path:
        return self.dir / "config.sha256"

    def save_config(self, cfg: Config) -> None:
        """Write the resolved config and its digest (:meth:`load_config` checks it)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        text = dumps_json(cfg.model_dump(mode="json"), indent=2)
        write_text_atomic(self.config_path, text)
        write_text_atomic(self.digest_path, hashlib.sha256(text.encode()).hexdigest() + "\n")

    def load_config(self) -> Config:
        """The run's saved config (``checkpoint/config.json``), validated.

        Raises
        ------
        FileNotFoundError
            If there is no saved config.
        ConfigError
            If it is not valid JSON or not a valid config (the message names the file and
            key), or was changed after the run wrote it (its digest no longer matches: a
            resume would mix the draws of two configs).
        """
        from pydantic import ValidationError

        if not self.config_path.is_file():
            raise FileNotFoundError(f"{self.config_path} not found: not a run directory written "
                                    "with output.checkpoint, or not a run directory at all")
        text = self.config_path.read_text()
        if self.digest_path.is_file():
            want = self.digest_path.read_text().strip()
            if hashlib.sha256(text.encode()).hexdigest() != want:
                raise ConfigError(
                    f"{self.config_path} was changed after the run started (its SHA-256 no "
                    f"longer matches {self.digest_path.name}): resuming would mix the draws of "
                    "two configs; put the original back, or start a new run (--overwrite, or "
                    "another --out) with the config you want")
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{self.config_path}: not valid JSON: {exc}") from None
        if not isinstance(raw, dict):
            raise ConfigError(f"{self.config_path}: the top level must be a mapping")
        # a run written before a key existed resumes with the behaviour it was started with,
        # not with a later default
        raw.setdefault("model", {}).setdefault("skull_barrier_mm", 0.0)
        raw["model"].setdefault("quadrature_level", 0)
        raw["model"].setdefault("moving_dtype", "float64")
        raw.setdefault("synthetic", {}).setdefault("outside", "background")
        raw.setdefault("sampler", {}).setdefault("joint", False)
        try:
            return Config.model_validate(raw)
        except ValidationError as exc:
            raise ConfigError(format_errors(exc, str(self.config_path))) from None

    def save_problem(self, data: ProblemData) -> None:
        """Write the data of a problem (images, mesh, truth) to ``problem.npz``, compressed and
        atomically: :meth:`load_problem` gives it back without meshing again (meshing with
        fTetWild is not bit-reproducible, so a resumed run must reuse the mesh)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        arrays = {
            "f": data.f.data, "f_affine": data.f.affine,
            "m": np.asarray(data.m.data), "m_affine": data.m.affine,
            "labels": data.labels.data, "labels_affine": data.labels.affine,
            "nodes": data.mesh.nodes, "tets": data.mesh.tets, "tissue": data.mesh.tissue,
            "boundary": data.mesh.boundary,
            "meta": np.array(dumps_json({
                "intensity_scale": data.intensity_scale, "n_skull_carved": data.n_skull_carved,
                "timings": data.timings, "truth_info": data.truth_info,
                "mesh_info": data.mesh_info,
            })),
        }
        if data.truth is not None:
            t = data.truth
            arrays.update(truth_u=t.u, truth_pushed=t.pushed)
            if t.parameters_known:
                arrays.update(truth_lam_e=t.lam_e, truth_mu_e=t.mu_e)
            if t.field is not None:
                arrays.update(truth_field=t.field.data, truth_field_affine=t.field.affine)
        savez_atomic(self.problem_path, compressed=True, **arrays)

    def load_problem(self) -> ProblemData:
        """The data :meth:`save_problem` wrote.

        Raises
        ------
        ValueError
            If the file is damaged or incomplete (not a readable ``.npz`` of a problem).
        """
        path = self.problem_path
        try:
            z = np.load(path, allow_pickle=False)
            meta = json.loads(str(z["meta"]))
            truth = None
            if "truth_u" in z:
                field = (Image(z["truth_field"], z["truth_field_affine"]) if "truth_field" in z
                         else None)
                truth = Truth(z["truth_u"], z["truth_lam_e"] if "truth_lam_e" in z else None,
                              z["truth_mu_e"] if "truth_mu_e" in z else None, z["truth_pushed"],
                              field)
            return ProblemData(
                f=Image(z["f"], z["f_affine"]), m=Image(z["m"], z["m_affine"]),
                labels=Image(z["labels"], z["labels_affine"]),
                mesh=Mesh(z["nodes"], z["tets"], z["tissue"], z["boundary"]),
                truth=truth, truth_info=meta["truth_info"],
                intensity_scale=meta["intensity_scale"], n_skull_carved=meta["n_skull_carved"],
                timings=meta["timings"], mesh_info=meta.get("mesh_info"))
        except (zipfile.BadZipFile, EOFError, KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path} is damaged or incomplete ({type(exc).__name__}: {exc}): "
                             "the problem cannot be read back") from exc

    def save_init(self, init: Initialisation) -> None:
        anchor = {} if init.anchor is None else {"anchor": init.anchor}
        savez_atomic(self.dir / "init.npz", x0=init.x0, center=init.center, blocked=init.blocked,
                     info=np.array(dumps_json(init.info, default=float)), **_numbered("sigma", init.sigma),
                     **anchor)

    def load_init(self) -> Initialisation | None:
        """The run's starts and proposal scales, or ``None`` if they were never saved."""
        path = self.dir / "init.npz"
        if not path.is_file():
            return None
        with _reading(path):
            z = np.load(path, allow_pickle=False)
            return Initialisation(z["x0"], z["center"], tuple(_read_numbered(z, "sigma")),
                                  bool(z["blocked"]), json.loads(str(z["info"])),
                                  z["anchor"] if "anchor" in z.files else None)

    # ---- sampler progress ----
    def on_chunk(self, ckpt: SamplerCheckpoint, out) -> None:
        """Callback for :func:`bayesreg.sampling.driver.sample`: write the chunk, then the state."""
        self.chunks_done = ckpt.chunks_done
        if out is not None:
            self.draws_dir.mkdir(parents=True, exist_ok=True)
            savez_atomic(self.draws_dir / f"chunk_{ckpt.chunks_done - 1:05d}.npz",
                         **dict(zip(_OUT_NAMES, out)))
        leaves = ckpt.states if isinstance(ckpt.states, list) else jax.tree.leaves(ckpt.states)
        meta = {"chunks_done": ckpt.chunks_done, "rhat_history": [list(h) for h in ckpt.rhat_history],
                "timings": ckpt.timings}
        savez_atomic(self.dir / "state.npz", warmup_acceptance=np.asarray(ckpt.warmup_acceptance),
                     meta=np.array(dumps_json(meta, default=float)), **_numbered("sigma", ckpt.sigma),
                     **_numbered("state", leaves))
        (self.dir / "warmup.npz").unlink(missing_ok=True)  # the warm-up's end supersedes it

    def on_warmup_chunk(self, ckpt: WarmupCheckpoint) -> None:
        """Callback for :func:`bayesreg.sampling.driver.sample` during the warm-up."""
        self.warmup_chunks_done = ckpt.chunks_done
        meta = {"chunks_done": ckpt.chunks_done, "timings": ckpt.timings}
        savez_atomic(self.dir / "warmup.npz", warmup_acceptance=np.asarray(ckpt.warmup_acceptance),
                     meta=np.array(dumps_json(meta, default=float)), **_numbered("state", ckpt.states),
                     **_numbered("adaptation", ckpt.adaptation))

    def load_warmup(self) -> WarmupCheckpoint | None:
        """The warm-up's progress, or ``None`` if no warm-up chunk was saved."""
        path = self.dir / "warmup.npz"
        if not path.is_file():
            return None
        with _reading(path):
            z = np.load(path, allow_pickle=False)
            meta = json.loads(str(z["meta"]))
            return WarmupCheckpoint(_read_numbered(z, "state"), _read_numbered(z, "adaptation"),
                                    int(meta["chunks_done"]), z["warmup_acceptance"],
                                    meta["timings"])

    def load_state(self):
        """``(SamplerCheckpoint, draws or None)``, or ``None`` if the warm-up never finished."""
        path = self.dir / "state.npz"
        if not path.is_file():
            return None
        with _reading(path):
            z = np.load(path, allow_pickle=False)
            meta = json.loads(str(z["meta"]))
            states = _read_numbered(z, "state")  # the sampler rebuilds the pytree
            k = int(meta["chunks_done"])
            ckpt = SamplerCheckpoint(states, tuple(_read_numbered(z, "sigma")),
                                     z["warmup_acceptance"], k,
                                     [_history_entry(h) for h in meta["rhat_history"]],
                                     meta["timings"])
        if k == 0:
            return ckpt, None
        chunks = []
        for j in range(k):
            p = self.draws_dir / f"chunk_{j:05d}.npz"
            if not p.is_file():
                raise FileNotFoundError(f"{p} is missing: the checkpoint is incomplete")
            with _reading(p):
                c = np.load(p, allow_pickle=False)
                # chunks written before the NUTS stats were stored: depth 0, energy NaN
                fill = {"tree_depth": 0, "energy": np.nan}
                chunks.append([c[n] if n in c.files or n not in fill
                               else np.full(c["logdensity"].shape, fill[n]) for n in _OUT_NAMES])
        draws = tuple(np.concatenate([c[j] for c in chunks], axis=1) for j in range(len(_OUT_NAMES)))
        return ckpt, draws

    def clear_progress(self) -> None:
        """Remove the draws and the sampler and warm-up states (after the outputs are written)."""
        shutil.rmtree(self.draws_dir, ignore_errors=True)
        (self.dir / "state.npz").unlink(missing_ok=True)
        (self.dir / "warmup.npz").unlink(missing_ok=True)


def _history_entry(h) -> tuple:
    """A stop-rule record read back from strict JSON (``null`` for a non-finite number): the
    classic R-hat ``inf`` (before it can be computed), the rank figures NaN (not computed);
    records of 2 entries (older checkpoints) get NaN rank figures."""
    classic = float("inf") if h[1] is None else float(h[1])
    rest = [float("nan") if v is None else float(v) for v in h[2:5]]
    return (int(h[0]), classic, *rest, *[float("nan")] * (3 - len(rest)))
