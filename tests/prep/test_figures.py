from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from gsavatar.prep import figures
from gsavatar.prep.localize import active_per_point, build_localization
from gsavatar.prep.sample_points import build_hierarchy
from prep_fixtures import arm_rig, arm_template

_MISSING = figures._missing_gl_libs()
needs_egl = pytest.mark.skipif(bool(_MISSING), reason=f"EGL/OpenGL libraries unavailable: {_MISSING}")


@pytest.fixture(scope="module")
def scene():
    t, rig = arm_template(), arm_rig()
    h = build_hierarchy(t, n_anchors=40, n_control=400, n_gaussians=6000, seed=0, min_candidates=3000)
    return t, rig, h, build_localization(h, rig, t.face_uv_mask)


def _read_png(path):
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None
    return img[..., ::-1].astype(np.int32)  # RGB


def _count(img, rgb, tol=40):
    c = np.round(np.array(rgb) * 255).astype(np.int32)
    return int(np.sum(np.all(np.abs(img - c) <= tol, axis=-1)))


def test_module_import_does_not_touch_env():
    code = (
        "import os, sys, gsavatar.prep.figures; "
        "print(os.environ.get('VTK_DEFAULT_OPENGL_WINDOW', 'unset'), 'pyvista' in sys.modules)"
    )
    env = {k: v for k, v in os.environ.items() if k != "VTK_DEFAULT_OPENGL_WINDOW"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split() == ["unset", "False"]


@needs_egl
def test_hierarchy_figure_colours(tmp_path, scene):
    t, _, h, _ = scene
    p = figures.render_hierarchy_figure(t, h, tmp_path / "sub" / "h.png", window_size=(480, 240))
    assert p == tmp_path / "sub" / "h.png" and p.exists()
    assert not any(q.name.startswith(".") for q in p.parent.iterdir())  # no temp leftovers
    img = _read_png(p)
    assert img.shape == (240, 480, 3)
    bg = _count(img, figures.BACKGROUND, tol=3)
    assert bg < img.shape[0] * img.shape[1]  # something was drawn
    assert _count(img, figures.ORANGE) > 30
    assert _count(img, figures.BLUE) > 30
    assert _count(img, figures.RED) > 10
    # grey-ish mesh pixels (shaded): r == g == b within a few levels, not background
    grey = np.all(np.abs(img - img[..., :1]) < 6, axis=-1) & (img[..., 0] < 240) & (img[..., 0] > 40)
    assert grey.sum() > 30


@needs_egl
def test_influence_figure_colours(tmp_path, scene):
    t, rig, h, lm = scene
    p = figures.render_influence_figure(
        t, h, lm, rig, tmp_path / "i.png", param="LeftFinger.rx", window_size=(480, 240)
    )
    img = _read_png(p)
    red, light = _count(img, figures.RED), _count(img, figures.INACTIVE)
    assert red > 30 and light > 30
    # the finger/hand region (x > ~0.6 on a cylinder spanning -0.2..1.0) is at the right of the front view
    front = img[:, : img.shape[1] // 2]
    cols = np.nonzero(np.all(np.abs(front - np.round(np.array(figures.RED) * 255)) <= 40, axis=-1))[1]
    assert cols.min() > 0.45 * front.shape[1]
    # the coloured Gaussians follow "any of the 3 anchors is active"
    g_on = active_per_point(lm.pose[:, lm.slot_of(rig, "LeftFinger.rx")], h.gauss_anchor_idx)
    assert 0 < g_on.sum() < len(g_on)
    with pytest.raises(KeyError, match="unknown pose parameter"):
        figures.render_influence_figure(t, h, lm, rig, tmp_path / "x.png", param="Nope.rx")


def test_missing_libraries_raise_clear_error(tmp_path, scene, monkeypatch):
    t, _, h, _ = scene
    monkeypatch.setattr(figures, "_missing_gl_libs", lambda: ["libEGL.so.1 (Debian/Ubuntu: libegl1)"])
    with pytest.raises(RuntimeError, match="libEGL.so.1"):
        figures.render_hierarchy_figure(t, h, tmp_path / "h.png")
    assert not (tmp_path / "h.png").exists()
