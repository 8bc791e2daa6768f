"""Arguments shared by every ``avatar-prep`` stage, and the stage bookkeeping around them."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from gsavatar.data_schema import Capture, load_capture
from gsavatar.data_schema.dataset import (
    NO_INPUTS,
    ShardStore,
    adopt_inputs,
    inputs_digest,
    plan_shards,
    read_dataset_json,
    record_stage,
    stage_dir,
    stage_status,
)
from gsavatar.prep.sharding import RankInfo, barrier, config_hash, init_distributed, parse_shard_arg, run_sharded
from gsavatar.utils.cli import set_resume_hint
from gsavatar.utils.jsonio import config_to_json
from gsavatar.utils.outdir import claim_output_dir

FRAME_FILES = "per-frame files"
"""Key of the recorded fingerprint that stands for every per-frame file (their tokens live in the shards' sidecars)."""


@dataclass
class StageArgs:
    capture: Path
    """Capture directory (format v1)."""
    out: Path
    """Output dataset directory (created if missing)."""
    force: bool = False
    """Recompute even if the stage's outputs are complete and valid (a stage whose inputs changed is
    recomputed without it)."""
    force_out: bool = False
    """Write into a non-empty ``out`` that is not a gsavatar dataset (refused otherwise, so a user's files
    are never overwritten). Separate from ``--force``, which only means recompute."""
    shard: str | None = None
    """Process only shards ``i/N`` (SLURM arrays). Under torchrun, RANK/WORLD_SIZE are used."""
    workers: int = 0
    """Local worker processes for per-frame stages (0 = all cores)."""
    shard_size: int = 16
    """Frames per shard of per-frame outputs."""
    timings: tyro.conf.Suppress[dict[str, float]] = field(default_factory=dict)
    """Seconds per stage run by this command (not an option: the CLI prints them as a summary)."""

    @property
    def num_workers(self) -> int:
        return self.workers if self.workers > 0 else (os.cpu_count() or 1)


def open_capture(args: StageArgs) -> Capture:
    return load_capture(args.capture)


def stage_config(cfg) -> dict:
    """JSON-able config of a stage (dataclass or dict), recorded in dataset.json."""
    return config_to_json(cfg if dataclasses.is_dataclass(cfg) else dict(cfg))


def open_dataset(args: StageArgs) -> Path:
    """The dataset folder of a stage, claimed before anything is written (refuses a foreign non-empty
    folder unless ``--force-out``, and a dataset of another format/version)."""
    root = Path(args.out)
    read_dataset_json(root)  # first: a dataset of another format/version is refused before anything is written
    claim_output_dir(root, "dataset", args.force_out, "--force-out", register=True)
    set_resume_hint("re-run the same command to resume: finished stages and shards are kept")
    return root


def _should_run(
    stage: str, args: StageArgs, root: Path, config: dict, inputs: dict[str, str], status: str | None
) -> bool:
    """Whether to (re)compute, given :func:`stage_status`; says why when a recorded stage is recomputed.
    A record of an older gsavatar without an input fingerprint, whose outputs verify, adopts the current one."""
    if status == NO_INPUTS and not args.force and stage_status(root, stage, config) is None:
        if parse_shard_arg(args.shard).is_main:
            adopt_inputs(root, stage, inputs)
        print(f"[{stage}] complete (recorded before input fingerprints: the current inputs are adopted), skipping")
        return False
    if status is None and not args.force:
        print(f"[{stage}] complete, skipping (use --force to recompute)")
        return False
    if status is not None and status != "not run yet":
        print(f"[{stage}] {status}, recomputing")
    return True


def run_single_file_stage(stage: str, args: StageArgs, config: dict, produce, inputs: dict[str, str]) -> bool:
    """Run ``produce() -> list[Path]`` unless the stage is complete with these ``inputs``
    (:mod:`gsavatar.prep.inputs`); record it. Returns True if run."""
    root = open_dataset(args)
    if not _should_run(stage, args, root, config, inputs, stage_status(root, stage, config, inputs)):
        return False
    info = parse_shard_arg(args.shard)
    if not info.is_main:  # single-file stages are cheap: rank 0 does them
        return False
    t0 = time.perf_counter()
    files = produce()
    dt = time.perf_counter() - t0
    record_stage(root, stage, config, files, dt, capture=args.capture, inputs=inputs)
    args.timings[stage] = args.timings.get(stage, 0.0) + dt
    print(f"[{stage}] done in {dt:.1f}s -> {stage_dir(root, stage)}")
    return True


def run_frame_stage(
    stage: str,
    args: StageArgs,
    config: dict,
    frames: list[int],
    compute,
    inputs: dict[str, str],
    frame_inputs: Callable[[list[int]], dict[str, str]] | None = None,
) -> bool:
    """Run a sharded per-frame stage (resumable, multi-rank). Returns True if the manifest is complete.

    ``inputs``: fingerprint of what every frame reads; ``frame_inputs(frames)``: of the per-frame files
    (images, masks). A shard whose fingerprint changed is recomputed, the others are resumed."""
    root = open_dataset(args)
    store = ShardStore(stage_dir(root, stage), stage)
    shard_inputs = {
        s.index: {**inputs, **(frame_inputs(s.frames) if frame_inputs else {})}
        for s in plan_shards(frames, args.shard_size)
    }
    recorded = dict(inputs)
    if frame_inputs is not None:
        recorded[FRAME_FILES] = inputs_digest({k: v for t in shard_inputs.values() for k, v in t.items()})
    status = stage_status(root, stage, config, recorded)
    if status == f"inputs changed ({FRAME_FILES})":  # name the file, from the shards' sidecars
        changed = (store.changed_input(s, shard_inputs[s.index]) for s in plan_shards(frames, args.shard_size))
        status = f"inputs changed ({next((c for c in changed if c), FRAME_FILES)})"
    if not _should_run(stage, args, root, config, recorded, status):
        return True
    info: RankInfo = parse_shard_arg(args.shard)
    init_distributed(info)
    cfg = dict(config, shard_size=args.shard_size)
    if args.force:
        for p in store.dir.glob("shard-*.json") if store.dir.exists() else []:
            p.unlink()
    t0 = time.perf_counter()
    specs, done = run_sharded(
        store,
        frames,
        args.shard_size,
        cfg,
        compute,
        info,
        workers=args.num_workers,
        label=f"[{stage}] rank {info.rank}/{info.world}",
        shard_inputs=shard_inputs,
    )
    barrier(info)
    dt = time.perf_counter() - t0
    args.timings[stage] = args.timings.get(stage, 0.0) + dt
    if info.torchrun:
        done = all(store.is_complete(s, config_hash(cfg), inputs_digest(shard_inputs[s.index])) for s in specs)
    # torchrun: rank 0 merges after the barrier; --shard i/N: whoever finds every shard done merges.
    if done and (info.is_main or not info.torchrun):
        manifest = store.merge_manifest(specs, {"config": cfg})
        files = [manifest] + [store.npz(s.index) for s in specs]
        record_stage(root, stage, config, files, dt, capture=args.capture, inputs=recorded)
        print(f"[{stage}] {len(frames)} frames in {len(specs)} shards, {dt:.1f}s -> {store.dir}")
    elif not done:
        print(
            f"[{stage}] rank {info.rank}/{info.world}: my shards are written; "
            f"the manifest is merged once all ranks finish "
            f"(re-run without --shard to merge)"
        )
    barrier(info)
    return done
