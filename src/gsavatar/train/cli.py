"""``avatar-train``: train the Gaussian avatar (and, later, the appearance predictor).

avatar-train avatar --dataset ds --out runs/tiny --preset tiny
avatar-train avatar --dataset ds --out runs/mmlps --variant mmlps_dagger     # the baseline
avatar-train eval --run runs/tiny
avatar-train export --run runs/tiny --frame 0 --out frame0.ply --up-axis -y   # -y: 3DGS viewers
avatar-train view --run runs/tiny               # the avatar at rest in the browser viewer
avatar-train predictor --run runs/tiny          # the autoregressive appearance predictor
"""

from __future__ import annotations

import json
import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro

from gsavatar.models.ply import export_frame_ply
from gsavatar.models.config import VARIANTS, PresetName
from gsavatar.runs.config import TrainConfig, model_config, preset_config
from gsavatar.runs.load import load_run
from gsavatar.train.predictor_cli import Predictor
from gsavatar.train.runs import evaluate_run, posed_output, render_turntable, train_and_evaluate
from gsavatar.utils.cli import parse_args, run_reporting_errors
from gsavatar.utils.outdir import claim_output_file, record_output_file
from gsavatar.utils.paths import add_output_root


@dataclass
class Avatar:
    """Train the avatar (encoder latents) on a prepared dataset; resumes from the run's latest checkpoint.
    Every model and schedule field is a flag (``--model.hidden 64 64``, ``--schedule.correctives-step 200``),
    starting from the ``--preset``'s values with the ``--variant`` applied."""

    train: Annotated[TrainConfig, tyro.conf.arg(name="")]
    """The run's configuration (flags without a prefix; ``--model.*``, ``--schedule.*``, ``--losses.*``)."""
    evaluate: bool = True
    """Evaluate held-out cameras of training frames (and test frames) at the end."""
    force: bool = False
    """Train into a non-empty ``out`` that is not a gsavatar run (refused otherwise, so a user's
    ``config.json`` or ``metrics.jsonl`` is never overwritten). A run of ours is resumed without it."""

    def execute(self) -> None:
        add_output_root(self.train.out)  # every write of this command stays in the run (cleared when it ends)
        train_and_evaluate(self.train, self.evaluate, force_out=self.force)


def _preset_default(argv: list[str]) -> Avatar:
    """The default instance ``avatar-train avatar`` parses into: the ``--preset`` and ``--variant`` given in
    ``argv`` (read first), their model and schedule spelt out, so every ``--model.*`` flag starts from the
    values that apply and ``--help`` shows them. Unknown names are left to tyro, which lists the choices."""

    def value(flag: str, default: str, choices: tuple[str, ...]) -> str:
        for i, a in enumerate(argv):
            got = (
                a.split("=", 1)[1]
                if a.startswith(flag + "=")
                else argv[i + 1]
                if a == flag and i + 1 < len(argv)
                else None
            )
            if got is not None:
                return got if got in choices else default
        return default

    preset = value("--preset", "tiny", typing.get_args(PresetName))
    variant = value("--variant", "ours", tuple(VARIANTS))
    # dataset/out are required flags: tyro still asks for them (MISSING), the defaults only fill the rest
    train = preset_config(tyro.MISSING, tyro.MISSING, preset, variant)  # type: ignore[arg-type]
    return Avatar(train=train)


@dataclass
class Eval:
    """Evaluate a trained run: held-out cameras of training frames, and held-out frames."""

    run: Path
    """Run directory written by ``avatar-train avatar``."""
    eval_frames: int = 8
    """Frames per split (evenly spaced)."""
    ag_lpips: Literal["auto", "on", "off"] = "auto"
    """LPIPS (VGG and Alex) of the field's ``ag`` protocol: ``auto`` = on CUDA only (5-15 s per view on a CPU)."""

    def execute(self) -> None:
        add_output_root(self.run)  # eval images and metrics stay in the run
        print(json.dumps(evaluate_run(self.run, self.eval_frames, ag_lpips=self.ag_lpips), indent=1))


