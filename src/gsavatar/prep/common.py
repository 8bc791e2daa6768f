"""Arguments shared by every ``avatar-prep`` stage, and the stage bookkeeping around them."""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from pathlib import Path

from gsavatar.data_schema import Capture, load_capture
from gsavatar.data_schema.dataset import ShardStore, read_dataset_json, record_stage, stage_complete
from gsavatar.prep.sharding import RankInfo, barrier, config_hash, init_distributed, parse_shard_arg, run_sharded


@dataclass
class StageArgs:
    capture: Path
    """Capture directory (format v1)."""
    out: Path
    """Output dataset directory (created if missing)."""
    force: bool = False
    """Recompute even if the stage's outputs are complete and valid."""
    shard: str | None = None
    """Process only shards ``i/N`` (SLURM arrays). Under torchrun, RANK/WORLD_SIZE are used."""
    workers: int = 0
    """Local worker processes for per-frame stages (0 = all cores)."""
    shard_size: int = 16
    """Frames per shard of per-frame outputs."""

    @property
    def num_workers(self) -> int:
        return self.workers if self.workers > 0 else (os.cpu_count() or 1)


TIMINGS: dict[str, float] = {}
"""Seconds per stage in this process, printed as a summary by the CLI."""


def stage_dir(root: Path, stage: str) -> Path:
    return Path(root) / stage.replace("-", "_")


def open_capture(args: StageArgs) -> Capture:
    return load_capture(args.capture)


def stage_config(cfg) -> dict:
    """JSON-able config of a stage (dataclass or dict), recorded in dataset.json."""
    d = dataclasses.asdict(cfg) if dataclasses.is_dataclass(cfg) else dict(cfg)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def run_single_file_stage(stage: str, args: StageArgs, config: dict, produce) -> bool:
    """Run ``produce() -> list[Path]`` unless the stage is complete; record it. Returns True if run."""
    root = Path(args.out)
    read_dataset_json(root)  # a dataset of another format/version is refused before anything is written
    root.mkdir(parents=True, exist_ok=True)
    if not args.force and stage_complete(root, stage, config):
        print(f"[{stage}] complete, skipping (use --force to recompute)")
        return False
    info = parse_shard_arg(args.shard)
    if not info.is_main:  # single-file stages are cheap: rank 0 does them
        return False
    t0 = time.perf_counter()
    files = produce()
    dt = time.perf_counter() - t0
    record_stage(root, stage, config, files, dt, capture=args.capture)
    TIMINGS[stage] = TIMINGS.get(stage, 0.0) + dt
    print(f"[{stage}] done in {dt:.1f}s -> {stage_dir(root, stage)}")
    return True


def run_frame_stage(stage: str, args: StageArgs, config: dict, frames: list[int], compute) -> bool:
    """Run a sharded per-frame stage (resumable, multi-rank). Returns True if the manifest is complete."""
    root = Path(args.out)
    read_dataset_json(root)  # a dataset of another format/version is refused before anything is written
    root.mkdir(parents=True, exist_ok=True)
    if not args.force and stage_complete(root, stage, config):
        print(f"[{stage}] complete, skipping (use --force to recompute)")
        return True
    info: RankInfo = parse_shard_arg(args.shard)
    init_distributed(info)
    store = ShardStore(stage_dir(root, stage), stage)
    cfg = dict(config, shard_size=args.shard_size)
    if args.force:
        for p in store.dir.glob("shard-*.json") if store.dir.exists() else []:
            p.unlink()
    t0 = time.perf_counter()
    specs, done = run_sharded(store, frames, args.shard_size, cfg, compute, info,
                              workers=args.num_workers, label=f"[{stage}] rank {info.rank}/{info.world}")
    barrier(info)
    dt = time.perf_counter() - t0
    TIMINGS[stage] = TIMINGS.get(stage, 0.0) + dt
    if info.torchrun:
        done = all(store.is_complete(s, config_hash(cfg)) for s in specs)
    # torchrun: rank 0 merges after the barrier; --shard i/N: whoever finds every shard done merges.
    if done and (info.is_main or not info.torchrun):
        manifest = store.merge_manifest(specs, {"config": cfg})
        files = [manifest] + [store.npz(s.index) for s in specs]
        record_stage(root, stage, config, files, dt, capture=args.capture)
        print(f"[{stage}] {len(frames)} frames in {len(specs)} shards, {dt:.1f}s -> {store.dir}")
    elif not done:
        print(f"[{stage}] rank {info.rank}/{info.world}: my shards are written; the manifest is merged once all ranks finish "
              f"(re-run without --shard to merge)")
    barrier(info)
    return done
