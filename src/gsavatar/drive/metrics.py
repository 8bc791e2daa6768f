"""Metrics of a driven sequence: image quality, temporal stability, the paper's figure-7 picture,
and the predictor's ramp-up after initialisation.

- Image quality per (frame, camera): PSNR (full image), PSNR inside the GT mask, SSIM and
  LPIPS (when given) against the ground truth composited onto the render background.
- Temporal stability per consecutive pair: ``mean |(r_t - r_{t-1}) - (g_t - g_{t-1})|`` over
  the pixels (and channels) inside the union of the two GT masks: 0 when the render changes
  exactly as the real footage does; flicker and popping raise it, while genuine motion does
  not. ``render_change`` (``mean |r_t - r_{t-1}|`` inside the same region) needs no ground
  truth and is what figure 7 visualises.
- Figure 7: frames t-1, t and the l1 difference image for the pair with the largest
  temporal error (render row; ground-truth row below when available).
- Ramp-up (the paper's future-work item on initialisation): per-frame latent L1 error
  against the encoder's latents of the same frame and PSNR, over the first frames after
  zero / pose-conditioned / encoder initialisation, as JSON and a plot drawn with OpenCV.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from gsavatar.data_schema.views import UndistortMaps, load_view, scaled_camera
from gsavatar.drive.driver import motion_inputs
from gsavatar.drive.sources import ramp_up_modes, source_class
from gsavatar.metrics.image import psnr, ssim
from gsavatar.metrics.protocols import ag_scores, on_white
from gsavatar.utils.io import atomic_write_json, write_image

_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75)]  # RGB


# --------------------------------------------------------------------------- stateless math
def chw(img: Tensor) -> Tensor:
    """[H, W, 3] -> [3, H, W] (no copy)."""
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(f"image must be [H, W, 3], got {list(img.shape)}")
    return img.permute(2, 0, 1)


def composite(image: Tensor, mask: Tensor, background: Tensor) -> Tensor:
    """Ground truth on the render background. image [3,H,W], mask [1,H,W] in [0,1], background [3] -> [3,H,W]"""
    return image * mask + background.to(image)[:, None, None] * (1 - mask)


def image_scores(pred: Tensor, gt: Tensor, mask: Tensor, lpips=None) -> dict[str, float]:
    """pred, gt [3,H,W] in [0,1], mask [1,H,W] -> psnr, psnr_fg (inside mask > 0.5), ssim[, lpips]."""
    p, g = pred[None].float(), gt[None].float().to(pred.device)
    m = (mask[None].to(pred.device) > 0.5).expand_as(p)
    out = {
        "psnr": float(psnr(p, g)[0]),
        "psnr_fg": float(psnr(p, g, mask=m)[0]) if m.any() else float("nan"),
        "ssim": float(ssim(p, g)[0]),
    }
    if lpips is not None:
        dev = next(lpips.parameters()).device
        out["lpips"] = float(lpips(p.to(dev), g.to(dev)).mean())
    return out


def temporal_error(pred0: Tensor, pred1: Tensor, gt0: Tensor, gt1: Tensor, region: Tensor) -> float:
    """``mean |(pred1 - pred0) - (gt1 - gt0)|`` over ``region`` [1,H,W] (bool/0-1) and channels; images [3,H,W].
    NaN for an empty region."""
    r = region.to(pred0.dtype).expand_as(pred0)
    d = ((pred1 - pred0) - (gt1.to(pred0) - gt0.to(pred0))).abs()
    n = float(r.sum())
    return float((d * r).sum()) / n if n > 0 else float("nan")


def render_change(pred0: Tensor, pred1: Tensor, region: Tensor) -> float:
    """``mean |pred1 - pred0|`` over ``region`` [1,H,W] and channels; images [3,H,W]. NaN for an empty region."""
    r = region.to(pred0.dtype).expand_as(pred0)
    n = float(r.sum())
    return float(((pred1 - pred0).abs() * r).sum()) / n if n > 0 else float("nan")


def _nanmean(v: list[float]) -> float | None:
    a = np.asarray([x for x in v if x is not None], dtype=np.float64)
    a = a[~np.isnan(a)]  # NaN: empty masks; +inf PSNR (identical images) is kept
    return float(a.mean()) if a.size else None


# --------------------------------------------------------------------------- pictures
def _label(img: np.ndarray, text: str) -> np.ndarray:
    """Write ``text`` on a uint8 RGB image (top-left, white on a dark box)."""
    scale = max(0.35, img.shape[0] / 400)
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(img, (0, 0), (w + 6, h + base + 6), (0, 0, 0), -1)
    cv2.putText(img, text, (3, h + 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def _tile(img: Tensor, height: int, text: str) -> np.ndarray:
    a = (img.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)  # [H, W, 3]
    f = max(1, height // a.shape[0])
    a = cv2.resize(a, (a.shape[1] * f, a.shape[0] * f), interpolation=cv2.INTER_NEAREST)
    return _label(np.ascontiguousarray(a), text)


def stability_figure(
    path: str | Path,
    frame0: Tensor,
    frame1: Tensor,
    gt0: Tensor | None = None,
    gt1: Tensor | None = None,
    t: int = 1,
    gain: float = 4.0,
    min_height: int = 256,
) -> Path:
    """The paper's figure 7: frames t-1, t and the l1 difference (x ``gain``); GT row when given.
    Images [H,W,3] in [0,1]. Writes a PNG and returns its path."""
    rows = [(frame0, frame1, "render")] + ([(gt0, gt1, "ground truth")] if gt0 is not None and gt1 is not None else [])
    out = []
    for a, b, name in rows:
        diff = ((b - a).abs().mean(-1, keepdim=True) * gain).clamp(0, 1).expand_as(a)
        out.append(
            np.concatenate(
                [
                    _tile(a, min_height, f"{name} t={t - 1}"),
                    _tile(b, min_height, f"t={t}"),
                    _tile(diff, min_height, f"|l1| x{gain:g}"),
                ],
                1,
            )
        )
    path = Path(path)
    write_image(path, np.concatenate(out, 0).astype(np.float32) / 255.0)
    return path


def line_plot(
    series: dict[str, list[float]], title: str, xlabel: str, ylabel: str, size: tuple[int, int] = (480, 320)
) -> np.ndarray:
    """A simple line plot (axes, ticks, legend) drawn with OpenCV. -> [H, W, 3] uint8 RGB"""
    W, H = size
    img = np.full((H, W, 3), 255, np.uint8)
    L, R, T, B = 56, 12, 28, 40
    ys = [y for v in series.values() for y in v if y is not None and math.isfinite(y)]
    n = max((len(v) for v in series.values()), default=1)
    lo, hi = (min(ys), max(ys)) if ys else (0.0, 1.0)
    if hi - lo < 1e-9:
        lo, hi = lo - 0.5, hi + 0.5
    pad = 0.05 * (hi - lo)
    lo, hi = lo - pad, hi + pad
    px = lambda i: int(round(L + (W - L - R) * (i / max(n - 1, 1))))  # noqa: E731
    py = lambda y: int(round(H - B - (H - T - B) * (y - lo) / (hi - lo)))  # noqa: E731
    black, grey = (0, 0, 0), (200, 200, 200)
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.38
    for k in range(5):  # y grid + ticks
        y = lo + (hi - lo) * k / 4
        cv2.line(img, (L, py(y)), (W - R, py(y)), grey, 1)
        cv2.putText(img, f"{y:.3g}", (4, py(y) + 4), font, fs, black, 1, cv2.LINE_AA)
    step = max(1, int(math.ceil((n - 1) / 8)))
    for i in range(0, n, step):  # x ticks
        cv2.line(img, (px(i), H - B), (px(i), H - B + 4), black, 1)
        cv2.putText(img, str(i), (px(i) - 4, H - B + 16), font, fs, black, 1, cv2.LINE_AA)
    cv2.rectangle(img, (L, T), (W - R, H - B), black, 1)
    lw = max((cv2.getTextSize(name, font, fs, 1)[0][0] for name in series), default=0) + 34  # legend width
    for k, (name, v) in enumerate(series.items()):
        c = _COLORS[k % len(_COLORS)]
        pts = [(px(i), py(y)) for i, y in enumerate(v) if y is not None and math.isfinite(y)]
        for p0, p1 in zip(pts[:-1], pts[1:]):
            cv2.line(img, p0, p1, c, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 2, c, -1)
        ly, lx = T + 14 + 14 * k, W - R - lw
        cv2.line(img, (lx, ly - 4), (lx + 20, ly - 4), c, 2)
        cv2.putText(img, name, (lx + 24, ly), font, fs, black, 1, cv2.LINE_AA)
    cv2.putText(img, title, (L, 18), font, 0.45, black, 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, ((L + W - R) // 2 - 20, H - 8), font, fs, black, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (4, 18), font, fs, black, 1, cv2.LINE_AA)
    return img


# --------------------------------------------------------------------------- sequences
def load_ground_truth(
    capture, frame: int, cameras: list[str], image_scale: float, background: Tensor, maps: UndistortMaps | None = None
) -> dict[str, tuple[Tensor, Tensor]]:
    """GT of one capture frame per camera, undistorted/resized like the driver's views.
    ``maps``: undistortion tables to reuse over a sequence (None: built for this call).
    -> {cam: (image on background [H,W,3], mask [H,W])}"""
    out = {}
    for cam in cameras:
        geo = scaled_camera(capture.cameras[cam], image_scale)
        img, msk = load_view(
            capture.cameras[cam], capture.image_path(cam, frame), capture.mask_path(cam, frame), geo, maps
        )
        im, mk = torch.from_numpy(img).permute(2, 0, 1), torch.from_numpy(msk)[None]
        out[cam] = (composite(im, mk, background.cpu()).permute(1, 2, 0).contiguous(), mk[0])
    return out


class SequenceMetrics:
    """Streaming accumulator: :meth:`add` each (frame, camera) in frame order, then :meth:`summary`."""

    def __init__(
        self, lpips=None, background: Tensor | None = None, ag_lpips: dict | None = None, ag_lpips_every: int = 10
    ) -> None:
        """``background`` [3]: what renders and ground truth are composited on (for the ``ag`` protocol's white;
        None: black); ``ag_lpips``: its LPIPS nets, scored on frames ``t % ag_lpips_every == 0``."""
        self.lpips = lpips
        self.background = torch.zeros(3) if background is None else background.detach().float().cpu()
        if int(ag_lpips_every) < 1:
            raise ValueError(f"ag_lpips_every must be >= 1 (every N-th frame), got {ag_lpips_every}")
        self.ag_lpips, self.ag_lpips_every = ag_lpips or {}, int(ag_lpips_every)
        self.rows: list[dict] = []
        self._prev: dict[str, tuple] = {}
        self.worst: dict | None = None

    def add(
        self, t: int, cam: str, pred: Tensor, alpha: Tensor, gt: Tensor | None = None, mask: Tensor | None = None
    ) -> dict:
        """pred [H,W,3], alpha [H,W], gt [H,W,3] | None, mask [H,W] | None -> this row's scores."""
        row: dict = {"t": int(t), "camera": cam}
        region = (mask > 0.5) if mask is not None else (alpha > 0.5)
        if gt is not None:
            row |= image_scores(chw(pred), chw(gt), mask[None], self.lpips)
            bg = self.background.to(pred)
            nets = self.ag_lpips if t % self.ag_lpips_every == 0 else None
            ag = ag_scores(
                on_white(chw(pred), alpha[None], bg).clamp(0, 1),
                on_white(chw(gt), mask[None].to(gt), bg),
                mask[None],
                nets,
            )
            row |= {f"ag_{k}": v for k, v in ag.items()}
        prev = self._prev.get(cam)
        if prev is not None and prev[0] == t - 1:
            _, p0, g0, r0 = prev
            reg = (region | r0)[None]
            row["render_change"] = render_change(chw(p0), chw(pred), reg)
            score = row["render_change"]
            if gt is not None:
                row["temporal_error"] = temporal_error(chw(p0), chw(pred), chw(g0), chw(gt), reg)
                score = row["temporal_error"]
            if math.isfinite(score) and (self.worst is None or score > self.worst["score"]):
                self.worst = {"score": score, "t": int(t), "camera": cam, "frames": (p0, pred), "gt": (g0, gt)}
        self._prev[cam] = (int(t), pred, gt, region)
        self.rows.append(row)
        return row

    def summary(self) -> dict:
        keys = [
            k
            for k in (
                "psnr",
                "psnr_fg",
                "ssim",
                "lpips",
                "temporal_error",
                "render_change",
                "ag_psnr",
                "ag_ssim",
                "ag_lpips_vgg",
                "ag_lpips_alex",
            )
            if any(k in r for r in self.rows)
        ]
        cams = sorted({r["camera"] for r in self.rows})
        per_cam = {c: {k: _nanmean([r.get(k) for r in self.rows if r["camera"] == c]) for k in keys} for c in cams}
        out = {
            "mean": {k: _nanmean([r.get(k) for r in self.rows]) for k in keys},
            "per_camera": per_cam,
            "frames": len({r["t"] for r in self.rows}),
            "rows": self.rows,
        }
        if self.worst is not None:
            out["worst_pair"] = {"t": self.worst["t"], "camera": self.worst["camera"], "score": self.worst["score"]}
        return out

    def write_figure(self, path: str | Path) -> Path | None:
        """Figure 7 for the pair with the largest temporal error (render change without GT); None if < 2 frames."""
        if self.worst is None:
            return None
        (a, b), (g0, g1) = self.worst["frames"], self.worst["gt"]
        return stability_figure(path, a, b, g0, g1, t=self.worst["t"])


