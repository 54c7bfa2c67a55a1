"""Images: NIfTI I/O and world frames, resampling onto other grids, padding."""

import numpy as np
import pytest

from bayesreg.data.images import (
    Image,
    check_same_frame,
    check_same_space,
    interpolate_numpy,
    load_nifti,
    nifti_frame,
    pad,
    resample,
    resample_to_spacing,
    save_nifti,
    to_reference_grid,
)
from helpers import smooth_image


def test_check_same_space_names_the_problem():
    a = smooth_image()
    b = Image(a.data, a.affine + np.diag([0, 0, 0.5, 0]))
    with pytest.raises(ValueError, match="affines disagree"):
        check_same_space(a, b)
    with pytest.raises(ValueError, match="different grids"):
        check_same_space(a, Image(a.data[:-1], a.affine))


def test_pad_and_resample_keep_world_frame():
    img = smooth_image()
    p = pad(img, 3.0)
    pts = np.array([[1.0, 2.0, 3.0], [10.5, -2.0, 7.25]])
    np.testing.assert_allclose(interpolate_numpy(p, pts), interpolate_numpy(img, pts), atol=1e-12)
    r = resample_to_spacing(img, 2.0)
    assert np.allclose(r.spacing, 2.0)
    np.testing.assert_allclose(interpolate_numpy(r, pts), interpolate_numpy(img, pts), atol=0.1)


def _world_points(affine, shape):
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    return ijk @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3]


def _rot(angles):
    a, b, c = angles
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def test_to_reference_grid_same_grid_is_identity():
    f = smooth_image()
    lab = Image(np.arange(40**3).reshape(40, 40, 40), f.affine + 1e-5)
    assert to_reference_grid(lab, f, name="labels", reference_name="f", order=0) is lab


def test_to_reference_grid_labels_nearest_neighbour():
    f = smooth_image(shape=(30, 30, 30), origin=0.0)  # 1 mm voxels, origin 0
    coarse = np.diag([2.0, 2.0, 2.0, 1.0])
    coarse[:3, 3] = [0.3, -0.7, 1.1]  # no fine voxel centre lies on a coarse voxel boundary
    rng = np.random.default_rng(1)
    data = rng.integers(0, 5, size=(15, 16, 14)).astype(np.int16)
    out = to_reference_grid(Image(data, coarse), f, name="labels", reference_name="f", order=0)
    assert out.data.shape == f.data.shape and out.data.dtype == np.int16
    np.testing.assert_array_equal(out.affine, f.affine)
    # nearest coarse voxel, by its extent (centre +- 1 mm); 0 outside the coarse grid
    idx = np.rint((_world_points(f.affine, f.data.shape) - coarse[:3, 3]) / 2.0).astype(int)
    ok = np.all((idx >= 0) & (idx < np.array(data.shape)), axis=-1)
    assert 0.5 < ok.mean() < 1.0
    want = np.zeros(f.data.shape, np.int16)
    want[ok] = data[tuple(idx[ok].T)]
    np.testing.assert_array_equal(out.data, want)


def test_to_reference_grid_linear_intensity_oblique():
    f = smooth_image(shape=(24, 22, 20), origin=0.0)
    g = np.array([0.3, -1.2, 0.7])
    aff = np.eye(4)
    aff[:3, :3] = _rot((0.2, -0.3, 0.5)) @ np.diag([1.7, 0.9, 1.3])
    aff[:3, 3] = [12.0, -11.4, -21.5]  # f's grid partly outside the source grid
    src_shape = (36, 40, 32)
    src = Image(_world_points(aff, src_shape) @ g + 5.0, aff)
    out = to_reference_grid(src, f, name="m", reference_name="f", order=1)
    world = _world_points(f.affine, f.data.shape)
    c = (world - aff[:3, 3]) @ np.linalg.inv(aff[:3, :3]).T
    inside = np.all((c >= 0) & (c <= np.array(src_shape) - 1), axis=-1)
    assert 0.5 < inside.mean() < 0.95
    np.testing.assert_allclose(out.data[inside], world[inside] @ g + 5.0, atol=1e-6)
    # a vector image: each world component resampled the same way
    vec = Image(np.stack([src.data, 2 * src.data, -src.data], -1), aff)
    vout = to_reference_grid(vec, f, name="u", reference_name="f", order=1)
    assert vout.data.shape == f.data.shape + (3,)
    np.testing.assert_allclose(vout.data[inside], (world[inside] @ g + 5.0)[:, None] * [1, 2, -1],
                               atol=1e-6)


