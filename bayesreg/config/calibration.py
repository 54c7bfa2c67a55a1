"""The calibration file of ``bayesreg calibrate`` (:mod:`bayesreg.experiments.calibration`), validated:
every key, its default, its meaning, its checks."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from bayesreg.config.models import BetaPrior, Float, GammaPrior, Int

__all__ = ["CalibrationSpec", "ProblemSpec", "CalModelSpec", "CalSamplerSpec"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class ProblemSpec(_Strict):
    """The small problem: a box mesh over an analytic image."""

    cells: Int = Field(3, ge=2, le=6, description="cubes per axis of the box mesh (6 tetrahedra "
                       "each; 3: 64 nodes, 56 on the boundary)")
    size_mm: Float = Field(30.0, gt=0, description="edge of the box, mm")
    voxel_mm: Float = Field(1.5, gt=0, description="voxel size of the moving image m, mm")
    wavelength_mm: Float = Field(15.0, gt=0, description="wavelength of the plane waves that make "
                                 "m, mm")
    quadrature_level: Int = Field(0, ge=0, le=2, description="quadrature of E_s (as "
                                  "model.quadrature_level of a run)")


class CalModelSpec(_Strict):
    """The posterior that is checked (and the prior the truths come from)."""

    prior_normaliser: Literal["paper", "exact"] = Field(
        "exact", description="exact: the posterior carries (1/2) log pdet S(lam, mu), the "
        "normaliser of its elastic prior; paper: Eq. 12 without it (the truths are drawn from "
        "the normalised prior either way)")
    t_s: Float = Field(0.5, gt=0, description="similarity temperature T_s (intensity^2 mm^3): "
                       "noise sd sqrt(T_s / (2 w_q)) at a quadrature point of weight w_q")
    t_s_prior: GammaPrior | None = Field(
        None, description="the similarity temperature as a parameter (as model.t_s_prior of a "
        "run): each truth's 1 / T_s drawn from this Gamma prior, the posterior integrating it out")
    data_t_s: Float | None = Field(
        None, gt=0, description="simulate the data with this temperature instead of the model's "
        "(noise the posterior does not assume: the simplest model mismatch); null: the model's")
    t_r: Float = Field(20.0, gt=0, description="elastic temperature T_r ([lam] mm^3)")
    rigid_sd_mm: Float = Field(1.0, gt=0, description="prior sd of the rms boundary "
                               "displacement along each rigid-body mode, mm")
    prior_lam: BetaPrior = Field(BetaPrior(a=2.0, b=2.0, r1=0.0, r2=20.0),
                                 description="prior of lam_a and lam_b")
    prior_mu: BetaPrior = Field(BetaPrior(a=2.0, b=2.0, r1=0.5, r2=2.0),
                                description="prior of mu_b (mu_a is fixed at 1)")


class CalSamplerSpec(_Strict):
    """The chains of each replica (NUTS in Gibbs, as ``sampler.kind: nuts``)."""

    chains: Int = Field(2, ge=2, description="chains per replica")
    warmup_steps: Int = Field(300, ge=20, description="transitions of Stan's windowed warm-up")
    draws: Int = Field(500, ge=10, description="draws per chain after the warm-up")
    thinning: Int = Field(1, ge=1, description="transitions per stored draw")
    max_tree_depth: Int = Field(6, ge=1, le=10, description="NUTS' maximum trajectory doublings")
    elastic_moves: Int = Field(4, ge=1, description="random-walk moves of the parameters per "
                               "transition")
    collapsed_moves: Int = Field(2, ge=0, description="collapsed moves of the parameters per "
                                 "transition (as sampler.collapsed_moves of a run; the likelihood "
                                 "linearised at each chain's start, then at its state after the "
                                 "warm-up)")
    chain_method: Literal["auto", "vectorized", "sequential", "threads"] = Field(
        "auto", description="how the replicas' chains run (as sampler.chain_method of a run: "
        "auto is threads on a CPU, vectorized on an accelerator); the draws do not depend on "
        "it beyond round-off, which NUTS trajectories amplify")
    ranks: Int = Field(99, ge=9, description="L: draws (thinned evenly from all chains) among "
                       "which each truth is ranked (ranks 0..L)")
    bins: Int = Field(10, ge=2, description="bins of the rank histograms (must divide L + 1)")

    @model_validator(mode="after")
    def _bins(self):
        if (self.ranks + 1) % self.bins:
            raise ValueError(f"bins ({self.bins}) must divide ranks + 1 ({self.ranks + 1})")
        if self.ranks > self.chains * self.draws:
            raise ValueError(f"ranks ({self.ranks}) exceeds the draws of all chains "
                             f"({self.chains * self.draws})")
        return self


class CalibrationSpec(_Strict):
    """A calibration file (YAML), validated: ``bayesreg calibrate FILE``."""

    name: str = Field("calibration", description="the check's name")
    seed: Int = Field(0, ge=0, description="seed of the truths, the data and the chains")
    replicas: Int = Field(100, ge=2, description="truths drawn from the prior, each sampled")
    problem: ProblemSpec = Field(ProblemSpec(), description="the small problem")
    model: CalModelSpec = Field(CalModelSpec(), description="the posterior that is checked")
    sampler: CalSamplerSpec = Field(CalSamplerSpec(), description="the chains")
    dir: str = Field("runs/calibration", description="output folder")
