"""Browser viewer: a viser server that streams the driven avatar's Gaussians frame by frame.

    avatar-drive --run runs/ours --motion captures/b --view                 # http://127.0.0.1:8080
    avatar-drive --run runs/ours --motion 01_01.bvh --view --port 8090 --start-paused
    avatar-train view --run runs/ours                                       # the avatar at rest
    python -m gsavatar.drive.viewer --run runs/ours [--motion M]            # the same, as a module

The page (viser's web client, served from the wheel; the server binds ``127.0.0.1`` unless ``--host``
says otherwise) draws the avatar as Gaussian splats, updated every generated frame: centres, world
covariances ``R diag(s)^2 R^T`` and one RGB per Gaussian from its SH for the direction from the viewing
camera (the first connected browser's camera; ``--sh0-only``: SH band 0, view independent), see
:mod:`gsavatar.drive.live`. Controls:

- Playback: playing (checkbox), timeline (frame slider, seeks), speed (x of the motion's frame rate),
  a status line (frames/s generated, frames dropped);
- Drive: the latent source (drive modes the run supports + ``mean_latent``), the motion (the
  ``--motion`` given, the run's own capture, or any capture directory / motion.npz / .bvh typed into
  "Load motion"); both switch live (the latent source restarts at the current frame);
- Camera: presets = a front view of the avatar (the initial camera) and the capture's calibrated cameras;
- Pose: one slider per pose parameter (radians, added to the motion's pose, grouped by body part)
  and "Reset pose", to see which Gaussians a single parameter moves.

Playback follows the motion's clock: frame = elapsed time x fps x speed. Generation slower than
that drops frames instead of falling behind: the latent source still steps through skipped frames
(the predictor's state stays that of the sequence), up to ``max_catch_up`` of them, beyond which it
restarts at the current frame. Play/pause without the GUI: ``--start-paused`` and
:meth:`AvatarViewer.play` / :meth:`AvatarViewer.pause` (the Python API the browser test uses).
The viewer writes no files.
"""

from __future__ import annotations

import dataclasses
import errno
import ipaddress
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro

from gsavatar.data_schema import SchemaError
from gsavatar.drive.driver import DriveConfig, Driver, FrameInputs, motion_inputs, texture_source
from gsavatar.drive.live import MEAN_LATENT, LiveGaussians
from gsavatar.drive.motion import DrivingMotion, load_driving_motion
from gsavatar.runs.load import load_run
from gsavatar.utils.cli import parse_args, run_reporting_errors


