"""Marching cubes against analytic answers: spheres and ellipsoids on odd grids."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ellipeinc, ellipkinc

from miss import BadParameter, EmptySurface, Volume, extract_surface
from miss.geometry import boundary_edge_count, enclosed_volume, surface_area


def ellipsoid_area(a: float, b: float, c: float) -> float:
    """Exact surface area (Legendre's formula with incomplete elliptic integrals)."""
    a, b, c = sorted((a, b, c), reverse=True)
    phi = np.arccos(c / a)
    m = (a * a * (b * b - c * c)) / (b * b * (a * a - c * c))
    s = np.sin(phi)
    return float(
        2 * np.pi * c * c
        + 2 * np.pi * a * b / s * (ellipeinc(phi, m) * s * s + ellipkinc(phi, m) * np.cos(phi) ** 2)
    )


def oblique_affine(spacing: tuple[float, float, float], seed: int = 3) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    affine = np.eye(4)
    affine[:3, :3] = q @ np.diag(spacing)
    affine[:3, 3] = [-40.0, 25.0, 110.0]
    return affine


def ellipsoid_volume(
    affine: np.ndarray, shape: tuple[int, int, int], axes: tuple[float, float, float]
) -> tuple[Volume, np.ndarray]:
    """A field 1 - |q| (q = normalised ellipsoid radius) sampled on the grid; centre in mm."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    centre_ijk = (np.array(shape) - 1) / 2.0
    centre = affine[:3, :3] @ centre_ijk + affine[:3, 3]
    xyz = ijk @ affine[:3, :3].T + affine[:3, 3] - centre
    q = np.sqrt(((xyz / np.array(axes)) ** 2).sum(axis=-1))
    data = np.asfortranarray((1.0 - q).astype(np.float32))
    return Volume(data=data, affine=affine, meta={"units": ""}), centre


def test_sphere_area_volume_and_orientation() -> None:
    vol, centre = ellipsoid_volume(np.diag([1.0, 1.0, 1.0, 1.0]), (64, 64, 64), (20.0, 20.0, 20.0))
    mesh = extract_surface(vol, 0.0)
    assert enclosed_volume(mesh.vertices, mesh.faces) == pytest.approx(
        4 / 3 * np.pi * 20**3, rel=0.01
    )
    assert surface_area(mesh.vertices, mesh.faces) == pytest.approx(4 * np.pi * 20**2, rel=0.01)
    assert boundary_edge_count(mesh.faces) == 0
    outward = np.einsum("ij,ij->i", mesh.normals, mesh.vertices - centre)
    assert (outward > 0).mean() > 0.999


@pytest.mark.slow
def test_without_normals_the_same_surface() -> None:
    # tall enough for three slabs, so the welding without normal columns is covered too
    vol, _ = ellipsoid_volume(np.diag([0.8, 0.8, 0.8, 1.0]), (160, 160, 400), (50.0, 50.0, 140.0))
    full = extract_surface(vol, 0.0)
    bare = extract_surface(vol, 0.0, normals=False)
    assert bare.normals is None and full.normals is not None
    np.testing.assert_array_equal(bare.vertices, full.vertices)
    np.testing.assert_array_equal(bare.faces, full.faces)


@pytest.mark.parametrize("spacing", [(0.7, 0.9, 1.3), (0.5, 0.5, 2.5)])
@pytest.mark.parametrize("mirror", [False, True])
def test_ellipsoid_under_oblique_anisotropic_affine(spacing, mirror) -> None:
    affine = oblique_affine(spacing)
    if mirror:  # a left-handed index grid (like many DICOM row orders) must not flip the surface
        affine[:3, 0] *= -1
    axes = (30.0, 22.0, 15.0)
    shape = tuple(int(80 / s) + 1 for s in spacing)  # 80 mm along every axis: room for any tilt
    vol, centre = ellipsoid_volume(affine, shape, axes)
    mesh = extract_surface(vol, 0.0)
    v_exact = 4 / 3 * np.pi * np.prod(axes)
    assert enclosed_volume(mesh.vertices, mesh.faces) == pytest.approx(v_exact, rel=0.01)
    assert surface_area(mesh.vertices, mesh.faces) == pytest.approx(ellipsoid_area(*axes), rel=0.01)
    # every vertex lies on the ellipsoid in patient mm (tolerance well under a voxel)
    q = np.sqrt((((mesh.vertices - centre) / np.array(axes)) ** 2).sum(axis=1))
    assert np.abs(q - 1.0).max() * min(axes) < 0.25


def test_sample_rate_and_slices_shrink_the_model() -> None:
    vol, _ = ellipsoid_volume(np.diag([1.0, 1.0, 1.0, 1.0]), (64, 64, 64), (25.0, 25.0, 25.0))
    full = extract_surface(vol, 0.0)
    coarse = extract_surface(vol, 0.0, sample_rate=2)
    assert coarse.n_triangles < full.n_triangles / 3
    assert enclosed_volume(coarse.vertices, coarse.faces) == pytest.approx(
        enclosed_volume(full.vertices, full.faces), rel=0.03
    )
    half = extract_surface(vol, 0.0, slices=(1, 32))
    assert boundary_edge_count(half.faces) == 0  # the cut is capped
    assert half.vertices[:, 2].max() <= 31.0 + 0.01  # the cap sits on the last slice
    assert enclosed_volume(half.vertices, half.faces) == pytest.approx(
        enclosed_volume(full.vertices, full.faces) / 2, rel=0.03
    )


def test_bad_parameters_have_clear_messages() -> None:
    vol, _ = ellipsoid_volume(np.diag([1.0, 1.0, 1.0, 1.0]), (16, 16, 16), (5.0, 5.0, 5.0))
    with pytest.raises(EmptySurface, match="pick a level inside"):
        extract_surface(vol, 5.0)
    with pytest.raises(BadParameter, match="outside 1..16"):
        extract_surface(vol, 0.0, slices=(3, 40))
    # the job declaration's region check and messages (miss.spec.Region)
    with pytest.raises(BadParameter, match="sample_rate must be an integer >= 1"):
        extract_surface(vol, 0.0, sample_rate=0)
    with pytest.raises(BadParameter, match="at least 2 along each axis"):
        extract_surface(vol, 0.0, sample_rate=(20, 1, 1))
    with pytest.raises(BadParameter, match="roi needs six voxel indices"):
        extract_surface(vol, 0.0, roi=(0, 5, 0, 5))