# --------------------------------------------------------------------------- ramp-up
def measure_ramp_up(
    driver, motion, textures, frames: int = 30, modes: tuple[str, ...] | None = None, with_images: bool = True
) -> dict:
    """Per-frame latent L1 error (vs the encoder's latents of the same frame) and PSNR (vs GT,
    mean over the driver's cameras) for the first ``frames`` frames after each initialisation.

    driver: a :class:`~gsavatar.drive.driver.Driver` with capture cameras; motion with ground
    truth; textures(t) -> [3,S,S]; modes: drive modes to compare (None: those of
    :func:`~gsavatar.drive.sources.ramp_up_modes`). Modes the run cannot do are reported under ``skipped``.
    -> {"frames": n, "modes": {mode: {"latent_l1": [n], "psnr": [n] | None}}, "skipped": {mode: reason}}
    """
    if motion.gt is None:
        raise ValueError("ramp-up needs a motion with ground truth (a capture directory)")
    if not driver.has_latents:
        raise ValueError("ramp-up needs a model with appearance latents")
    n = min(int(frames), motion.num_frames)
    if n < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    inputs = [motion_inputs(motion, t, textures(t)) for t in range(n)]
    targets = [driver.encode(x.texture).cpu() for x in inputs]
    cams = [v.name for v in driver.views]
    maps = UndistortMaps()
    gts = (
        [
            load_ground_truth(motion.gt.capture, motion.gt.frames[t], cams, driver.config.image_scale, driver.bg, maps)
            for t in range(n)
        ]
        if with_images and driver.config.cameras == "capture"
        else None
    )
    result: dict = {"frames": n, "fps": motion.fps, "cameras": cams, "modes": {}, "skipped": {}}
    for mode in ramp_up_modes() if modes is None else modes:
        try:
            d = driver.with_mode(mode)
        except ValueError as e:
            result["skipped"][mode] = str(e)
            continue
        d.start(inputs[0])
        lat_err, ps = [], []
        for t in range(n):
            fr = d.step(inputs[t], render=gts is not None)
            lat_err.append(float((fr.latents - targets[t]).abs().mean()))
            if gts is not None:
                ps.append(
                    float(np.mean([float(psnr(chw(fr.images[c])[None], chw(gts[t][c][0])[None])[0]) for c in cams]))
                )
        result["modes"][mode] = {"latent_l1": lat_err, "psnr": ps if gts is not None else None}
    return result


def write_ramp_up(result: dict, out_dir: str | Path, stem: str = "ramp_up") -> tuple[Path, Path]:
    """ramp_up.json + ramp_up.png (latent error and PSNR panels side by side)."""
    out_dir = Path(out_dir)
    atomic_write_json(out_dir / f"{stem}.json", result)
    modes = result["modes"]
    panels = [
        line_plot(
            {m: v["latent_l1"] for m, v in modes.items() if not source_class(m).matches_encoder},
            "latent L1 vs encoder latents",
            "frame",
            "L1",
        )
    ]
    if any(v.get("psnr") for v in modes.values()):
        panels.append(
            line_plot({m: v["psnr"] for m, v in modes.items() if v.get("psnr")}, "PSNR vs ground truth", "frame", "dB")
        )
    png = out_dir / f"{stem}.png"
    write_image(png, np.concatenate(panels, 1).astype(np.float32) / 255.0)
    return out_dir / f"{stem}.json", png