@dataclass
class ViewerOptions:
    """Server and playback options of :class:`AvatarViewer`."""

    port: int = 8080
    """Port of the web page (http://HOST:PORT)."""
    host: str = "127.0.0.1"
    """Interface to bind (default: this machine only)."""
    start_paused: bool = False
    """Open paused on the first frame (play from the GUI or :meth:`AvatarViewer.play`)."""
    speed: float = 1.0
    """Playback speed, x the motion's frame rate."""
    sh0_only: bool = False
    """Colour from SH band 0 only (view independent) instead of the viewing camera's direction."""
    max_catch_up: int = 8
    """Frames the latent source steps through without drawing when generation falls behind; more: restart."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {self.port}")
        if not self.speed > 0:
            raise ValueError(f"speed must be > 0, got {self.speed}")
        if self.max_catch_up < 0:
            raise ValueError(f"max_catch_up must be >= 0, got {self.max_catch_up}")


RESOLVE_TIMEOUT_S = 5.0
"""How long resolving ``--host`` may take before the viewer gives up (a name no DNS answers must not hang)."""


def _resolve(host: str, port: int, timeout: float) -> list[tuple]:
    """``socket.getaddrinfo`` with a deadline (it has none of its own). -> [(family, sockaddr)]"""
    box: dict = {}

    def work() -> None:
        try:
            box["infos"] = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError as e:  # socket.gaierror too
            box["error"] = e

    t = threading.Thread(target=work, daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive():
        raise ValueError(f"--host {host!r}: did not resolve within {timeout:.0f} s")
    if "error" in box:
        raise ValueError(f"--host {host!r}: cannot resolve ({box['error']})")
    return [(fam, addr) for fam, _, _, _, addr in box["infos"]]


def claim_address(host: str, port: int, timeout: float = RESOLVE_TIMEOUT_S, warn=print) -> int:
    """Check that the viewer can serve exactly ``host:port``; returns the port (``port=0``: a free one, chosen here).

    Raises ValueError naming the host or port when the host does not resolve (within ``timeout``) or cannot be
    bound, or the port is in use: viser would otherwise move to the next free port silently, so a link to the
    asked-for port would reach another server. ``warn`` gets one line when the address is not loopback (the
    viewer has no authentication: anyone who can reach it sees and drives the avatar).
    """
    if not 0 <= port <= 65535:
        raise ValueError(f"--port must be in [0, 65535], got {port}")
    infos = _resolve(host, port, timeout)
    if not infos:
        raise ValueError(f"--host {host!r}: resolves to no address")
    family, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        if hasattr(socket, "SO_REUSEADDR"):  # a TIME_WAIT socket of an earlier viewer is not "in use"
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        chosen = int(sock.getsockname()[1])
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise ValueError(
                f"--port {port}: already in use on {host} (another server holds it); choose another "
                f"port, or --port 0 for any free one"
            ) from None
        raise ValueError(f"--host {host!r}: cannot bind {addr[0]}:{port} ({e.strerror or e})") from None
    finally:
        sock.close()
    try:
        loopback = ipaddress.ip_address(str(addr[0]).split("%")[0]).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        warn(
            f"warning: the viewer binds {host} ({addr[0]}), which is not loopback; it has no authentication, so "
            f"anyone who can reach this address can watch and drive the avatar"
        )
    return chosen


def rest_motion(driver: Driver) -> DrivingMotion:
    """One frame: the rest pose (zeros) at the root transform of the run's capture frame 0."""
    cap = driver.scene.capture
    P = driver.pose_dim
    rr = rt = np.zeros((1, 3), np.float32)
    try:
        m = load_driving_motion(cap.root, cap.rig, driver.fps, count=1)
        rr, rt = m.root_rotation[:1], m.root_translation[:1]
    except (ValueError, OSError):  # a capture without poses: origin, identity
        pass
    return DrivingMotion(
        np.zeros((1, P), np.float32),
        rr.astype(np.float32),
        rt.astype(np.float32),
        None,
        float(driver.fps),
        None,
        "rest pose",
        float(driver.fps),
    )


@dataclass
class _Playback:
    playing: bool
    pos: float = 0.0
    """Motion time in frames (fractional)."""
    shown: int = -1
    """Motion frame on screen (-1: none yet)."""
    restart: bool = True
    dirty: bool = True
    generated: int = 0
    dropped: int = 0
    fps_ema: float = 0.0
    error: str = ""
    stats_t: float = field(default_factory=time.perf_counter)
    loop_t: float = 0.0
    """perf_counter() at the start of the playback loop's latest iteration (0: not started)."""