def test_to_reference_grid_flipped_axis_same_world_content():
    f = smooth_image(shape=(20, 18, 16), origin=-3.0)
    flipped_aff = f.affine.copy()
    flipped_aff[:3, 1] = -f.affine[:3, 1]  # j runs the other way ...
    flipped_aff[:3, 3] = f.affine[:3, :3] @ [0, f.data.shape[1] - 1, 0] + f.affine[:3, 3]
    flipped = Image(f.data[:, ::-1, :].copy(), flipped_aff)  # ... over the same world points
    out = to_reference_grid(flipped, f, name="m", reference_name="f", order=1)
    np.testing.assert_allclose(out.data, f.data, atol=1e-10)
    lab = Image((f.data > 0).astype(np.uint8)[:, ::-1, :].copy(), flipped_aff)
    np.testing.assert_array_equal(
        to_reference_grid(lab, f, name="labels", reference_name="f", order=0).data, f.data > 0)


def test_to_reference_grid_refuses_disjoint_world_boxes():
    f = smooth_image()
    far = f.affine.copy()
    far[:3, 3] += [200.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="world frame") as err:
        to_reference_grid(Image(f.data, far), f, name="data.labels", reference_name="data.fixed",
                          order=0)
    assert "data.labels" in str(err.value) and "data.fixed" in str(err.value)
    # a partial overlap above min_overlap is accepted
    near = f.affine.copy()
    near[:3, 3] += [10.0, 0.0, 0.0]
    to_reference_grid(Image(f.data, near), f, name="m", reference_name="f", order=1)


def test_load_nifti_refuses_qform_sform_disagreement(tmp_path):
    nib = pytest.importorskip("nibabel")
    data = np.zeros((4, 5, 6), np.float32)
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    shifted = aff.copy()
    shifted[0, 3] = 5.0
    bad = nib.Nifti1Image(data, aff)
    bad.set_qform(shifted, code=1)
    bad.set_sform(aff, code=1)
    nib.save(bad, tmp_path / "bad.nii.gz")
    with pytest.raises(ValueError, match="qform and sform disagree") as err:
        load_nifti(tmp_path / "bad.nii.gz")
    assert "bad.nii.gz" in str(err.value)
    good = nib.Nifti1Image(data, aff)
    good.set_qform(aff, code=1)
    good.set_sform(aff, code=1)
    nib.save(good, tmp_path / "good.nii")
    np.testing.assert_allclose(load_nifti(tmp_path / "good.nii").affine, aff)
    # a disagreeing qform with code 0 is ignored (nibabel uses the sform)
    bad.set_qform(shifted, code=0)
    nib.save(bad, tmp_path / "q0.nii")
    np.testing.assert_allclose(load_nifti(tmp_path / "q0.nii").affine, aff)


def test_frames_scanner_vs_mni_refused(tmp_path):
    nib = pytest.importorskip("nibabel")
    data = np.zeros((4, 5, 6), np.float32)
    paths = {}
    for frame in ("scanner", "aligned", "mni", "unknown"):
        img = nib.Nifti1Image(data, np.eye(4))
        img.set_qform(np.eye(4), code=0)
        img.set_sform(np.eye(4), code=frame)
        paths[frame] = tmp_path / f"{frame}.nii"
        nib.save(img, paths[frame])
    assert nifti_frame(paths["mni"]) == "mni"
    assert nifti_frame(paths["unknown"]) == "unknown"
    save_nifti(Image(data, np.eye(4)), tmp_path / "ours.nii")
    assert nifti_frame(tmp_path / "ours.nii") == "aligned"
    check_same_frame(paths["scanner"], paths["aligned"], paths["unknown"], None,
                     names=("data.fixed", "data.labels", "x", "data.moving"))
    with pytest.raises(ValueError, match="different world frames") as err:
        check_same_frame(paths["scanner"], paths["mni"], names=("data.fixed", "data.labels"))
    assert "data.fixed: scanner" in str(err.value) and "data.labels: mni" in str(err.value)
    with pytest.raises(ValueError, match="different world frames"):
        check_same_frame(paths["scanner"], paths["aligned"], strict=True)


