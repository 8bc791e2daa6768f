"""The live viewer: viewer Gaussians equal the avatar's (covariances, SH -> RGB), frame dropping keeps the
latent source's state, bad input exits 2, and the page in headless Chromium shows the avatar, changes
while playing and holds still while paused (skipped when ``chromium`` is not installed)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import traceback
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from gsavatar.drive.cli import main as drive_main
from gsavatar.drive.driver import DriveConfig, Driver, motion_inputs
from gsavatar.drive.live import LiveGaussians, covariances_from, sh_to_rgb, viewer_arrays
from gsavatar.drive.motion import load_driving_motion
from gsavatar.drive.viewer import AvatarViewer, ViewerOptions, rest_motion
from gsavatar.models.predictor import AppearancePredictor, PredictorConfig


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def driver(tiny_dataset) -> Driver:
    """An untrained tiny avatar + untrained small predictor on the tiny dataset (no run directory)."""
    from gsavatar.data_schema.prepared import load_scene
    from gsavatar.models.net import build_net
    from gsavatar.runs.config import TrainConfig, model_config, resolve
    from gsavatar.runs.load import LoadedRun

    scene = load_scene(tiny_dataset)
    cfg = resolve(TrainConfig(dataset=tiny_dataset, out=Path(tempfile.gettempdir()) / "unused", preset="tiny"))
    net = build_net(scene, model_config(cfg), 0).eval()
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():  # move the untrained model off its flat start so frames and SH bands differ
        for name, p in net.avatar.named_parameters():
            if "basis" in name or name.startswith("sh"):
                p.add_(torch.randn(p.shape, generator=g) * 0.05)
    av = net.avatar
    pc = PredictorConfig(
        history=4,
        width=16,
        heads=2,
        ff=32,
        latent_dim=av.latent_in,
        token_hidden=8,
        latent_pca_components=4,
        initial_hidden=16,
    )
    pred = AppearancePredictor(pc, av.num_anchors, np.arange(0, av.pose_dim, 5), av.pose_dim, seed=1).eval()
    torch.nn.init.normal_(pred.head.weight, std=0.1)
    return Driver(
        Path("<untrained tiny>"),
        DriveConfig(mode="predictor", device="cpu"),
        loaded=LoadedRun(net, scene, cfg, 0),
        predictor=pred,
    )


@pytest.fixture(scope="module")
def motion(driver):
    cap = driver.scene.capture
    return load_driving_motion(cap.root, cap.rig, driver.fps)


# --------------------------------------------------------------------------- Gaussians
@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_fused_kernel_equals_reference(deg):
    g = torch.Generator().manual_seed(deg)
    N = 500
    q = torch.nn.functional.normalize(torch.randn(N, 4, generator=g), dim=-1)
    s = torch.rand(N, 3, generator=g) * 0.05 + 1e-3
    sh = torch.randn(N, (deg + 1) ** 2, 3, generator=g) * 0.3
    m = torch.randn(N, 3, generator=g)
    eye = np.array([0.5, -2.0, 1.0], np.float32)
    cov, rgb = viewer_arrays(m, q, s, sh, eye, deg)
    ref = covariances_from(q, s)
    np.testing.assert_allclose(cov, ref.numpy(), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(rgb, sh_to_rgb(sh, m, eye, deg).numpy(), atol=1e-5)
    # covariance = R diag(s^2) R^T: eigenvalues are the squared scales
    ev = np.sort(np.linalg.eigvalsh(cov.astype(np.float64)), 1)
    np.testing.assert_allclose(ev, np.sort(s.double().numpy() ** 2, 1), rtol=1e-3, atol=1e-9)
    _, rgb0 = viewer_arrays(m, q, s, sh, None, deg)  # no eye: band 0 only
    np.testing.assert_allclose(rgb0, (sh[:, 0] * 0.28209479177387814 + 0.5).clamp(0, 1).numpy(), atol=1e-6)


def test_live_gaussians_are_the_avatars(driver, motion):
    live = LiveGaussians(driver)
    eye = np.array([0.3, -2.5, 1.2], np.float32)
    live.start(motion_inputs(motion, 0))
    ref = driver.with_mode("predictor")  # same run + predictor, fresh state
    ref.start(motion_inputs(motion, 0))
    for t in range(3):
        x = motion_inputs(motion, t)
        g = live.next(x, eye)
        lat = ref.step(x, render=False).latents
        with torch.no_grad():
            av = ref.net(ref.check_inputs(x).batch(lat), sh_degree=ref.sh_degree).avatar
        np.testing.assert_allclose(g.centers, av.means[0].numpy(), atol=1e-6)
        np.testing.assert_allclose(
            g.covariances, covariances_from(av.quats[0], av.scales[0]).numpy(), rtol=1e-5, atol=1e-10
        )
        np.testing.assert_allclose(g.rgbs, sh_to_rgb(av.sh[0], av.means[0], eye, ref.sh_degree).numpy(), atol=1e-5)
        np.testing.assert_allclose(g.opacities[:, 0], av.opacities[0].numpy(), atol=1e-7)
    assert set(live.timings) >= {"predictor", "avatar", "covariance + SH -> RGB"} and live.frames == 3
    # a pose offset moves only part of the body (locality): a wrist parameter leaves the feet in place
    rig = driver.scene.capture.rig
    slot = next(
        i
        for i, j in enumerate(rig.slot_joints())
        if "wrist" in rig.joints[j].name.lower() or "hand" in rig.joints[j].name.lower()
    )
    live.pose_offset[slot] = 1.0
    moved = live.gaussians(motion_inputs(motion, 2), lat, eye)
    d = np.linalg.norm(moved.centers - g.centers, axis=1)
    assert d.max() > 0.01 and (d < 1e-5).mean() > 0.25, (d.max(), (d < 1e-5).mean())  # 24 anchors: coarse


def test_dropped_frames_keep_the_predictor_state(driver, motion):
    v = AvatarViewer(driver, {"m": motion}, ViewerOptions(max_catch_up=3, start_paused=True))
    v.generate(0)
    v.generate(3)  # frames 1, 2 dropped (not drawn) but stepped
    assert v.frames_dropped == 2 and v.frame == 3
    ref = driver.with_mode("predictor")
    ref.start(motion_inputs(motion, 0))
    lats = [ref.step(motion_inputs(motion, t), render=False).latents for t in range(4)]
    torch.testing.assert_close(v._latents, lats[3])
    v.generate(3 + 5)  # more than max_catch_up behind: the source restarts there
    assert v._seq_start == 8 and v.frames_dropped == 2
    with pytest.raises(ValueError, match="frame must be in"):
        v.seek(motion.num_frames)
    with pytest.raises(ValueError, match="mode must be one of"):
        v.set_mode("nope")
    r = rest_motion(driver)
    assert r.num_frames == 1 and not r.pose.any()


def test_cli_errors(tmp_path, capsys):
    assert drive_main(["--run", str(tmp_path / "nope"), "--motion", str(tmp_path), "--view"]) == 2
    assert "config.json" in capsys.readouterr().err
    assert drive_main(["--run", str(tmp_path / "nope"), "--motion", str(tmp_path)]) == 2
    assert "--out is required" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


# --------------------------------------------------------------------------- headless Chromium
class Chromium:
    """Headless Chromium driven over the DevTools protocol (screenshots of a live page)."""

    def __init__(self, url: str, size: tuple[int, int], tmp: Path) -> None:
        from websockets.sync.client import connect

        self.dir = Path(tempfile.mkdtemp(dir=tmp, prefix="chromium"))
        self.proc = subprocess.Popen(
            [
                shutil.which("chromium"),
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--enable-unsafe-swiftshader",
                f"--window-size={size[0]},{size[1]}",
                "--remote-debugging-port=0",
                f"--user-data-dir={self.dir}",
                "--no-first-run",
                "--hide-scrollbars",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        port_file = self.dir / "DevToolsActivePort"
        t0 = time.time()
        while not (port_file.exists() and port_file.read_text().strip()):
            if time.time() - t0 > 30 or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not start")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json"))
        self.ws = connect(next(p for p in pages if p["type"] == "page")["webSocketDebuggerUrl"], max_size=None)
        self.id = 0
        self.call(
            "Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1, mobile=False
        )
        self.call("Page.navigate", url=url)

    def call(self, method: str, **params) -> dict:
        self.id += 1
        self.ws.send(json.dumps({"id": self.id, "method": method, "params": params}))
        while True:
            m = json.loads(self.ws.recv(timeout=60))
            if m.get("id") == self.id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})

    def screenshot(self) -> np.ndarray:
        """The page as RGB uint8 [H, W, 3]."""
        import imageio.v2 as imageio

        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return imageio.imread(png)[..., :3]

    def close(self) -> None:
        if getattr(self, "ws", None) is not None:
            self.ws.close()
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        shutil.rmtree(self.dir, ignore_errors=True)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _loop_state(v: AvatarViewer) -> str:
    """The playback thread: alive, seconds since its last iteration and, when stalled, where it is."""
    t = v._thread
    if t is None or not t.is_alive():
        return "playback thread not running"
    idle = time.perf_counter() - v._state.loop_t
    out = f"playback loop last ran {idle:.1f} s ago"
    if idle > 2.0:
        frame = sys._current_frames().get(t.ident)
        out += " in:\n" + "".join(traceback.format_stack(frame)[-8:]) if frame is not None else ""
    return out


W, H, PANEL = 800, 600, 340  # page size; viser's control panel takes the right PANEL pixels


def avatar_mask(img: np.ndarray) -> np.ndarray:
    """Non-background pixels of the 3D view (left of the control panel, below the notification). [h, w]"""
    view = img[180:, : W - PANEL].astype(int)
    return np.abs(view - view[-1:, -1:]).sum(-1) > 30  # background: the bottom-right corner of the view


@pytest.mark.browser
def test_viewer_in_headless_chromium(driver, motion, tmp_path):
    if shutil.which("chromium") is None:
        pytest.skip("browser: `chromium` is not installed (scripts/setup.sh installs it: apt-get install chromium)")
    v = AvatarViewer(driver, {"tiny capture": motion}, ViewerOptions(port=_free_port()))
    url = v.start()
    assert url.startswith("http://127.0.0.1:")
    b = None
    try:
        b = Chromium(url, (W, H), tmp_path)
        t0, img = time.time(), None
        while time.time() - t0 < 40:  # the client connects, receives the splats and sorts them
            time.sleep(1.0)
            img = b.screenshot()
            if avatar_mask(img).mean() > 0.01:
                break
        m = avatar_mask(img)
        assert m.mean() > 0.01, f"no avatar on the page (non-background fraction {m.mean():.4f})"
        ys, xs = np.nonzero(m)
        h, w = m.shape
        assert 0.1 * w < xs.mean() < 0.9 * w and 0.05 * h < ys.mean() < 0.95 * h  # framed by the camera preset
        # playing: frames some apart differ
        f0, n0, a = v.frame, v.frames_generated, b.screenshot()
        seen, diff_play, t0 = {f0}, 0.0, time.time()
        while time.time() - t0 < 90:  # new frames reach the page (slower while a fresh process compiles kernels)
            for _ in range(30):  # sample the frame on screen often: a looping short motion can be back at f0
                time.sleep(0.05)
                seen.add(v.frame)
            c = b.screenshot()
            diff_play = np.abs(a.astype(int) - c.astype(int))[180:, : W - PANEL].mean()
            if diff_play > 0.05:
                break
        st = v._state
        state = (
            f"frames seen {sorted(seen)}, {v.frames_generated - n0} generated in {time.time() - t0:.1f} s "
            f"({st.fps_ema:.1f} frames/s), error {st.error!r}, playing {st.playing}, {_loop_state(v)}"
        )
        assert len(seen) > 1 and v.frames_generated - n0 > 2, f"no new frame while playing: {state}"
        assert diff_play > 0.05, f"the page did not change while playing ({diff_play:.4f}): {state}"
        # paused: the same frame, the same pixels
        v.pause()
        f2, prev, diff_pause = v.frame, b.screenshot(), float("inf")
        t0 = time.time()
        while time.time() - t0 < 40:  # the last update reaches the page and is sorted (slow on a loaded box)
            time.sleep(1.5)
            cur = b.screenshot()
            diff_pause = np.abs(prev.astype(int) - cur.astype(int))[180:, : W - PANEL].mean()
            if diff_pause < 0.05:
                break
            prev = cur
        assert v.frame == f2  # no frame advanced while paused
        assert diff_pause < 0.2 * diff_play and diff_pause < 0.05, (diff_pause, diff_play)
    finally:
        if b is not None:
            b.close()
        v.stop()
    assert os.listdir(tmp_path) == []  # the viewer wrote nothing (chromium's profile is removed)