class AvatarViewer:
    """The viewer of a driver and its motions (module docstring).

    Args:
        driver: a :class:`~gsavatar.drive.driver.Driver` of the run (mode = the initial latent source).
        motions: motion name -> driving motion (resampled to ``driver.fps``); the first is shown first.
        options: :class:`ViewerOptions`.
        mode: initial latent source (default ``driver.config.mode``; may be ``mean_latent``).
    """

    def __init__(
        self,
        driver: Driver,
        motions: dict[str, DrivingMotion],
        options: ViewerOptions | None = None,
        mode: str | None = None,
    ) -> None:
        if not motions:
            raise ValueError("motions: at least one driving motion is needed")
        self.options = opt = options or ViewerOptions()
        self.live = LiveGaussians(driver, sh0_only=opt.sh0_only)
        self.motions = dict(motions)
        self.motion_name = next(iter(self.motions))
        self._textures: dict[str, object] = {}
        self._lock = threading.RLock()
        self._state = _Playback(playing=not opt.start_paused)
        self._speed = opt.speed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._latents: torch.Tensor | None = None
        self._seq_start = 0
        self._src_t = -1
        self._eye: np.ndarray | None = None
        self._gui_sync = False
        self.server = None
        self.handle = None
        if mode is not None:
            self.live.set_mode(mode)
        self._check_textures(self.live.mode, self.motion_name)

    # ------------------------------------------------------------------ python control
    @property
    def motion(self) -> DrivingMotion:
        return self.motions[self.motion_name]

    @property
    def playing(self) -> bool:
        return self._state.playing

    @property
    def frame(self) -> int:
        """Motion frame on screen (-1 before the first)."""
        return self._state.shown

    @property
    def frames_generated(self) -> int:
        return self._state.generated

    @property
    def frames_dropped(self) -> int:
        return self._state.dropped

    @property
    def url(self) -> str:
        if self.server is None:
            raise RuntimeError("the viewer is not started")
        return f"http://{self.options.host}:{self.server.get_port()}/"

    def play(self) -> None:
        """Resume playback from the frame on screen."""
        with self._lock:
            self._state.playing = True
        self._sync_gui()

    def pause(self) -> None:
        """Hold the frame on screen (pose sliders and the camera still update it)."""
        with self._lock:
            self._state.playing = False
        self._sync_gui()

    def seek(self, frame: int) -> None:
        """Show motion frame ``frame`` (the latent source restarts there)."""
        T = self.motion.num_frames
        if not 0 <= frame < T:
            raise ValueError(f"frame must be in [0, {T}), got {frame}")
        with self._lock:
            self._state.pos = float(frame)
            self._state.restart = True

    def set_speed(self, speed: float) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        with self._lock:
            self._speed = float(speed)

    def set_mode(self, mode: str) -> None:
        """Switch the latent source live; ValueError (state unchanged) if the run or motion cannot drive it."""
        with self._lock:
            old = self.live.mode
            self.live.set_mode(mode)
            try:
                self._check_textures(mode, self.motion_name)
            except ValueError:
                self.live.set_mode(old)
                raise
            self._state.restart = True

    def add_motion(self, name: str, motion: DrivingMotion) -> None:
        """Offer another driving motion (resampled to the driver's fps)."""
        if motion.pose.shape[1] != self.live.driver.pose_dim:
            raise ValueError(f"{name}: pose must be [T, {self.live.driver.pose_dim}], got {list(motion.pose.shape)}")
        with self._lock:
            self.motions[name] = motion
        if self.server is not None:
            self._gui_motion.options = list(self.motions)

    def load_motion(self, path: str | Path) -> str:
        """Load a capture directory / motion.npz / .bvh, add it and switch to it; returns its name."""
        d = self.live.driver
        m = load_driving_motion(Path(path), d.scene.capture.rig, d.fps)
        name = str(path)
        self.add_motion(name, m)
        self.set_motion(name)
        return name

    def set_motion(self, name: str) -> None:
        """Switch to motion ``name`` at its first frame."""
        if name not in self.motions:
            raise ValueError(f"motion must be one of {list(self.motions)}, got {name!r}")
        self._check_textures(self.live.mode, name)
        with self._lock:
            self.motion_name = name
            self._state.pos = 0.0
            self._state.restart = True
        if self.server is not None:
            with self._gui_guard():
                self._gui_frame.max = max(self.motion.num_frames - 1, 1)

    def set_pose_offset(self, index: int, value: float) -> None:
        """Add ``value`` radians to pose parameter ``index`` of every frame."""
        with self._lock:
            self.live.pose_offset[index] = float(value)
            self._state.dirty = True

    def _check_textures(self, mode: str, motion_name: str) -> None:
        live = self.live
        if mode == MEAN_LATENT or not live.needs_textures:
            return
        if motion_name not in self._textures:
            self._textures[motion_name] = texture_source(
                self.motions[motion_name], live.driver.scene, live.driver.config.textures
            )

    # ------------------------------------------------------------------ generation
    def _inputs(self, k: int, t_since_start: int) -> FrameInputs:
        tex = None
        if self.live.texture_needed_at(t_since_start):
            tex = self._textures[self.motion_name](k)
        return motion_inputs(self.motion, k, tex)

    def generate(self, target: int) -> None:
        """Bring the latent source to motion frame ``target`` and draw its Gaussians."""
        st = self._state
        live = self.live
        restart = (
            st.restart
            or self._src_t < 0
            or target < self._src_t
            or target - self._src_t > self.options.max_catch_up + 1
        )
        if restart:
            st.restart = False
            self._seq_start = target
            x = self._inputs(target, 0)
            live.start(x)
            self._latents = live.latents(x)
            self._src_t = target
        elif target > self._src_t:
            st.dropped += target - self._src_t - 1
            for k in range(self._src_t + 1, target + 1):
                self._latents = live.latents(self._inputs(k, k - self._seq_start))
            self._src_t = target
        g = live.gaussians(motion_inputs(self.motion, target), self._latents, self._eye)
        if self.handle is not None:
            self.handle.set_gaussians(g.centers, g.covariances, g.rgbs, g.opacities)
        st.shown = target
        st.generated += 1
        st.dirty = False
        return g

    def _loop(self) -> None:
        last = time.perf_counter()
        while not self._stop.is_set():
            now = time.perf_counter()
            self._state.loop_t = now
            try:
                todo = self._tick(now, last)
            except Exception as e:  # noqa: BLE001 - the loop outlives any one frame: shown in the page, playback pauses
                with self._lock:
                    self._state.error = f"{type(e).__name__}: {e}"
                    self._state.playing = False
                todo = False
            last = now
            if todo:
                try:
                    self._sync_gui()
                except Exception as e:  # noqa: BLE001 - a client gone mid-update; the next frame syncs again
                    self._state.error = f"GUI: {type(e).__name__}: {e}"
            period = 1.0 / (self.motion.fps * self._speed)
            self._stop.wait(max(0.002, period - (time.perf_counter() - now)) if not todo else 0.001)

    def _tick(self, now: float, last: float) -> bool:
        """One step of the playback clock: advance it, generate the frame it lands on when needed."""
        with self._lock:
            st = self._state
            T = self.motion.num_frames
            if st.playing:
                st.pos += (now - last) * self.motion.fps * self._speed
                if st.pos >= T:  # loop: the sequence starts again
                    st.pos %= T
                    st.restart = True
            target = min(int(st.pos), T - 1)
            eye = self._viewer_eye()
            if eye is not None and (self._eye is None or np.abs(eye - self._eye).max() > 1e-3):
                self._eye = eye
                st.dirty = st.dirty or (not self.options.sh0_only and self.live.driver.sh_degree > 0)
            todo = st.restart or target != st.shown or st.dirty
            if todo:
                tic = time.perf_counter()
                try:
                    self.generate(target)
                    st.error = ""
                except Exception as e:  # noqa: BLE001 - shown in the page, playback pauses
                    st.error = f"{type(e).__name__}: {e}"
                    st.playing = False
                    st.dirty = False
                    st.shown = target
                dt = time.perf_counter() - tic
                st.fps_ema = 1 / dt if st.fps_ema == 0 else 0.9 * st.fps_ema + 0.1 / max(dt, 1e-6)
        return todo

    def _viewer_eye(self) -> np.ndarray | None:
        if self.server is None:
            return None
        clients = self.server.get_clients()
        if not clients:
            return None
        return np.asarray(next(iter(clients.values())).camera.position, np.float32)

    # ------------------------------------------------------------------ server + GUI
    def start(self) -> str:
        """Start the server and the playback thread; returns the page's URL."""
        import viser

        opt = self.options
        port = claim_address(opt.host, opt.port, warn=lambda m: print(m, file=sys.stderr, flush=True))
        self.server = server = viser.ViserServer(host=opt.host, port=port, verbose=False, label="gsavatar")
        if server.get_port() != port:  # taken between the check and viser's bind: never serve another port
            server.stop()
            raise ValueError(f"--port {port}: taken by another server while the viewer started; choose another port")
        server.gui.configure_theme(show_logo=False, dark_mode=False)
        g = self.generate(min(int(self._state.pos), self.motion.num_frames - 1))
        self.handle = server.scene.add_gaussian_splats(
            "/avatar", centers=g.centers, covariances=g.covariances, rgbs=g.rgbs, opacities=g.opacities
        )
        self._presets = self._camera_presets(g.centers)
        server.scene.set_up_direction(tuple(map(float, self._up)))  # orbiting keeps the capture cameras' up
        self._build_gui()

        @server.on_client_connect
        def _(client) -> None:
            self._apply_preset(next(iter(self._presets)), [client])

        self._thread = threading.Thread(target=self._loop, name="gsavatar-viewer", daemon=True)
        self._thread.start()
        return self.url

    def stop(self) -> None:
        """Stop playback and the server."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)
        if self.server is not None:
            self.server.stop()

    def serve_forever(self) -> None:
        """Start, print the URL, and run until Ctrl-C."""
        url = self.start()
        print(f"avatar viewer: {url} (Ctrl-C to stop)", flush=True)
        try:
            while not self._stop.is_set():
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()

    def _camera_presets(self, centers: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
        """name -> (position, look_at, up, vertical fov radians): a front view of the avatar (the initial
        camera), then the capture's calibrated cameras."""
        d = self.live.driver
        c = centers.mean(0).astype(np.float64)
        cap = d.camera_capture
        names = list(
            dict.fromkeys(list(cap.splits["test"].cameras if "test" in cap.splits else []) + sorted(cap.cameras))
        )
        cams = {}
        for n in names:
            cam = cap.cameras[n]
            R = np.asarray(cam.R, np.float64)
            pos = -R.T @ np.asarray(cam.T, np.float64)
            fwd, up = R.T @ np.array([0.0, 0.0, 1.0]), -R.T @ np.array([0.0, 1.0, 0.0])
            dist = max(float(np.dot(c - pos, fwd)), 0.5)
            fov = 2 * np.arctan(cam.height / (2 * float(cam.K[1, 1])))
            cams[f"camera {n}"] = (pos, pos + dist * fwd, up, fov)
        # front: 3.2 m from the avatar towards the first capture camera, level, the cameras' mean up
        up = np.mean([v[2] for v in cams.values()], 0) if cams else np.array([0.0, 0.0, 1.0])
        up = up / max(np.linalg.norm(up), 1e-9)
        toward = (next(iter(cams.values()))[0] - c) if cams else np.array([0.0, -1.0, 0.0])
        toward = toward - np.dot(toward, up) * up
        if np.linalg.norm(toward) < 1e-6:
            toward = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        toward = toward / np.linalg.norm(toward)
        self._up = up
        return {"front": (c + 3.2 * toward + 0.3 * up, c, up, np.deg2rad(45.0)), **cams}

    def _apply_preset(self, name: str, clients=None) -> None:
        pos, look, up, fov = self._presets[name]
        for cl in clients if clients is not None else self.server.get_clients().values():
            with cl.atomic():
                cl.camera.fov = float(fov)
                cl.camera.up_direction = tuple(map(float, up))
                cl.camera.position = tuple(map(float, pos))
                cl.camera.look_at = tuple(map(float, look))

    class _Guard:
        def __init__(self, v: AvatarViewer) -> None:
            self.v = v

        def __enter__(self):
            self.v._gui_sync = True

        def __exit__(self, *a):
            self.v._gui_sync = False

    def _gui_guard(self) -> AvatarViewer._Guard:
        return AvatarViewer._Guard(self)

    def _sync_gui(self) -> None:
        if self.server is None:
            return
        st = self._state
        with self._gui_guard():
            if self._gui_playing.value != st.playing:
                self._gui_playing.value = st.playing
            if st.shown >= 0 and self._gui_frame.value != st.shown:
                self._gui_frame.value = st.shown
        status = (
            f"frame {st.shown + 1}/{self.motion.num_frames} · {st.fps_ema:.1f} frames/s generated · "
            f"{st.dropped} dropped · mode `{self.live.mode}`"
        )
        if st.error:
            status += f"\n\n**error:** {st.error}"
        if self._gui_status.content != status:
            self._gui_status.content = status

    def _build_gui(self) -> None:
        gui = self.server.gui
        d = self.live.driver
        with gui.add_folder("Playback"):
            self._gui_playing = gui.add_checkbox("Playing", self._state.playing)
            self._gui_frame = gui.add_slider(
                "Frame", 0, max(self.motion.num_frames - 1, 1), 1, max(self._state.shown, 0)
            )
            self._gui_speed = gui.add_slider("Speed", 0.1, 4.0, 0.1, float(self._speed))
            self._gui_status = gui.add_markdown("")
        with gui.add_folder("Drive"):
            modes = LiveGaussians.modes(d)
            if self.live.mode not in modes:
                modes.insert(0, self.live.mode)
            self._gui_mode = gui.add_dropdown("Latents", modes, initial_value=self.live.mode)
            self._gui_motion = gui.add_dropdown("Motion", list(self.motions), initial_value=self.motion_name)
            self._gui_path = gui.add_text("Load motion", "", hint="capture directory, motion.npz or .bvh")
            load = gui.add_button("Load")
        with gui.add_folder("Camera"):
            self._gui_preset = gui.add_dropdown("Preset", list(self._presets), initial_value=next(iter(self._presets)))
            go = gui.add_button("Go to preset")
        pose_sliders = []
        with gui.add_folder("Pose (offsets, rad)", expand_by_default=False):
            reset = gui.add_button("Reset pose")
            rig = d.scene.capture.rig
            labels = [f"{p.name}[{k}]" if p.size > 1 else p.name for p in rig.params for k in range(p.size)]
            for i, lab in enumerate(labels[: d.pose_dim]):
                s = gui.add_slider(lab, -3.14, 3.14, 0.01, 0.0)
                pose_sliders.append(s)

                def on_pose(_, i=i, s=s) -> None:
                    self.set_pose_offset(i, s.value)

                s.on_update(on_pose)

        def user(fn):
            def cb(_) -> None:
                if self._gui_sync:
                    return
                try:
                    fn()
                    self._state.error = ""
                except Exception as e:  # noqa: BLE001 - reported in the page
                    self._state.error = f"{type(e).__name__}: {e}"
                self._sync_gui()

            return cb

        self._gui_playing.on_update(user(lambda: self.play() if self._gui_playing.value else self.pause()))
        self._gui_frame.on_update(user(lambda: self.seek(int(self._gui_frame.value))))
        self._gui_speed.on_update(user(lambda: self.set_speed(float(self._gui_speed.value))))

        def mode_changed() -> None:
            try:
                self.set_mode(self._gui_mode.value)
            except Exception:
                with self._gui_guard():
                    self._gui_mode.value = self.live.mode
                raise

        self._gui_mode.on_update(user(mode_changed))
        self._gui_motion.on_update(user(lambda: self.set_motion(self._gui_motion.value)))

        def load_clicked() -> None:
            name = self.load_motion(self._gui_path.value.strip())
            with self._gui_guard():
                self._gui_motion.value = name

        load.on_click(user(load_clicked))
        go.on_click(user(lambda: self._apply_preset(self._gui_preset.value)))

        def reset_pose() -> None:
            with self._gui_guard():
                for s in pose_sliders:
                    s.value = 0.0
            with self._lock:
                self.live.pose_offset.zero_()
                self._state.dirty = True

        reset.on_click(user(reset_pose))