def test_load_nifti_names_a_path_that_is_not_an_image(tmp_path):
    with pytest.raises(ValueError, match="is a directory, not a NIfTI image"):
        load_nifti(tmp_path)
    (tmp_path / "notes.nii.gz").write_text("not an image")
    with pytest.raises(ValueError, match="notes.nii.gz is not an image nibabel can read"):
        load_nifti(tmp_path / "notes.nii.gz")
    with pytest.raises(FileNotFoundError, match="image not found"):
        load_nifti(tmp_path / "missing.nii.gz")


def test_load_nifti_names_a_truncated_or_corrupted_file(tmp_path):
    """A ``.nii.gz`` cut short (a copy that failed) or with damaged bytes: a ValueError that
    names the file and says it is truncated or damaged."""
    good = tmp_path / "f.nii.gz"
    rng = np.random.default_rng(0)
    save_nifti(Image(rng.normal(size=(20, 20, 20)), np.eye(4)), good)
    data = good.read_bytes()
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut.nii.gz: the image data cannot be read .* truncated or damaged"):
        load_nifti(cut)
    flipped = tmp_path / "flipped.nii.gz"
    for pos in (len(data) // 3, len(data) // 2):  # a CRC mismatch; a zlib stream error
        damaged = bytearray(data)
        damaged[pos] ^= 0xFF
        flipped.write_bytes(bytes(damaged))
        with pytest.raises(ValueError, match=r"flipped.nii.gz: the image data cannot be read"):
            load_nifti(flipped)


def test_saved_nifti_files_get_the_umasks_mode(tmp_path):
    """NIfTI outputs get the mode the process's umask allows, like the run's other files (not
    the 0600 of the temporary file they are written under), and no temporary is left."""
    import os


    old = os.umask(0o022)
    try:
        save_nifti(Image(np.zeros((2, 2, 2)), np.eye(4)), tmp_path / "m.nii.gz")
        (tmp_path / "run.json").write_text("{}")
    finally:
        os.umask(old)
    assert (tmp_path / "m.nii.gz").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "run.json").stat().st_mode & 0o777 == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.nii.gz", "run.json"]  # no leftovers


@pytest.mark.parametrize("spacing", [0, -2.0, np.nan, np.inf])
def test_resample_to_spacing_rejects_a_spacing_that_is_not_positive_and_finite(spacing):
    with pytest.raises(ValueError, match=r"spacing_mm must be a finite number > 0, got"):
        resample_to_spacing(smooth_image((4, 4, 4)), spacing)


def test_resample_rejects_a_singular_target_affine_and_a_bad_shape():
    img = smooth_image((4, 4, 4))
    with pytest.raises(ValueError, match="target affine is singular"):
        resample(img, np.diag([1.0, 1.0, 0.0, 1.0]), (3, 3, 3))
    with pytest.raises(ValueError, match=r"target affine must be a finite \(4, 4\) matrix, got shape \(3, 3\)"):
        resample(img, np.eye(3), (3, 3, 3))
    with pytest.raises(ValueError, match=r"shape must be 3 positive integers, got \(3, 0, 3\)"):
        resample(img, np.eye(4), (3, 0, 3))


@pytest.mark.parametrize("margin", [-4.0, np.nan])
def test_pad_rejects_a_negative_or_nan_margin(margin):
    with pytest.raises(ValueError, match=r"margin_mm must be a finite number >= 0, got"):
        pad(smooth_image((4, 4, 4)), margin)
    assert pad(smooth_image((4, 4, 4)), 0.0).data.shape == (4, 4, 4)


# Oblique source grids: resample() maps output voxels to source voxel coordinates through
# np.linalg.solve of the two affines, so a centre on the source grid's boundary lands 1e-16
# outside it, where scipy.ndimage's "constant" mode alone would return cval.
OBLIQUE = pytest.param(True, id="oblique")


