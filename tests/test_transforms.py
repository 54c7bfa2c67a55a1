"""Displacement-field files against ITK (SimpleITK), ANTs (ANTsPy) and NiTransforms; the FE
map's inverse and point mapping against exact affine maps."""

import numpy as np
import pytest

from bayesreg.data.images import Image, grid_points, interpolate_numpy
from bayesreg.interop.transforms import (displace_points, field_image, inverse_displacement,
                                 load_displacement, save_displacement)
from conftest import box_mesh

AFFINE = np.array([[2.0, 0, 0, -20], [0, 2.0, 0, -30], [0, 0, 2.0, -10], [0, 0, 0, 1]])
SHAPE = (20, 22, 18)


def _moving():
    ii = np.indices(SHAPE).astype(float)
    return Image(np.sin(ii[0] / 3) + np.cos(ii[1] / 4) * ii[2] / 10 + 0.01 * ii[0] * ii[1], AFFINE)


def _field():
    """A smooth RAS field, mm, on the grid."""
    x = grid_points(Image(np.zeros(SHAPE), AFFINE)).reshape(*SHAPE, 3)
    return np.stack([1.3 + 0.02 * x[..., 1], -0.7 + 0.01 * x[..., 2], 0.9 - 0.015 * x[..., 0]], -1)


def _own_pullback(m, u):
    """m(x + u(x)) at the grid's voxel centres (the project's warp)."""
    pts = grid_points(Image(np.zeros(SHAPE), AFFINE)) + u.reshape(-1, 3)
    return interpolate_numpy(m, pts, order=1).reshape(SHAPE)


@pytest.mark.parametrize("convention", ["itk", "nifti"])
def test_saved_field_reads_back_and_simpleitk_resamples_as_our_warp(tmp_path, convention):
    sitk = pytest.importorskip("SimpleITK")
    import nibabel as nib

    u, m = _field(), _moving()
    path = save_displacement(u, AFFINE, tmp_path / "u.nii.gz", convention=convention)
    nii = nib.load(path)
    assert nii.shape == SHAPE + (1, 3)
    assert nii.header.get_xyzt_units()[0] == "mm"
    assert b"fixed->moving" in nii.header["descrip"].tobytes()
    back = load_displacement(path)
    np.testing.assert_allclose(back.data, u, atol=1e-5)  # float32 storage
    np.testing.assert_allclose(back.affine, AFFINE)

    nib.save(nib.Nifti1Image(m.data.astype(np.float32), AFFINE), tmp_path / "m.nii.gz")
    mi = sitk.ReadImage(str(tmp_path / "m.nii.gz"), sitk.sitkFloat64)
    field = sitk.ReadImage(str(path), sitk.sitkVectorFloat64)
    out = sitk.Resample(mi, mi, sitk.DisplacementFieldTransform(field), sitk.sitkLinear, 0.0)
    got = sitk.GetArrayFromImage(out).transpose(2, 1, 0)
    want = _own_pullback(Image(m.data.astype(np.float32).astype(float), AFFINE), u)
    inner = (slice(3, -3),) * 3  # away from the edge, where the two treat outside differently
    np.testing.assert_allclose(got[inner], want[inner], atol=1e-4)


def test_ants_applies_the_itk_field_as_our_warp(tmp_path):
    try:
        import ants
    except Exception as exc:  # pragma: no cover - depends on the platform's wheel
        pytest.skip(f"ANTsPy is not installed here ({type(exc).__name__}: {exc}); the test "
                    "extra installs it on Linux x86_64 only")
    import nibabel as nib

    u, m = _field(), _moving()
    path = save_displacement(u, AFFINE, tmp_path / "u_1Warp.nii.gz")
    nib.save(nib.Nifti1Image(m.data.astype(np.float32), AFFINE), tmp_path / "m.nii.gz")
    mi = ants.image_read(str(tmp_path / "m.nii.gz"))
    got = ants.apply_transforms(fixed=mi, moving=mi, transformlist=[str(path)],
                                interpolator="linear").numpy()
    want = _own_pullback(Image(m.data.astype(np.float32).astype(float), AFFINE), u)
    inner = (slice(3, -3),) * 3
    np.testing.assert_allclose(got[inner], want[inner], atol=1e-4)


def test_nitransforms_round_trip_gives_the_same_field(tmp_path):
    import nibabel as nib
    from nitransforms.nonlinear import DenseFieldTransform

    u = _field()
    path = save_displacement(u, AFFINE, tmp_path / "u.nii.gz")
    xfm = DenseFieldTransform.from_filename(path, fmt="itk")
    np.testing.assert_allclose(np.asarray(xfm._deltas), u, atol=1e-5)
    # and a field NiTransforms writes reads back here unchanged
    DenseFieldTransform(nib.Nifti1Image(u, AFFINE)).to_filename(tmp_path / "nt.nii.gz", fmt="itk")
    np.testing.assert_allclose(load_displacement(tmp_path / "nt.nii.gz").data, u, atol=1e-6)


def test_field_files_refuse_what_is_not_a_field(tmp_path):
    import nibabel as nib

    with pytest.raises(ValueError, match="convention"):
        field_image(_field(), AFFINE, convention="fsl")
    with pytest.raises(ValueError, match="I, J, K, 3"):
        field_image(np.zeros(SHAPE), AFFINE)
    nib.save(nib.Nifti1Image(np.zeros(SHAPE, np.float32), AFFINE), tmp_path / "s.nii.gz")
    with pytest.raises(ValueError, match="s.nii.gz: not a 3-D displacement field"):
        load_displacement(tmp_path / "s.nii.gz")


def test_inverse_and_points_of_an_affine_map_are_exact():
    mesh = box_mesh((4, 4, 4), size=(40.0, 40.0, 40.0), origin=(-20.0, -20.0, -20.0))
    a = np.array([[0.05, 0.02, 0.0], [-0.01, 0.03, 0.01], [0.0, 0.02, -0.04]])
    b = np.array([1.0, -0.5, 0.7])
    u = mesh.nodes @ a.T + b  # affine: the FE map reproduces it exactly
    grid = Image(np.zeros((15, 15, 15)), np.array([[2.0, 0, 0, -14], [0, 2, 0, -14],
                                                    [0, 0, 2, -14], [0, 0, 0, 1]]))
    v, inside = inverse_displacement(mesh, u, grid)
    y = grid_points(grid)[inside.ravel()]
    x = y + v.reshape(-1, 3)[inside.ravel()]
    np.testing.assert_allclose(x + x @ a.T + b, y, atol=1e-9)  # phi(phi^-1(y)) = y
    assert inside.sum() > 0.5 * inside.size
    assert np.all(v.reshape(-1, 3)[~inside.ravel()] == 0)

    pts = np.array([[0.0, 0.0, 0.0], [5.0, -3.0, 2.0], [100.0, 0.0, 0.0]])
    moved, ins = displace_points(mesh, u, pts)
    np.testing.assert_allclose(moved[:2], pts[:2] + pts[:2] @ a.T + b, atol=1e-12)
    assert ins.tolist() == [True, True, False] and np.all(moved[2] == pts[2])
    many, _ = displace_points(mesh, np.stack([u, 2 * u]), pts)
    assert many.shape == (2, 3, 3)
    np.testing.assert_allclose(many[1, :2], pts[:2] + 2 * (pts[:2] @ a.T + b), atol=1e-12)

    with pytest.raises(ValueError, match="inverted"):
        inverse_displacement(mesh, -3.0 * mesh.nodes, grid)