# --------------------------------------------------------------------------- entry points
def viewer_from_run(
    run: Path,
    motion: Path | None = None,
    *,
    config: DriveConfig | None = None,
    options: ViewerOptions | None = None,
    motion_fps: float = 0.0,
    start: int = 0,
    count: int = 0,
    split: str | None = None,
) -> AvatarViewer:
    """A viewer of run ``run`` driven by ``motion`` (None: the rest pose) and the run's own capture.

    ``config``: the drive configuration (mode, textures, device); a run without the mode's predictor or
    encoder raises ValueError naming what is missing. Without ``motion`` the mode is ``mean_latent``
    when the run has an encoder.
    """
    cfg = config or DriveConfig(device="cpu")
    loaded = load_run(run, cfg.device)
    if motion is None and loaded.net.encoder is not None and loaded.net.avatar.latent_in:
        d = Driver(run, dataclasses.replace(cfg, mode="encoder"), loaded=loaded)
        return AvatarViewer(d, {"rest pose": rest_motion(d)}, options, mode=MEAN_LATENT)
    d = Driver(run, cfg, loaded=loaded)
    cap = d.scene.capture
    motions: dict[str, DrivingMotion] = {}
    if motion is not None:
        m = load_driving_motion(
            motion, cap.rig, d.fps, fps=motion_fps or None, start=start, count=count or None, split=split
        )
        if m.face is not None and m.face.shape[1] != d.face_dim:
            raise SchemaError(motion, "face", f"has {m.face.shape[1]} columns, the avatar expects {d.face_dim}")
        if m.gt is not None:
            d.use_capture_cameras(m.gt.capture)
        motions[str(motion)] = m
    else:
        motions["rest pose"] = rest_motion(d)
    if motion is None or Path(motion).resolve() != Path(cap.root).resolve():
        try:
            motions[f"capture {Path(cap.root).name}"] = load_driving_motion(cap.root, cap.rig, d.fps)
        except (ValueError, OSError):
            pass
    return AvatarViewer(d, motions, options)


