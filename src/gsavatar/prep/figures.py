"""Pictures of the point hierarchy and of pose-parameter influence regions.

(a) :func:`render_hierarchy_figure` - like the paper's fig. 2: the template mesh in
grey with anchors (orange, large), control points (blue, small) and a subset of
the Gaussians (red, tiny).
(b) :func:`render_influence_figure` - like fig. 3b: the region of influence of one
pose parameter (e.g. the neck twist ``Neck.ry``): a Gaussian is active when any of
its 3 interpolation anchors has the parameter in its (dilated) mask; active
Gaussians red, inactive light blue; anchors as larger dots, active orange, inactive blue.

Both render off-screen with pyvista/VTK through EGL (``VTK_DEFAULT_OPENGL_WINDOW=
vtkEGLRenderWindow`` is set inside the functions, never at import time), show a
front and a back view side by side, write the PNG atomically and return its path.
If off-screen rendering is unavailable a :class:`RuntimeError` names the missing
system libraries.
"""

from __future__ import annotations

import ctypes.util
import os
from pathlib import Path

import numpy as np

from gsavatar.prep.localize import active_per_point
from gsavatar.utils.io import write_image

# RGB in [0, 1]
GREY = (0.78, 0.78, 0.78)
ORANGE = (1.0, 0.55, 0.0)
BLUE = (0.1, 0.35, 1.0)
RED = (0.9, 0.05, 0.05)
INACTIVE = (0.55, 0.75, 1.0)
BACKGROUND = (1.0, 1.0, 1.0)

_GL_LIBS = {"EGL": "libEGL.so.1 (Debian/Ubuntu: libegl1)", "OpenGL": "libOpenGL.so.0 (libopengl0)"}


def _missing_gl_libs() -> list[str]:
    missing = []
    for name, desc in _GL_LIBS.items():
        found = ctypes.util.find_library(name)
        try:
            ctypes.CDLL(found or f"lib{name}.so")
        except OSError:
            missing.append(desc)
    return missing