@pytest.mark.parametrize("order", [0, 1, 3])
def test_resample_reads_the_edge_within_tolerance_and_cval_beyond(order):
    """A target centre 1e-9 voxels outside the source's last centre reads the source's edge
    value; one 1e-3 voxels outside, and one farther, read ``cval``; one inside is unchanged."""
    src = Image(np.arange(5 * 4 * 3, dtype=float).reshape(5, 4, 3), np.eye(4))
    for shift, want in ((1e-9, src.data[4]), (1e-3, np.full((4, 3), -7.0)), (-0.0, src.data[4])):
        tgt = np.eye(4)
        tgt[0, 3] = 4.0 + shift  # target slab 0 at source coordinate 4 + shift along axis 0
        out = resample(src, tgt, (2, 4, 3), order=order, cval=-7.0)
        np.testing.assert_allclose(out.data[0], want, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(out.data[1], -7.0)  # a whole voxel beyond the grid


def _source_affine(spacing, oblique):
    """An affine with voxel sizes ``spacing`` (mm) along its axes, rotated if ``oblique``."""
    affine = np.eye(4)
    affine[:3, :3] = (_rot((0.3, -0.2, 0.4)) if oblique else np.eye(3)) @ np.diag(spacing)
    affine[:3, 3] = (12.0, -7.5, 3.0)
    return affine


@pytest.mark.parametrize("oblique", [pytest.param(False, id="axis-aligned"), OBLIQUE])
def test_resample_to_spacing_upsampled_reproduces_a_linear_field_at_every_voxel(oblique):
    """Finer voxels on every axis (no anti-aliasing): the output grid keeps the first voxel
    centre and the axes, its centres reach as far into the source grid as whole voxels do,
    and linear interpolation of a field linear in world coordinates equals the field at
    every output voxel centre."""
    g, c = np.array([0.7, -1.3, 0.4]), 5.0
    spacing, shape = np.array([1.7, 1.3, 1.15]), (9, 12, 13)  # extents 13.6, 14.3, 13.8 mm
    src_aff = _source_affine(spacing, oblique)
    img = Image(_world_points(src_aff, shape) @ g + c, src_aff)
    out = resample_to_spacing(img, 1.0)
    np.testing.assert_allclose(out.spacing, 1.0, rtol=1e-12)
    np.testing.assert_allclose(out.affine[:3, 3], src_aff[:3, 3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.affine[:3, :3] @ np.diag(spacing), src_aff[:3, :3], rtol=0, atol=1e-12)
    assert out.data.shape == tuple(int(np.floor((n - 1) * h)) + 1 for n, h in zip(shape, spacing))
    world = _world_points(out.affine, out.data.shape)
    np.testing.assert_allclose(out.data, world @ g + c, rtol=0, atol=1e-10)


@pytest.mark.parametrize("oblique", [pytest.param(False, id="axis-aligned"), OBLIQUE])
def test_resample_to_spacing_downsampled_reproduces_a_linear_field_where_smoothing_leaves_it(oblique):
    """Coarser voxels along one axis: the Gaussian anti-aliasing (``sigma = (factor - 1) / 2``
    source voxels along that axis, truncated at ``4 sigma``) leaves a linear field unchanged
    wherever its kernel stays inside the grid, and everywhere for a field constant along
    that axis.  The output equals the field at every output voxel centre whose interpolation
    stencil lies in that region; for the field constant along the smoothed axis, at every
    output voxel centre."""
    spacing = np.array([0.4, 1.25, 1.6])  # factors 2.5 (smoothed), 0.8 and 0.625 (not smoothed)
    src_aff = _source_affine(spacing, oblique)
    shape = (40, 12, 10)
    factor = 1.0 / spacing
    out_shape = tuple(int(np.floor((n - 1) / f)) + 1 for n, f in zip(shape, factor))
    sigma = (factor[0] - 1.0) / 2.0
    radius = int(4.0 * sigma + 0.5)  # scipy.ndimage's kernel radius
    # output voxel i samples source voxel coordinate i * factor along axis 0, between voxels
    # floor and ceil of it: both must be radius voxels or more from either face
    pos = np.arange(out_shape[0]) * factor[0]
    clear = (np.floor(pos) >= radius) & (np.ceil(pos) <= shape[0] - 1 - radius)
    assert 0.5 < clear.mean() < 1.0
    axis0 = src_aff[:3, 0] / np.linalg.norm(src_aff[:3, 0])
    for g, everywhere in ((np.array([0.7, -1.3, 0.4]), False),
                          (np.cross(axis0, [0.2, 0.5, -1.0]), True)):  # g . axis0 = 0
        img = Image(_world_points(src_aff, shape) @ g + 5.0, src_aff)
        out = resample_to_spacing(img, 1.0)
        assert out.data.shape == out_shape
        np.testing.assert_allclose(out.spacing, 1.0, rtol=1e-12)
        want = _world_points(out.affine, out_shape) @ g + 5.0
        where = np.ones(out_shape, bool) if everywhere else np.broadcast_to(clear[:, None, None], out_shape)
        np.testing.assert_allclose(out.data[where], want[where], rtol=0, atol=1e-10)
        if not everywhere:  # the faces' reflection bends the field next to them
            assert np.abs(out.data - want).max() > 1e-3
