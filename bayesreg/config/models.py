"""The run configuration as pydantic models: every key, its default, its meaning, its checks.

Unknown keys are errors naming the key; so are a boolean, infinity or NaN given for a
number, a key that the chosen data source or synthetic case would ignore, and a start
(``model.initial_*``) outside its prior's support.  Each field's ``description`` is the
documentation of its key (the configuration reference is generated from these models).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    StrictInt,
    Tag,
    model_validator,
)
from pydantic_core import PydanticCustomError

__all__ = ["Config", "ConfigError", "DataConfig", "MeshConfig", "SyntheticConfig", "ModelConfig",
           "SolverConfig", "SamplerConfig", "InitConfig", "OutputConfig", "BetaPrior", "GammaPrior",
           "TissuePriors", "TissueValues", "FixedParam", "PRIOR_TAGS"]

Tissue = Literal["csf", "gm", "wm"]


def _no_bool(v):
    # YAML 1.1 reads yes/no/on/off/true/false as booleans, which pydantic's lax float would
    # take as 1.0 / 0.0
    if isinstance(v, bool):
        raise PydanticCustomError("float_type", "Input should be a valid number, not a boolean")
    return v


Float = Annotated[float, BeforeValidator(_no_bool)]
"""A float that refuses booleans (integers and numeric strings as pydantic's lax mode)."""
Int = StrictInt
"""An int that refuses booleans, floats and strings (YAML integers are ints)."""


class ConfigError(ValueError):
    """A configuration is invalid; the message names the offending key."""


class _Strict(BaseModel):
    # allow_inf_nan=False: ``.inf``, ``.nan`` and overflowing literals (1e400) are errors
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class TissueValues(_Strict):
    """One positive value per tissue (a partial mapping keeps the default's other tissues)."""

    csf: Float = Field(gt=0, description="cerebrospinal fluid")
    gm: Float = Field(gt=0, description="grey matter")
    wm: Float = Field(gt=0, description="white matter")


def _fill_from_defaults(cls, data):
    """A partial mapping given for a field whose default is a model of required values (per
    tissue values; a Beta prior, unless the mapping names tissues) takes the rest from that
    default: ``--set model.initial_lam.gm=5`` or ``initial_lam: {gm: 5}`` keeps the
    default's ``csf`` and ``wm``."""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for name, field in cls.model_fields.items():
        given, default = data.get(name), field.default
        if not isinstance(given, dict):
            continue
        if isinstance(default, TissueValues) or (
                isinstance(default, BetaPrior) and _prior_kind(given) == "beta"):
            out[name] = {**default.model_dump(), **given}
    return out


class DataConfig(_Strict):
    """The images and the label map (paper Sec. 4.1)."""

    source: Literal["mni152", "brainweb", "nifti"] = Field(
        "mni152", description="mni152: the MNI ICBM152 2009a template that ships with nilearn "
        "(T1 and GM/WM probability maps; labels derived from them); brainweb: a BrainWeb "
        "anatomical model (data.subject) and a T1-weighted image made from its labels "
        "(bayesreg.data.datasets.brainweb); nifti: your own images (data.fixed, data.labels, "
        "data.label_coding and, without a synthetic case, data.moving)")
    resolution_mm: Float | None = Field(
        2.0, gt=0, description="resample the images to isotropic voxels of this size (mm; "
        "linear for images, nearest for labels, anti-aliased when downsampling); null keeps "
        "the fixed image's grid.  Default 2 mm; 1 mm (the paper's) for brainweb, where it "
        "must be a multiple of the models' 0.5 mm")
    skull_margin_mm: Float = Field(
        5.0, gt=0, description="width (mm) of the free space around the intracranial tissues, "
        "for every source: every other voxel within it is free (whatever its label: a skull "
        "that touches the brain, scalp, air), every one beyond it is the skull region "
        "(bayesreg.data.labels.free_shell), so the brain can leave the skull and slide along it, "
        "never further.  The images are also padded by four times this on every side, the "
        "labels with skull, so an image edge that cuts the brainstem keeps the constraint")
    subject: Int | Path | None = Field(
        None, description="brainweb: the subject number of a BrainWeb normal model (04, 05, "
        "06, 18, 20, 38, 41-54), found in data.brainweb_dir, or the path of a crisp model file "
        "(MINC or NIfTI, BrainWeb's class labels), relative to the config file's folder")
    brainweb_dir: Path | None = Field(
        None, description="brainweb: the folder holding subjectNN_crisp_v.mnc(.gz); default the "
        "environment variable BAYESREG_BRAINWEB_DIR (the models are not bundled: "
        "https://brainweb.bic.mni.mcgill.ca/brainweb/anatomic_normal_20.html)")
    noise_percent: Float = Field(
        0.0, ge=0, description="brainweb: Rician noise of the T1-weighted image, % of the white "
        "matter's signal (BrainWeb offers 0, 1, 3, 5, 7, 9); seeded by the run's seed")
    fixed: Path | None = Field(None, description="nifti: the pre-operative image f (NIfTI), "
                               "relative to the config file's folder")
    moving: Path | None = Field(None, description="nifti: the intra-operative image m, any grid "
                                "in f's world frame (resampled onto f's grid); required without "
                                "a synthetic case")
    labels: Path | None = Field(None, description="nifti: the label map, any grid in f's world "
                                "frame (resampled onto f's grid, nearest neighbour)")
    label_coding: dict[str, Int | list[Int]] | None = Field(
        None, description="nifti: the label values of each tissue in data.labels, e.g. {csf: 1, "
        "gm: 2, wm: 3, skull: [4, 5]}; the free space and the skull region then follow "
        "data.skull_margin_mm")
    intensity_percentile: Float = Field(
        99.5, gt=0, le=100, description="f and m are divided by this percentile of f inside "
        "the intracranial volume (intensities about [0, 1], so that T_s has image-independent "
        "units)")
    smoothing_mm: Float = Field(
        0.0, ge=0, description="Gaussian sigma (mm) applied to the posterior's copies of f and "
        "m before the SSD; smooths the likelihood surface sampled at the Gauss points")

    @model_validator(mode="before")
    @classmethod
    def _source_resolution(cls, data):
        # BrainWeb's default grid is the paper's 1 mm (its models are 0.5 mm)
        if isinstance(data, dict) and data.get("source") == "brainweb" and "resolution_mm" not in data:
            data = {**data, "resolution_mm": 1.0}
        return data

    @model_validator(mode="after")
    def _source_keys(self):
        own = {"nifti": ("fixed", "moving", "labels", "label_coding"),
               "brainweb": ("subject", "brainweb_dir", "noise_percent")}
        needed = {"nifti": ("fixed", "labels", "label_coding"), "brainweb": ("subject",)}
        missing = [k for k in needed.get(self.source, ()) if getattr(self, k) is None]
        if missing:
            raise ValueError(f"data.source '{self.source}' needs data.{', data.'.join(missing)}")
        for source, keys in own.items():
            if source == self.source:
                continue
            given = [k for k in keys if k in self.model_fields_set and getattr(self, k) is not None
                     and getattr(self, k) != type(self).model_fields[k].default]
            if given:
                raise ValueError(f"data.{', data.'.join(given)} {'is' if len(given) == 1 else 'are'} "
                                 f"only used with data.source: {source} (data.source is "
                                 f"'{self.source}', which brings its own image and labels)")
        if self.source == "brainweb":
            k = (self.resolution_mm or 0.5) / 0.5
            if abs(k - round(k)) > 1e-9:
                raise ValueError(f"data.resolution_mm must be a multiple of 0.5 mm with data.source: "
                                 f"brainweb (its models are 0.5 mm), got {self.resolution_mm}")
        return self


class MeshConfig(_Strict):
    """The tetrahedral mesh of the intracranial volume (fTetWild; paper Sec. 2.1)."""

    edge_length_mm: Float = Field(16.0, gt=0, description="fTetWild's target edge length (mm); "
                                  "with target_nodes, that of the first attempt")
    smoothing_sigma_mm: Float = Field(
        4.0, ge=0, description="Gaussian sigma (mm) applied to the intracranial mask before its "
        "surface is extracted (marching cubes)")
    epsilon: Float = Field(2e-2, gt=0, description="fTetWild's envelope, relative to the "
                           "surface's bounding-box diagonal: how far the mesh surface may depart "
                           "from the extracted one")
    target_nodes: Int | None = Field(
        None, ge=20, description="re-mesh, scaling the edge length, until the node count is within "
        "target_tolerance of this (fTetWild's count at one edge length scatters by several "
        "percent between runs); null: one mesh at edge_length_mm "
        "(bayesreg.mesh.meshing.mesh_brain_sized)")
    target_tolerance: Float = Field(0.05, gt=0, lt=1, description="relative tolerance on target_nodes")
    max_attempts: Int = Field(12, ge=1, description="meshes tried at most for target_nodes (the "
                              "closest is kept, with a warning, when none is within the tolerance)")
    file: Path | None = Field(
        None, description="a tetrahedral mesh to use instead of meshing: any format meshio reads "
        "(e.g. a run's mesh.vtu, to run again on that very mesh: fTetWild is not reproducible), "
        "points in world mm in the images' frame; relative to the config's folder; the element "
        "tissues come from the label map (bayesreg.mesh.tetmesh.read_mesh); excludes target_nodes")

    @model_validator(mode="after")
    def _one_source(self):
        if self.file is not None and self.target_nodes is not None:
            raise ValueError("mesh.file and mesh.target_nodes exclude each other (a given mesh is "
                             "not re-meshed); remove one")
        return self


# keys of the FE truths that a dense truth does not use
_DENSE_UNUSED = ("lam", "mu", "pushed_nodes", "clearance_mm", "tol_mm", "min_volume_ratio", "outside")
_UNUSED_BY = {"bump": _DENSE_UNUSED, "random": _DENSE_UNUSED,
              "field": _DENSE_UNUSED + ("shift_mm", "falloff_mm")}


class SyntheticConfig(_Strict):
    """A synthetic case: ``m`` is ``f`` warped exactly by a known FE deformation (Sec. 4.1)."""

    enabled: bool = Field(True, description="make m from f and a known deformation (the paper's "
                          "experiment); false: register data.moving")
    truth: Literal["constrained", "smooth", "bump", "random", "field"] = Field(
        "constrained", description="constrained: the pushed nodes fixed, every other boundary node "
        "at the minimum elastic energy subject to the skull constraint (paper Sec. 4.1); smooth: "
        "the push fades over the boundary with falloff_mm (no minimisation); both are FE fields "
        "of the lam, mu below.  Truths the model does not make (a dense voxel field, no lam, mu: "
        "the mismatch case): bump, a Gaussian bump of the whole image of peak shift_mm and sd "
        "falloff_mm at the top of the brain toward its centre of gravity "
        "(bayesreg.truth.synthetic.bump_field); random, a smooth random field of the whole "
        "image, white noise smoothed by a Gaussian of sd falloff_mm, largest displacement "
        "shift_mm at the nodes, seeded by the run's seed (bayesreg.truth.synthetic."
        "random_field); field, the displacement field of synthetic.field")
    solenoidal: bool = Field(
        False, description="the random field (truth: random, or the discrepancy_mm added to an "
        "FE truth): the curl of a random vector potential instead, a "
        "divergence-free (volume-preserving) field, as nearly incompressible tissue moves; the "
        "plain random field changes volume by tens of percent, which an FE model fits with "
        "compressible tissue (bayesreg.truth.synthetic.random_field)")
    discrepancy_mm: Float = Field(
        0.0, ge=0, description="FE truths (constrained, smooth): add a smooth random field of "
        "this largest displacement at the nodes (mm; as truth: random, of smoothing sd "
        "discrepancy_length_mm, seeded by the run's seed, volume-preserving with solenoidal) to "
        "the FE field, a part of the shift no FE field makes: the ratios keep their truths, so "
        "the elastography can be checked under mismatch (bayesreg.truth.synthetic."
        "with_discrepancy); 0: none")
    discrepancy_length_mm: Float = Field(
        30.0, gt=0, description="the sd of the Gaussian that smooths the added field's noise, mm")
    field: Path | None = Field(
        None, description="truth: field: a displacement-field NIfTI (ITK/ANTs/Slicer or "
        "bayesreg's displacement_*.nii.gz, fixed to moving: m(x + u(x)) = f(x)) in f's world "
        "frame, resampled onto f's grid (linear; zero beyond its grid); relative to the config "
        "file's folder")
    shift_mm: Float = Field(15.0, gt=0, description="displacement of the pushed nodes toward the "
                            "brain's centre of gravity (bump: the peak displacement; random: the "
                            "largest at the nodes)")
    n_pushed: Int = Field(20, ge=1, description="pushed nodes: the n_pushed boundary nodes with the "
                          "largest world z (top of the head)")
    pushed_nodes: list[Int] | None = Field(None, description="explicit mesh node indices instead")
    falloff_mm: Float = Field(30.0, gt=0, description="smooth truth: the push of the other "
                              "boundary nodes fades as exp(-d^2 / (2 falloff^2)) with their "
                              "distance d to the nearest pushed node; bump: the Gaussian's sd; "
                              "random: the sd of the Gaussian that smooths the noise")
    clearance_mm: Float | None = Field(
        None, ge=0, description="constrained truth: distance (mm) kept in front of the skull's "
        "smooth surface (bayesreg.mesh.constraints; default half a voxel diagonal, so that a "
        "sampler's barrier barely sees the truth's nodes)")
    tol_mm: Float = Field(1e-3, gt=0, description="constrained truth: allowed constraint violation")
    min_volume_ratio: Float = Field(
        0.05, ge=0, lt=1, description="constrained truth: no element may shrink below this "
        "fraction of its rest volume (a CSF element of the paper's stiffness, 1e-6, resists "
        "nothing and would otherwise be crushed through zero volume: an inverted element)")
    outside: Literal["extend", "background"] = Field(
        "extend", description="voxels of m that no deformed element covers: extend, f shifted by "
        "the displacement continued from the nearest boundary nodes (so that trilinear samples "
        "of m near the deformed surface are not blended with a constant); background, 0")
    lam: TissueValues = Field(TissueValues(csf=1e-6, gm=10.0, wm=30.0),
                              description="the truth's Lamé lambda per tissue (paper Sec. 4.1)")
    mu: TissueValues = Field(TissueValues(csf=1e-6, gm=1.0, wm=1.0),
                             description="the truth's Lamé mu per tissue (paper Sec. 4.1)")

    _partial = model_validator(mode="before")(classmethod(_fill_from_defaults))

    @model_validator(mode="before")
    @classmethod
    def _null_unused(cls, data):
        # null removes a key the truth does not use (a config that extends one, --set):
        # lam: null, mu: null for bump and field, also shift_mm: null etc. for field
        if isinstance(data, dict) and isinstance(data.get("truth"), str):
            unused = _UNUSED_BY.get(data["truth"], ())
            data = {k: v for k, v in data.items() if not (k in unused and v is None)}
        return data

    @model_validator(mode="after")
    def _truth_keys(self):
        if (self.truth == "field") != (self.field is not None):
            raise ValueError("synthetic.truth: field and synthetic.field go together (the field "
                             "file is the truth)")
        if self.discrepancy_mm > 0 and self.truth not in ("constrained", "smooth"):
            raise ValueError(f"synthetic.discrepancy_mm adds to an FE truth (constrained, "
                             f"smooth), not to synthetic.truth: {self.truth}")
        if self.solenoidal and self.truth != "random" and self.discrepancy_mm == 0:
            raise ValueError(f"synthetic.solenoidal is for synthetic.truth: random or a "
                             f"synthetic.discrepancy_mm > 0, not {self.truth} alone")
        if self.truth in _UNUSED_BY:
            given = [k for k in _UNUSED_BY[self.truth] if k in self.model_fields_set
                     and getattr(self, k) != type(self).model_fields[k].default]
            if given:
                raise ValueError(f"synthetic.{', synthetic.'.join(given)} {'is' if len(given) == 1 else 'are'}"
                                 f" not used by synthetic.truth: {self.truth} (a dense field the "
                                 "model did not make: no lam, mu); remove "
                                 f"{'it' if len(given) == 1 else 'them'} (null over a config "
                                 "that extends another)")
        return self


class BetaPrior(_Strict):
    """A Beta(a, b) prior scaled to [r1, r2] (paper Sec. 3.1)."""

    a: Float = Field(1.0, gt=0, description="first shape parameter")
    b: Float = Field(1.0, gt=0, description="second shape parameter")
    r1: Float = Field(0.0, ge=0, description="lower end of the support")
    r2: Float = Field(gt=0, description="upper end of the support (> r1)")

    @model_validator(mode="after")
    def _range(self):
        if self.r2 <= self.r1:
            raise ValueError(f"r2 ({self.r2}) must exceed r1 ({self.r1})")
        return self


class GammaPrior(_Strict):
    """A Gamma(shape, rate) prior of a precision (the similarity's 1 / T_s)."""

    shape: Float = Field(gt=0, description="shape a")
    rate: Float = Field(gt=0, description="rate b, in the units of the temperature")


class DiscrepancyPrior(_Strict):
    """The prior of the model discrepancy (``model.discrepancy: interior`` or ``modes``)."""

    shape: Float = Field(1.0, gt=0, description="shape a of the Gamma prior of 1 / T_d (a = 1: "
                         "weakly informative, the images set the amplitude)")
    floor_mm: Float = Field(0.05, gt=0, description="rms per interior node (mm) of the "
                            "discrepancy at the floor of T_d, where the images ask for none: "
                            "sets the Gamma prior's rate b (bayesreg.model.posterior."
                            "discrepancy_rate); well below a voxel")
    modes: int = Field(64, ge=1, description="discrepancy: modes: how many of the smoothest "
                       "eigenmodes of K0_ii the discrepancy spans (capped at 3 n_i; "
                       "bayesreg.model.posterior.smoothest_modes)")
    orthogonal: bool = Field(False, description="the discrepancy displaces the interior only "
                             "K0_ii-orthogonally to the FE interior's sensitivities to the free "
                             "elastic parameters (Plumlee 2017), taken at model.initial_* and "
                             "the mode search's u_b (the central start's without one), the "
                             "search then going on under it: d cannot mimic a change of lam, "
                             "mu, which are then read from the interior's components along "
                             "those sensitivities whatever the discrepancy's spread elsewhere "
                             "(bayesreg.model.posterior.orthogonal_discrepancy).  Needs a start "
                             "that displaces the tissue (init.method: mode or init.start: "
                             "registration) and parameter groups, not one per element (docs: "
                             "Method, measured with sampler.joint: true)")


class TissuePriors(_Strict):
    """A separate scaled Beta prior per tissue (paper Sec. 3.1: priors per compartment)."""

    csf: BetaPrior = Field(description="the prior of the CSF group's parameter")
    gm: BetaPrior = Field(description="the prior of the GM group's parameter")
    wm: BetaPrior = Field(description="the prior of the WM group's parameter")


def _prior_kind(v):
    """Which form of prior ``v`` is: per tissue if it names a tissue, else one Beta prior (so a
    bad value gets the errors of its own form only, not those of both)."""
    if isinstance(v, dict):
        return "per-tissue" if set(v) & {"csf", "gm", "wm"} else "beta"
    if isinstance(v, TissuePriors):
        return "per-tissue"
    return "beta" if isinstance(v, BetaPrior) else None


PRIOR_TAGS = ("beta", "per-tissue")
Prior = Annotated[
    Union[Annotated[BetaPrior, Tag("beta")], Annotated[TissuePriors, Tag("per-tissue")]],
    Discriminator(_prior_kind, custom_error_type="prior_type",
                  custom_error_message="Input should be a prior {a, b, r1, r2} or per-tissue "
                  "priors {csf: {...}, gm: {...}, wm: {...}}"),
]


class FixedParam(_Strict):
    """An elastic parameter held fixed (paper Sec. 3.3: one fixed value pins the scale)."""

    param: Literal["lam", "mu"] = Field("mu", description="which Lamé parameter")
    group: str = Field("gm", description="its group: csf, gm or wm (elastic: tissue), all "
                       "(uniform), eK (element K)")
    value: Float = Field(1.0, gt=0, description="its value")


class LNCCConfig(_Strict):
    """The local normalised cross-correlation term (model.similarity: lncc)."""

    window_mm: Float = Field(9.0, gt=0, description="side of the windows' cubes (mm), laid every "
                             "window_mm / 2 over the quadrature points (ANTs' CC radius r at "
                             "spacing h: (2r + 1) h)")
    t_s: Float = Field(8.0, gt=0, description="temperature of the LNCC term, in mm^3 (its value "
                       "is sum_k W_k (1 - rho_k^2), windows weighted by their volume / 8); the "
                       "default gives the Gauss-Newton curvature that SSD has at t_s 0.1 on the "
                       "quickstart's truth with 9 mm windows")
    eps: Float = Field(1e-4, gt=0, description="variance floor of a window (intensity^2, "
                       "intensities scaled to about [0, 1]): keeps the term smooth where the "
                       "image is flat")


class ModelConfig(_Strict):
    """The posterior (paper Eqs. 8-12): elastic parameterisation, temperatures, priors."""

    similarity: Literal["ssd", "lncc"] = Field(
        "ssd", description="the similarity term E_s: ssd (the paper's sum of squared differences, "
        "Eq. 1, temperature t_s) or lncc (local normalised cross-correlation, ANTs' CC: blind "
        "to an intensity change that is affine within a window, such as a bias field or "
        "another contrast; settings and temperature under lncc)")
    lncc: LNCCConfig = Field(LNCCConfig(), description="the LNCC term (similarity: lncc)")

    elastic: Literal["uniform", "tissue", "element"] = Field(
        "tissue", description="groups of elements sharing Lamé parameters: uniform (one pair), "
        "tissue (one pair per tissue: CSF, GM, WM, the paper's three-compartment model), "
        "element (one pair per element)")
    t_s: Float = Field(0.1, gt=0, description="similarity temperature T_s (Eq. 11), in "
                       "intensity^2 mm^3")
    t_s_prior: GammaPrior | None = Field(
        None, description="the similarity temperature as a parameter: a Gamma(shape, rate) prior "
        "on 1 / T_s, integrated out (Risholm et al. 2013), so exp(-E_s / T_s) becomes "
        "(1 + E_s / rate)^-(shape + n_q / 2) with n_q quadrature points: a misfit the model "
        "cannot explain widens the posterior instead of bending the elastic parameters; t_s "
        "then only seeds the preconditioners.  null: T_s = t_s")
    t_r: Float = Field(3.0, gt=0, description="elastic temperature T_r (Eq. 12), in [lam] mm^3")
    prior_lam: Prior = Field(BetaPrior(r2=100.0), description="prior of every free lambda: "
                             "{a, b, r1, r2}, or one per tissue {csf: {...}, gm: {...}, wm: {...}} "
                             "(elastic: tissue)")
    prior_mu: Prior = Field(BetaPrior(r2=10.0), description="prior of every free mu, as "
                            "prior_lam")
    skull_barrier_mm: Float = Field(
        1.0, ge=0, description="width w (mm) of a smooth barrier -sum (w/s - 1)^3 over nodes at "
        "clearance s < w from the skull's smooth surface (bayesreg.mesh.constraints: the one signed "
        "distance of the truth, the mode search and the sampler), added to the log-density: gradient "
        "trajectories turn before the hard constraint, which stays in place either way; 0: "
        "off, the paper's hard constraint alone (the paper's configs)")
    quadrature_level: Int = Field(
        1, ge=0, le=3, description="quadrature of E_s (Eq. 1): 0, the paper's 4 Gauss points per "
        "tetrahedron; k, the same rule in each of the 8^k children of k red refinements "
        "(4 * 8^k points, up to 8^k times the cost of E_s).  Four points per element alias an "
        "image of finer voxels into local modes of the boundary nodes; level 1 removes most "
        "of them (the paper's configs keep 0, the paper's rule)")
    interpolation: Literal["linear", "cubic"] = Field(
        "linear", description="how E_s (Eq. 1) reads the images at the quadrature points: "
        "linear (trilinear, the paper's: the gradient of E_s jumps at every voxel face, where "
        "the tissue edges hold the information) or cubic (B-spline with its prefilter, C2: a "
        "smooth potential for the gradient samplers, several times the cost per point)")
    moving_dtype: Literal["float32", "float64"] = Field(
        "float32", description="storage precision of the moving image m that E_s (Eq. 1) "
        "samples: float32 rounds its values once (relative 2^-24) and halves the bytes that "
        "each evaluation gathers from; the interpolation and E_s stay float64.  float64: m "
        "exactly as given")
    fixed: FixedParam | None = Field(FixedParam(), description="a parameter held fixed (paper "
                                     "Sec. 3.3: mu of GM = 1 pins the scale); null: every "
                                     "parameter free (with prior_normaliser: exact)")
    prior_normaliser: Literal["paper", "exact"] = Field(
        "exact", description="exact: the elastic prior on u_b carries its normaliser "
        "(1/2) log pdet S(lam, mu) (S the Schur complement on the boundary DOFs; two sparse "
        "Cholesky factorisations per change of lam, mu; joint trajectories see a smooth "
        "surrogate of it, corrected to the exact posterior once per transition), which removes "
        "the paper's drift of the parameters toward zero (its 90% intervals held 0-1% of "
        "the ratio truths in bayesreg calibrate) and lets every parameter be free; paper: "
        "Eq. 12 as published, without it (then fix one parameter, Sec. 3.3)")
    interior: Literal["solve", "sample"] = Field(
        "solve", description="solve: the interior nodes at the FE solve K_ii u_i = -K_ib u_b, "
        "only boundary nodes sampled (paper Sec. 3.3: the interior at its conditional mean "
        "under the elastic prior); sample: every node sampled, the interior under the same "
        "elastic prior exp(-E_r / T_r) (given the boundary, N(-K_ii^-1 K_ib u_b, T_r K_ii^-1)) "
        "and moved by the images, so that deformations the FE solve cannot make (a bump, "
        "real brain shift) are reachable, but the images then no longer identify the ratios "
        "(the interior's obeying the FE solve is what carries them); needs prior_normaliser: "
        "exact (the normaliser of the whole K)")
    discrepancy: Literal["none", "interior", "modes"] = Field(
        "none", description="none: the paper's model, the interior at the FE solve; interior: "
        "a model discrepancy (Kennedy and O'Hagan 2001), u_i = -K_ii^-1 K_ib u_b + d with d "
        "sampled under N(0, T_d K0_ii^-1) (K0 at the start's parameters, model.initial_*, "
        "fixed: d says nothing of lam, mu) and its amplitude T_d learned (a Gamma prior on "
        "1 / T_d, integrated out: a Student t), so that what the FE model cannot make (a "
        "bump, real brain shift) goes into d while the elastic parameters keep what it can; "
        "the report maps |d| (bayesreg.model.posterior.Discrepancy); modes: the same prior "
        "restricted to the discrepancy_prior.modes smoothest eigenmodes of K0_ii (a truncated "
        "Karhunen-Loeve expansion), so that a smooth shift is representable while the "
        "interior's finer pattern still follows the FE solve.  Needs interior: solve "
        "and a gradient sampler (nuts, hmc, mala) without collapsed moves")
    discrepancy_prior: DiscrepancyPrior = Field(
        DiscrepancyPrior(), description="prior of the discrepancy (discrepancy: interior or "
        "modes)")
    initial_lam: TissueValues = Field(TissueValues(csf=1.0, gm=5.0, wm=5.0),
                                      description="the chains' central start of lambda per tissue "
                                      "(uniform: their volume-weighted mean)")
    initial_mu: TissueValues = Field(TissueValues(csf=1.0, gm=1.0, wm=1.0),
                                     description="the chains' central start of mu per tissue")

    _partial = model_validator(mode="before")(classmethod(_fill_from_defaults))

    @model_validator(mode="after")
    def _similarity(self):
        if self.similarity != "ssd" and self.t_s_prior is not None:
            raise ValueError("model.t_s_prior (the SSD's noise precision integrated out) needs "
                             "model.similarity: ssd")
        return self


class SolverConfig(_Strict):
    """The interior FE solve K_ii u_i = -K_ib u_b (preconditioned CG, float64)."""

    rtol: Float = Field(1e-8, gt=0, lt=1, description="relative residual at which CG stops; a "
                        "solve that does not reach it rejects its proposal (counted in run.json)")
    maxiter: Int = Field(1000, ge=1, description="CG iterations at most per solve")
    preconditioner: Literal["auto", "dense", "spectral", "block-jacobi"] = Field(
        "auto", description="CG preconditioner of the interior solves (the random walks', "
        "the gradient kernels' elastic moves', the mode search's): spectral (one parameter "
        "group only, model.elastic: uniform: the generalised eigenvectors of the unit "
        "stiffness blocks, K_ii^-1 exact at every lam, mu, one float32 basis for all chains: "
        "one or two CG iterations per solve; where 3 n_i > 4096 block-jacobi instead, as run.json "
        "reports), dense (K_ii^-1 in float32 at each chain's parameters, rebuilt at every "
        "chunk start: a few CG iterations instead of a hundred), block-jacobi (3x3 blocks, no "
        "memory), or auto: spectral for one group and "
        "dense for more where 3 n_i <= 4096 (and, for dense, the chains' inverses, 4 (3 n_i)^2 "
        "bytes each, take at most 2 GiB on a CPU, a sixteenth of an accelerator's memory, "
        "at least 2 GiB), else block-jacobi.  Any choice meets the same "
        "tolerance (rtol): the posterior does not depend on it")


class SamplerConfig(_Strict):
    """The chains: kernel, warm-up, draws, stopping rule (paper Sec. 3.2)."""

    kind: Literal["rwmh", "mala", "hmc", "nuts"] = Field(
        "nuts", description="kernel of u_b: rwmh (the paper's random walk; blocked or joint), or a "
        "gradient kernel in Gibbs with a random walk of the elastic parameters in their "
        "unconstrained (logit) space: mala, hmc, nuts (BlackJAX; windowed warm-up); the "
        "paper's configs say rwmh")
    chains: Int = Field(3, ge=2, description="parallel chains (dispersed starts; at least 2 "
                        "for R-hat)")
    chain_method: Literal["auto", "vectorized", "sequential", "threads", "pieces"] = Field(
        "auto", description="how the chains run (bayesreg.sampling.chains; the draws do not depend on "
        "it): vectorized (vmap, the default on an accelerator), sequential, threads (groups of "
        "chains in host threads), pieces (pieces of chains, one worker per core, where the "
        "chains do not split evenly over the cores; random walk only); auto chooses")
    thinning: Int | None = Field(None, ge=1, description="keep every n-th step; default 10 (rwmh), "
                                 "1 (gradient kernels)")
    warmup_steps: Int | None = Field(None, ge=0, description="steps per chain before the stored "
                                     "draws; default 2000 (rwmh), 500 (gradient kernels)")
    max_draws: Int = Field(2000, ge=1, description="stored draws per chain at most (after the "
                           "warm-up and thinning), counted in whole chunks")
    min_draws: Int = Field(100, ge=2, description="stored draws per chain before the R-hat "
                           "stop may apply")
    chunk_draws: Int = Field(50, ge=2, description="draws per compiled chunk: the interval of "
                             "the R-hat check, the progress bar and the checkpoint")
    target_acceptance: Float | None = Field(
        None, gt=0, lt=1, description="warm-up target of the u_b kernel's acceptance; default 0.25 "
        "(rwmh), 0.57 (mala), 0.8 (hmc, nuts)")
    stop: Literal["rank", "paper"] = Field(
        "rank", description="stop rule, checked after each chunk from min_draws on, over every "
        "estimand (each boundary coordinate, free parameter and lam/mu ratio): rank, the "
        "rank-normalised split R-hat at most rhat_rank_max and bulk and tail ESS at least "
        "ess_min (Vehtari et al. 2021; ArviZ's and Stan's defaults); paper, the classic "
        "Gelman-Rubin R-hat below rhat_threshold (Sec. 3.2; the paper's configs)")
    rhat_rank_max: Float = Field(1.01, gt=1, description="stop: rank, the largest rank-normalised "
                                 "split R-hat allowed")
    ess_min: Float = Field(400.0, gt=0, description="stop: rank, the smallest bulk and tail "
                           "effective sample size allowed")
    rhat_threshold: Float = Field(1.2, gt=1, description="stop: paper, stop once the classic "
                                  "Gelman-Rubin R-hat of every estimand is below this (paper: "
                                  "1.2); recorded under either rule")
    rhat_split: bool = Field(
        False, description="stop: paper, monitor the split-chain Gelman-Rubin R-hat (catches a "
        "common drift) instead of the paper's whole-chain one")
    blocked: bool = Field(
        True, description="update u_b and the elastic parameters in turn (Metropolis-within-"
        "Gibbs, each block with its own tuned scale); false: the paper's joint proposal")
    condensed: bool | None = Field(
        None, description="moves of u_b take the interior from a cached dense condensation "
        "u_i = H(lam, mu) u_b (one mat-vec instead of a CG solve), rebuilt after each accepted "
        "elastic move; memory 72 n_i n_b bytes per chain (paper size ~12 MB); rwmh: blocked "
        "only, default false; gradient kernels: default true")
    u_moves: Int = Field(
        1, ge=1, description="condensed only: updates of u_b per step (the cheap moves that "
        "amortise one rebuild of the condensation)")
    proposal: Literal["laplace", "isotropic"] = Field(
        "laplace", description="shape of u_b's proposal (rwmh) or coordinates (gradient "
        "kernels): laplace, whitened by the Gauss-Newton precision of u_b at the central start "
        "(or the mode); isotropic, the paper's sigma_u (rwmh) or 1 mm")
    sigma_u: Float = Field(0.008, gt=0, description="rwmh, isotropic: initial jumping-kernel "
                           "sd of each boundary coordinate, mm (Eq. 14; adapted in the warm-up)")
    sigma_lam: Float = Field(0.5, gt=0, description="rwmh: initial jumping-kernel sd of each "
                             "free lambda (adapted)")
    sigma_mu: Float = Field(0.05, gt=0, description="rwmh: initial jumping-kernel sd of each "
                            "free mu (adapted)")
    step_size: Float = Field(0.1, gt=0, description="gradient kernels: initial leapfrog step in the "
                             "preconditioned coordinates (adapted in the warm-up)")
    hmc_steps: Int = Field(16, ge=1, description="hmc: leapfrog steps per transition (the mean "
                           "number with hmc_jitter)")
    hmc_jitter: bool = Field(True, description="hmc: draw each transition's number of leapfrog "
                             "steps uniformly from 1 .. 2 hmc_steps - 1 (a fixed length can make "
                             "trajectories nearly periodic: antithetic draws, a high tail R-hat)")
    max_tree_depth: Int = Field(6, ge=1, le=15, description="nuts: maximum trajectory doublings "
                                "(at most 2^depth - 1 gradients per transition)")
    dense_mass: bool = Field(False, description="gradient kernels: adapt a dense inverse mass "
                             "matrix instead of a diagonal one")
    adapt_mass: bool = Field(True, description="gradient kernels: adapt the inverse mass matrix in "
                             "the warm-up windows; false: identity in the Laplace-preconditioned "
                             "coordinates, step size alone adapted")
    joint: bool | None = Field(
        None, description="gradient kernels: move u_b and the free elastic parameters (their "
        "logits) together in one trajectory, through the interior solve with implicit "
        "differentiation; false: Gibbs, the trajectory moves u_b and elastic_moves random-walk "
        "moves the parameters.  Default: true (on the quickstart 2.4-3x the effective draws "
        "per second of Gibbs), but false with collapsed_moves and for the per-element model "
        "under the exact normaliser (which has no surrogate there)")
    normaliser_surrogate: Literal["auto", "warmup", "start"] = Field(
        "auto", description="joint gradient kernels under prior_normaliser: exact: where the "
        "trajectories' smooth surrogate of the normaliser is built (each transition's "
        "Metropolis correction keeps the chains exact either way).  start: at the starts' "
        "centre (the mode; the correction rejects much where the mode's parameters sit on "
        "their prior's margin and the chains do not); warmup: rebuilt after the warm-up at "
        "the chains' median parameters (one more compilation of the sampling program); auto: "
        "rebuilt as warmup where the correction spans more than 1 nat over the chains' "
        "positions, else kept")
    elastic_moves: Int = Field(8, ge=1, description="gradient kernels: random-walk updates of the "
                               "elastic parameters per transition (cheap next to a trajectory)")
    collapsed_moves: Int = Field(0, ge=0, description="gradient kernels: "
                                 "collapsed moves of the elastic parameters per transition, which "
                                 "carry u_b (with a model discrepancy [u_b, d]) along (carry): "
                                 "they move the "
                                 "parameters as if u_b were integrated out, where random-walk "
                                 "moves given u_b barely move them")
    carry: Literal["conditional", "displacement"] | None = Field(
        None, description="how collapsed_moves carry the displacement along: conditional, by "
        "its Laplace approximation given the parameters (one dense factorisation per move; "
        "needs proposal laplace); displacement (with a model discrepancy): u_b stays and the "
        "discrepancy takes up the FE interior's change, so every node's displacement stays "
        "(one more interior solve per move, no factorisation; the parameters given u instead "
        "of given [u_b, d]).  Default: displacement with a model discrepancy, else conditional")
    sigma_eta: Float = Field(0.1, gt=0, description="gradient kernels: initial scale of the elastic "
                             "random walk in the unconstrained (logit) space (adapted); with "
                             "joint, the logits' unit in the trajectory's coordinates")

    @model_validator(mode="after")
    def _collapsed(self):
        if self.collapsed_moves and not self.gradient:
            raise ValueError("sampler.collapsed_moves needs a gradient kernel (mala, hmc, nuts)")
        if self.joint and not self.gradient:
            raise ValueError("sampler.joint needs a gradient kernel (mala, hmc, nuts): rwmh's "
                             "blocked: false is the paper's joint proposal")
        if self.collapsed_moves and self.joint:
            raise ValueError("sampler.collapsed_moves needs sampler.joint: false (joint "
                             "trajectories already move the parameters with u_b)")
        return self

    @model_validator(mode="after")
    def _draws(self):
        # sampling runs whole chunks until max_draws (sampler._drive): a chunk beyond
        # max_draws overshoots it, and min_draws beyond it never applies
        for key in ("min_draws", "chunk_draws"):
            if getattr(self, key) > self.max_draws:
                raise ValueError(f"sampler.{key} ({getattr(self, key)}) must not exceed "
                                 f"sampler.max_draws ({self.max_draws})")
        return self

    @model_validator(mode="after")
    def _per_kind_defaults(self):
        # filled in without marking the keys as given (no assignment): a config re-validated
        # from its given keys (``model_dump(exclude_unset=True)``, as ``bayesreg.run`` does
        # with overrides) then takes the defaults of its new kind
        if self.thinning is None:
            self.__dict__["thinning"] = 1 if self.gradient else 10
        if self.warmup_steps is None:
            self.__dict__["warmup_steps"] = 500 if self.gradient else 2000
        return self

    @property
    def gradient(self) -> bool:
        return self.kind != "rwmh"

    @property
    def use_condensed(self) -> bool:
        return self.gradient if self.condensed is None else self.condensed


class InitConfig(_Strict):
    """Where the chains start (paper Sec. 4.2) and the mode search."""

    start: Literal["between", "registration"] = Field(
        "between",
        description="central start of u_b: between: fraction * truth (paper Sec. 4.2, synthetic "
        "cases only); registration: a fast registration of f to m (scikit-image optical flow) "
        "sampled at the boundary nodes")
    method: Literal["perturb", "mode"] = Field(
        "perturb",
        description="perturb: chains at the central start plus Gaussian jitter perturb_mm; mode: "
        "maximise the posterior from the central start (L-BFGS, optax) and start the chains "
        "overdispersed around the mode",
    )
    fraction: Float = Field(0.5, ge=0, le=1, description="between: start at fraction * truth")
    registration: Literal["tvl1", "ilk"] = Field(
        "tvl1", description="registration: skimage.registration.optical_flow_<method>")
    perturb_mm: Float = Field(0.5, ge=0, description="perturb: per-chain Gaussian jitter, mm")
    overdispersion: Float = Field(
        2.0, ge=0, description="mode: chains start at mode + overdispersion * Laplace draw"
    )
    optimizer_iterations: Int = Field(1000, ge=1, description="mode: L-BFGS iterations of "
                                      "the mode search in all")
    optimize_parameters: bool = Field(
        True, description="mode: optimise the free elastic parameters jointly with u_b")
    param_jitter: Float = Field(0.2, ge=0, description="log-normal sd of start parameters")


class OutputConfig(_Strict):
    """The run directory."""

    dir: Path = Field(Path("runs/run"), description="the run directory (the CLI's --out "
                      "overrides it)")
    overwrite: bool = Field(False, description="replace an existing run directory that "
                            "bayesreg wrote (the CLI's --overwrite)")
    progress: bool = Field(True, description="show progress bars (tqdm); the one line per "
                           "finished stage (bayesreg: mesh done ...) is printed either way")
    reference: Annotated[Literal["tvl1", "ilk", "syn", "none"], BeforeValidator(
            lambda v: ({True: "tvl1", False: "none"}[v] if isinstance(v, bool) else v))] = Field(
        "tvl1", description="synthetic runs: also register f to m and report that field beside "
        "the posterior mean, the point estimate to beat (displacement_reference.nii.gz; "
        "errors.json: brain, boundary_reference_mm; the printed table): tvl1 or ilk, "
        "scikit-image's optical flow (seconds at 2 mm, about a minute at 1 mm); syn, ANTs SyN "
        "through ANTsPy (antspyx, an optional dependency; bayesreg.interop.syn: the deformable "
        "stage of antsRegistrationSyNQuick.sh with its finest level); none.  true and "
        "false (earlier versions) read as tvl1 and none")
    checkpoint: bool = Field(
        True, description="write the draws chunk by chunk and the sampler state after each chunk "
        "(checkpoint/ in the run directory), so that a killed run keeps its draws and "
        "`bayesreg run --resume RUN_DIR` continues it")


class Config(_Strict):
    """A whole run: every key's default, meaning and checks (the documentation's configuration
    reference lists them); ``configs/quickstart.yaml`` is a commented example of the common
    ones.

    Examples
    --------
    >>> from bayesreg import Config
    >>> cfg = Config.model_validate({"sampler": {"kind": "rwmh"}})
    >>> cfg.sampler.thinning, cfg.sampler.warmup_steps  # the random walk's defaults
    (10, 2000)
    """

    name: str = Field("run", description="a name recorded in run.json and posterior.nc")
    seed: Int = Field(0, ge=0, lt=2**32, description="seed of NumPy's and JAX's generators")
    data: DataConfig = Field(DataConfig(), description="images and labels")
    mesh: MeshConfig = Field(MeshConfig(), description="the FE mesh")
    synthetic: SyntheticConfig = Field(SyntheticConfig(), description="a synthetic case with "
                                       "known truth")
    model: ModelConfig = Field(ModelConfig(), description="the posterior")
    solver: SolverConfig = Field(SolverConfig(), description="the interior FE solve")
    sampler: SamplerConfig = Field(SamplerConfig(), description="the chains")
    init: InitConfig = Field(InitConfig(), description="the starts")
    output: OutputConfig = Field(OutputConfig(), description="the run directory")

    @model_validator(mode="after")
    def _consistent(self):
        groups = {"uniform": ["all"], "tissue": ["csf", "gm", "wm"], "element": None}[
            self.model.elastic
        ]
        if self.model.fixed is not None and groups is not None and self.model.fixed.group not in groups:
            raise ValueError(
                f"model.fixed.group '{self.model.fixed.group}' is not a group of elastic "
                f"'{self.model.elastic}' (groups: {groups})"
            )
        if self.sampler.condensed and not self.sampler.blocked and not self.sampler.gradient:
            raise ValueError("sampler.condensed needs sampler.blocked: true (the joint proposal "
                             "changes lam, mu at every step)")
        if self.sampler.chain_method == "pieces" and self.sampler.gradient:
            raise ValueError("sampler.chain_method: pieces needs kind: rwmh (a gradient kernel's "
                             "chunk cannot be cut into pieces); use threads or auto")
        if self.sampler.u_moves > 1 and (not self.sampler.condensed or self.sampler.gradient):
            raise ValueError("sampler.u_moves > 1 needs sampler.condensed: true and kind: rwmh")
        if self.solver.preconditioner == "spectral" and self.model.elastic != "uniform":
            raise ValueError("solver.preconditioner: spectral needs one parameter group "
                             f"(model.elastic: uniform), got model.elastic: {self.model.elastic}")
        for key in ("prior_lam", "prior_mu"):
            if isinstance(getattr(self.model, key), TissuePriors) and self.model.elastic != "tissue":
                raise ValueError(f"model.{key}: per-tissue priors need elastic: tissue")
        if not self.synthetic.enabled and self.data.moving is None:
            raise ValueError("without synthetic.enabled, data.moving (the image m) is required"
                             + (" (with data.source: nifti)" if self.data.source != "nifti" else ""))
        if self.synthetic.enabled and self.data.moving is not None:
            raise ValueError("data.moving is not used with synthetic.enabled: true (m is f warped "
                             "by the synthetic deformation); remove it or set synthetic.enabled: "
                             "false")
        if self.model.interior == "sample" and self.model.prior_normaliser != "exact":
            raise ValueError("model.interior: sample needs model.prior_normaliser: exact (with "
                             "every node sampled, the paper's unnormalised prior drives the "
                             "free parameters to zero)")
        if self.model.discrepancy != "none":
            which = f"model.discrepancy: {self.model.discrepancy}"
            if self.model.interior != "solve":
                raise ValueError(f"{which} needs model.interior: solve (the "
                                 "discrepancy is the interior's deviation from the FE solve)")
            if not self.sampler.gradient:
                raise ValueError(f"{which} needs a gradient sampler "
                                 "(sampler.kind: nuts, hmc or mala): it samples the interior's "
                                 "deviation too")
            if self.model.discrepancy_prior.orthogonal and self.model.elastic == "element":
                raise ValueError("model.discrepancy_prior.orthogonal removes one direction per "
                                 "free parameter: it needs parameter groups (model.elastic: "
                                 "tissue or uniform), not one per element")
        elif self.model.discrepancy_prior.orthogonal:
            raise ValueError("model.discrepancy_prior.orthogonal needs a model discrepancy "
                             "(model.discrepancy: interior or modes)")
        elif self.sampler.collapsed_moves and self.sampler.carry == "displacement":
            raise ValueError("sampler.carry: displacement needs a model discrepancy "
                             "(model.discrepancy: interior or modes), which takes up the FE "
                             "interior's change; use carry: conditional")
        if (self.sampler.collapsed_moves and self.collapsed_carry == "conditional"
                and self.sampler.proposal != "laplace"):
            raise ValueError("sampler.collapsed_moves with carry: conditional needs "
                             "sampler.proposal: laplace (the likelihood's Gauss-Newton curvature)")
        self._initial_in_support()
        if self.init.start == "between" and not self.synthetic.enabled and self.init.fraction > 0:
            raise ValueError("init.start 'between' needs a synthetic truth (synthetic.enabled); "
                             "use init.start: registration for real data")
        return self

    @property
    def collapsed_carry(self) -> str:
        """``sampler.carry`` with its default filled in: ``"displacement"`` with a model
        discrepancy, else ``"conditional"``."""
        if self.sampler.carry is not None:
            return self.sampler.carry
        return "displacement" if self.model.discrepancy != "none" else "conditional"

    def _initial_in_support(self):
        """The start of each free elastic parameter (``model.initial_*``) must lie strictly
        inside its prior's support ``(r1, r2)`` (the posterior refuses it after meshing).

        Per tissue: each tissue's value against its prior (``model.prior_*`` or its tissue's
        entry); ``elastic: uniform`` starts at the volume-weighted mean of the tissues' values,
        known only after meshing, so each value must lie inside; ``element``: each element
        starts at its tissue's value.  The fixed parameter (``model.fixed``) is not free: its
        tissue is skipped (uniform: the whole parameter)."""
        m = self.model
        for p in ("lam", "mu"):
            prior = getattr(m, f"prior_{p}")
            initial = getattr(m, f"initial_{p}")
            for t in ("csf", "gm", "wm"):
                if m.fixed is not None and m.fixed.param == p and (
                        (m.elastic == "tissue" and m.fixed.group == t)
                        or (m.elastic == "uniform" and m.fixed.group == "all")):
                    continue
                pr, key = prior, f"model.prior_{p}"
                if isinstance(prior, TissuePriors):
                    pr, key = getattr(prior, t), f"model.prior_{p}.{t}"
                v = getattr(initial, t)
                if not pr.r1 < v < pr.r2:
                    raise ValueError(
                        f"model.initial_{p}.{t} ({v:g}) must lie strictly inside the support "
                        f"({pr.r1:g}, {pr.r2:g}) of {key}"
                        + (" (elastic: uniform starts at the volume-weighted mean of the "
                           "tissues' values)" if m.elastic == "uniform" else ""))