def _pyvista():
    """Import pyvista for EGL off-screen rendering, or raise a RuntimeError saying what is missing."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    missing = _missing_gl_libs()
    if missing:
        raise RuntimeError(
            "off-screen rendering needs the system libraries "
            + ", ".join(missing)
            + " (plus a Mesa EGL driver, e.g. libegl-mesa0, for rendering without a GPU)"
        )
    try:
        import pyvista as pv
    except Exception as e:  # pragma: no cover - depends on the system
        raise RuntimeError(f"cannot import pyvista/VTK for off-screen rendering: {e}") from e
    pv.OFF_SCREEN = True
    return pv


def _mesh(pv, vertices: np.ndarray, faces: np.ndarray):
    f = np.hstack([np.full((len(faces), 1), 3, np.int64), faces.astype(np.int64)]).ravel()
    return pv.PolyData(np.asarray(vertices, np.float32), f)


def _lift(points: np.ndarray, normals: np.ndarray, scale: float) -> np.ndarray:
    """Move points a little off the surface so the mesh does not hide them (no z-fighting)."""
    return (points + normals * scale).astype(np.float32)


def _views(vertices: np.ndarray):
    """Front (+Z) and back (-Z) views with +Y up (gsavatar template axes)."""
    return [((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)), ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0))]


def _render(
    pv, add_layers, vertices: np.ndarray, path: str | Path, window_size: tuple[int, int], zoom: float = 1.6
) -> Path:
    path = Path(path)
    views = _views(vertices)
    try:
        pl = pv.Plotter(off_screen=True, shape=(1, len(views)), window_size=window_size, border=False)
        for i, (direction, up) in enumerate(views):
            pl.subplot(0, i)
            pl.set_background(BACKGROUND)
            add_layers(pl, i)
            pl.view_vector(direction, viewup=up)
            pl.reset_camera()
            pl.camera.zoom(zoom)
        img = pl.screenshot(return_img=True)
        pl.close()
    except RuntimeError:
        raise
    except Exception as e:  # VTK raises assorted errors when no OpenGL context can be made
        raise RuntimeError(
            f"off-screen rendering failed ({type(e).__name__}: {e}); it needs libEGL.so.1 and libOpenGL.so.0 "
            "with a working EGL driver (Mesa: libegl-mesa0, libgl1-mesa-dri) and "
            "VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow"
        ) from e
    if img is None or img.ndim != 3:
        raise RuntimeError("off-screen rendering returned no image (EGL context missing?)")
    write_image(path, img[..., :3].astype(np.float32) / 255.0)
    return path


def _sizes(window_size: tuple[int, int]) -> tuple[float, float, float]:
    s = min(window_size) / 1000.0
    return max(4.0, 14 * s), max(1.5, 2.5 * s), max(1.0, 1.2 * s)


def render_hierarchy_figure(
    template,
    hierarchy,
    path: str | Path,
    max_gaussians: int = 30_000,
    window_size: tuple[int, int] = (1200, 1000),
    seed: int = 0,
) -> Path:
    """Fig. 2-style picture: grey mesh, anchors (orange), control points (blue), Gaussians (red).

    ``template``: :class:`~gsavatar.data_schema.template.Template`; ``hierarchy``:
    :class:`~gsavatar.data_schema.hierarchy.Hierarchy`; at most ``max_gaussians`` random
    Gaussians are drawn. Returns ``path`` (PNG).
    """
    pv = _pyvista()
    V = np.asarray(template.vertices)
    scale = float(np.linalg.norm(V.max(0) - V.min(0)))
    lift = 2e-3 * scale
    g = hierarchy.gaussians
    rng = np.random.default_rng(seed)
    sel = rng.choice(len(g), size=min(max_gaussians, len(g)), replace=False)
    a_size, c_size, g_size = _sizes(window_size)
    mesh = _mesh(pv, V, template.faces)
    gpts = pv.PolyData(_lift(g.position[sel], g.normal[sel], lift))
    cpts = pv.PolyData(_lift(hierarchy.control.position, hierarchy.control.normal, 1.5 * lift))
    apts = pv.PolyData(_lift(hierarchy.anchors.position, hierarchy.anchors.normal, 2 * lift))

    def layers(pl, view):
        pl.add_mesh(mesh, color=GREY, smooth_shading=True)
        pl.add_points(gpts, color=RED, point_size=g_size, lighting=False)
        pl.add_points(cpts, color=BLUE, point_size=c_size, render_points_as_spheres=True, lighting=False)
        pl.add_points(apts, color=ORANGE, point_size=a_size, render_points_as_spheres=True, lighting=False)

    return _render(pv, layers, V, path, window_size)


def render_influence_figure(
    template,
    hierarchy,
    masks,
    rig,
    path: str | Path,
    param: str = "Neck.ry",
    window_size: tuple[int, int] = (1200, 1000),
    show_anchors: bool = True,
) -> Path:
    """Fig. 3b-style picture: Gaussians coloured by whether pose parameter ``param`` is active.

    ``masks``: :class:`~gsavatar.data_schema.localization.LocalizationMasks` of the hierarchy's
    anchors. A Gaussian is active when any of its 3 interpolation anchors is. Gaussians:
    active red, inactive light blue; anchors: active orange, inactive blue. Returns ``path`` (PNG).
    """
    slot = masks.slot_of(rig, param)
    anchor_on = masks.pose[:, slot]
    g = hierarchy.gaussians
    g_on = active_per_point(anchor_on, hierarchy.gauss_anchor_idx)
    pv = _pyvista()
    V = np.asarray(template.vertices)
    scale = float(np.linalg.norm(V.max(0) - V.min(0)))
    lift = 2e-3 * scale
    a_size, _, g_size = _sizes(window_size)
    mesh = _mesh(pv, V, template.faces)
    gp = _lift(g.position, g.normal, lift)
    ap = _lift(hierarchy.anchors.position, hierarchy.anchors.normal, 2 * lift)
    g_off_pts, g_on_pts = pv.PolyData(gp[~g_on]), pv.PolyData(gp[g_on])
    a_off_pts, a_on_pts = pv.PolyData(ap[~anchor_on]), pv.PolyData(ap[anchor_on])

    def layers(pl, view):
        pl.add_mesh(mesh, color=GREY, smooth_shading=True)
        if g_off_pts.n_points:
            pl.add_points(g_off_pts, color=INACTIVE, point_size=2.5 * g_size, lighting=False)
        if g_on_pts.n_points:
            pl.add_points(g_on_pts, color=RED, point_size=2.5 * g_size, lighting=False)
        if show_anchors:
            if a_off_pts.n_points:
                pl.add_points(
                    a_off_pts, color=BLUE, point_size=0.6 * a_size, render_points_as_spheres=True, lighting=False
                )
            if a_on_pts.n_points:
                pl.add_points(
                    a_on_pts, color=ORANGE, point_size=0.6 * a_size, render_points_as_spheres=True, lighting=False
                )
        if view == 0:
            pl.add_text(
                f"{param}: {int(anchor_on.sum())}/{len(anchor_on)} anchors, {int(g_on.sum())}/{len(g_on)} Gaussians",
                font_size=10,
                color="black",
            )

    return _render(pv, layers, V, path, window_size)