@dataclass(kw_only=True)
class ViewArgs:
    """Open the browser viewer of a trained run (``avatar-train view``)."""

    options: Annotated[ViewerOptions, tyro.conf.arg(name="")] = field(default_factory=ViewerOptions)
    """Port, host and display options of the viewer (flags without a prefix)."""
    run: Path
    """Run directory of ``avatar-train avatar``."""
    motion: Path | None = None
    """Driving motion (capture directory, motion.npz or .bvh); default: the avatar at rest."""
    mode: str = "predictor"
    """Latent source of ``--motion`` (a drive mode; without --motion: the mean latent)."""
    device: str = "cpu"
    """``cpu``, ``cuda[:i]`` or ``auto``."""


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m gsavatar.drive.viewer`` (``avatar-train view``); exit 2 on bad input."""
    args = parse_args(
        lambda: tyro.cli(ViewArgs, args=argv, prog="avatar-train view", description=__doc__), exit_codes=True
    )
    if isinstance(args, int):
        return args
    opts = args.options

    def go() -> None:
        claim_address(opts.host, opts.port, warn=lambda m: None)  # fail in seconds, before loading the run
        v = viewer_from_run(args.run, args.motion, config=DriveConfig(mode=args.mode, device=args.device), options=opts)
        v.serve_forever()

    return run_reporting_errors(go)


if __name__ == "__main__":
    raise SystemExit(main())


def serve_drive_args(args) -> None:
    """``avatar-drive --view``: the viewer of :class:`gsavatar.drive.cli.DriveArgs` until Ctrl-C."""
    opts = ViewerOptions(port=args.port, host=args.host, start_paused=args.start_paused, sh0_only=args.sh0_only)
    claim_address(opts.host, opts.port, warn=lambda m: None)  # fail in seconds, before loading the run
    v = viewer_from_run(
        args.run,
        args.motion,
        config=args.config(),
        options=opts,
        motion_fps=args.motion_fps,
        start=args.start,
        count=args.count,
        split=args.split,
    )
    v.serve_forever()
