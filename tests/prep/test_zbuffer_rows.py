"""The packed rows of the z-buffer kernels (prep/zbuffer.py): the camera row (:data:`CAMERA_ROW`, written by
``pack_camera``) and the block-bounds row (:data:`BOUNDS_ROW`, written by ``_block_bounds``) are laid out by
one table each; the offset constants the kernels index by must agree with it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gsavatar.data_schema.capture import Camera
from gsavatar.prep import zbuffer as zb

ROWS = {"camera": (zb.CAMERA_ROW, zb.CAM_SIZE, "CAM_"), "bounds": (zb.BOUNDS_ROW, zb.BND_SIZE, "BND_")}


@pytest.mark.parametrize("row", sorted(ROWS))
def test_row_table_is_contiguous_and_matches_its_constants(row):
    fields, size, prefix = ROWS[row]
    names = [f.name for f in fields]
    assert len(set(names)) == len(names)
    end = 0
    for f in fields:  # in order, each field right after the previous one: no gap, no overlap
        assert f.offset == end and f.width >= 1 and f.doc, f
        end += f.width
    assert end == size
    for f in fields:
        assert getattr(zb, prefix + f.name) == f.offset, f.name
    # every offset constant of the module is a field of the table (none defined beside it)
    consts = {k[len(prefix) :] for k, v in vars(zb).items() if k.startswith(prefix) and isinstance(v, int)}
    assert consts == set(names) | {"SIZE"}


def _rotation(axis, angle):
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * S + (1 - math.cos(angle)) * S @ S  # Rodrigues


def test_pack_camera_fields_round_trip_a_hand_made_camera():
    R = _rotation((0.3, -0.5, 0.8), 0.7)  # every entry distinct and non-zero: a swapped pair would show
    T = np.array([0.11, -0.23, 2.9])
    K = np.array([[301.5, 0.75, 40.25], [0.0, 299.0, 30.5], [0.0, 0.0, 1.0]])
    dist = np.array([-0.12, 0.031, 0.0017, -0.0023, 0.0041])
    cam = Camera("hand", K, R, T, dist, 80, 60)
    grid = zb.Grid(301.5, 0.75, 52.0, 299.0, 41.0, 105, 83)
    cp = zb.pack_camera(cam, 2.25, grid, crop=(7, 11), region=(3, 5, 64, 48))
    assert cp.shape == (zb.CAM_SIZE,) and cp.dtype == np.float64
    centre = -R.T @ T
    want = {f"R{i}{j}": R[i, j] for i in range(3) for j in range(3)}
    want.update(T0=T[0], T1=T[1], T2=T[2], CENTER_X=centre[0], CENTER_Y=centre[1], CENTER_Z=centre[2])
    want.update(FX=301.5, SKEW=0.75, CX=40.25, FY=299.0, CY=30.5)
    want.update(K1=dist[0], K2=dist[1], P1=dist[2], P2=dist[3], K3=dist[4], USE_DIST=1.0, R2MAX=2.25)
    want.update(WIDTH=80, HEIGHT=60, GRID_FX=301.5, GRID_SKEW=0.75, GRID_CX=52.0, GRID_FY=299.0, GRID_CY=41.0)
    want.update(GRID_WIDTH=105, GRID_HEIGHT=83, CROP_X=7, CROP_Y=11, GRID_IS_IMAGE=0.0)
    want.update(REGION_X=3, REGION_Y=5, REGION_WIDTH=64, REGION_HEIGHT=48)
    assert set(want) == {f.name for f in zb.CAMERA_ROW}
    for f in zb.CAMERA_ROW:
        assert cp[getattr(zb, "CAM_" + f.name)] == want[f.name], f.name

    # no distortion and the camera's own K as the grid: the grid is the image; the region defaults to it
    plain = Camera("plain", K, R, T, np.zeros(5), 80, 60)
    cp = zb.pack_camera(plain, math.inf, zb.pinhole_grid(plain, math.inf))
    assert cp[zb.CAM_USE_DIST] == 0.0 and cp[zb.CAM_GRID_IS_IMAGE] == 1.0 and cp[zb.CAM_R2MAX] == math.inf
    region = cp[[zb.CAM_REGION_X, zb.CAM_REGION_Y, zb.CAM_REGION_WIDTH, zb.CAM_REGION_HEIGHT]]
    np.testing.assert_array_equal(region, [0, 0, 80, 60])
    grid_crop = cp[[zb.CAM_GRID_WIDTH, zb.CAM_GRID_HEIGHT, zb.CAM_CROP_X, zb.CAM_CROP_Y]]
    np.testing.assert_array_equal(grid_crop, [80, 60, 0, 0])


def test_pack_row_names_a_missing_or_unknown_field():
    values = {f.name: 0.0 for f in zb.CAMERA_ROW}
    del values["FX"]
    with pytest.raises(ValueError, match="row fields must be"):
        zb._pack_row(zb.CAMERA_ROW, zb.CAM_SIZE, values)
    values.update(FX=1.0, LENS=0.0)
    with pytest.raises(ValueError, match="LENS"):
        zb._pack_row(zb.CAMERA_ROW, zb.CAM_SIZE, values)


def test_block_bounds_fields_hold_the_sphere_and_the_normal_cone():
    rng = np.random.default_rng(3)
    P = rng.normal(size=(3, 40))
    Nrm = np.array([0.2, -0.1, 1.0])[:, None] + 0.3 * rng.normal(size=(3, 40))
    Nrm /= np.linalg.norm(Nrm, axis=0)
    bnd = np.empty(zb.BND_SIZE)
    zb._block_bounds(P, Nrm, 5, 30, bnd)
    p, nrm = P[:, 5:35], Nrm[:, 5:35]
    c = bnd[[zb.BND_CENTER_X, zb.BND_CENTER_Y, zb.BND_CENTER_Z]]
    np.testing.assert_allclose(c, p.mean(1), rtol=1e-12, atol=1e-15)
    assert bnd[zb.BND_RADIUS] >= np.linalg.norm(p - c[:, None], axis=0).max()
    axis = bnd[[zb.BND_AXIS_X, zb.BND_AXIS_Y, zb.BND_AXIS_Z]]
    np.testing.assert_allclose(axis, nrm.sum(1) / np.linalg.norm(nrm.sum(1)), rtol=1e-12)
    assert bnd[zb.BND_HALF_ANGLE] >= np.arccos(np.clip(axis @ nrm, -1, 1)).max()
    assert bnd[zb.BND_HALF_ANGLE] < math.pi