@dataclass
class Export:
    """Export the posed avatar of one frame as a standard 3DGS PLY."""

    run: Path
    """Run directory."""
    frame: int = 0
    """Capture frame whose pose (and projected texture) is used."""
    out: Path = Path("avatar.ply")
    """Output PLY path."""
    up_axis: Literal["y", "-y", "z"] = "y"
    """Up axis of the file: ``y`` (ours, the capture's world), ``-y`` (COLMAP / 3DGS viewers: SuperSplat, SIBR) or
    ``z`` (Z-up tools); positions, rotations and SH rotated together, docs/drive.md."""
    force: bool = False
    """Replace an existing ``out`` that is not a gsavatar PLY (refused otherwise)."""

    def execute(self) -> None:
        claim_output_file(self.out, "ply", self.force)
        add_output_root(Path(self.out).parent)  # the one file named, nothing beside it elsewhere
        net, scene, cfg, _ = load_run(self.run)
        if not 0 <= self.frame < scene.capture.num_frames:
            raise ValueError(f"frame must be in [0, {scene.capture.num_frames}), got {self.frame}")
        export_frame_ply(self.out, posed_output(net, scene, self.frame, model_config(cfg).sh_degree), 0, self.up_axis)
        print(f"wrote {self.out}")


@dataclass
class Viewer:
    """Open the browser viewer (viser, http://127.0.0.1:PORT) of a trained run: the avatar at rest, or driven
    by ``--motion``. Runs ``python -m gsavatar.drive.viewer`` (the viewer lives in the drive layer)."""

    run: Path
    """Run directory."""
    motion: Path | None = None
    """Driving motion (capture directory, motion.npz, .bvh); default: the rest pose, mean latent."""
    port: int = 8080
    """Port of the page."""
    host: str = "127.0.0.1"
    """Interface to bind (default: this machine only)."""
    start_paused: bool = False
    """Open paused."""
    sh0_only: bool = False
    """Colour from SH band 0 only (view independent)."""

    def execute(self) -> None:
        import subprocess
        import sys

        cmd = [
            sys.executable,
            "-m",
            "gsavatar.drive.viewer",
            "--run",
            str(self.run),
            "--port",
            str(self.port),
            "--host",
            self.host,
        ]
        cmd += ["--motion", str(self.motion)] if self.motion is not None else []
        cmd += ["--start-paused"] * self.start_paused + ["--sh0-only"] * self.sh0_only
        rc = subprocess.call(cmd)
        if rc:
            raise SystemExit(rc)


@dataclass
class Turntable:
    """Render an orbit around the posed avatar of one frame as an mp4."""

    run: Path
    """Run directory."""
    out: Path = Path("turntable.mp4")
    """Output video."""
    frame: int = 0
    """Capture frame whose pose and texture are used."""
    views: int = 48
    """Frames of the orbit."""
    size: int = 256
    """Image size in pixels (square)."""
    force: bool = False
    """Replace an existing ``out`` that is not a gsavatar video (refused otherwise)."""

    def execute(self) -> None:
        claim_output_file(self.out, "video", self.force)
        add_output_root(Path(self.out).parent)
        print(f"wrote {render_turntable(self.run, self.out, self.frame, self.views, self.size)}")
        record_output_file(self.out, "video")


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    commands = {
        "avatar": Avatar,
        "eval": Eval,
        "export": Export,
        "turntable": Turntable,
        "predictor": Predictor,
        "view": Viewer,
    }
    if args[:1] == ["avatar"]:  # parsed into the --preset's default instance (_preset_default)
        cmd = parse_args(
            lambda: tyro.cli(Avatar, default=_preset_default(args[1:]), args=args[1:], prog="avatar-train avatar")
        )
    else:
        cmd = parse_args(
            lambda: tyro.extras.subcommand_cli_from_dict(commands, prog="avatar-train", description=__doc__, args=args)
        )
    if isinstance(cmd, int):  # a nested config refused a value (named on stderr)
        return cmd
    try:
        return run_reporting_errors(cmd.execute)  # one method name: Eval, Predictor... have a `run` field
    finally:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


if __name__ == "__main__":
    raise SystemExit(main())
