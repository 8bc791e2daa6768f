"""Running a per-frame stage over shards: resumable, parallel on local cores, splittable
across ranks (``torchrun`` with gloo, or ``--shard i/N`` for SLURM arrays).

A rank processes the shards ``index % world == rank``. Under torchrun all ranks meet
at a barrier and rank 0 merges the manifest; with ``--shard i/N`` there is no
barrier, so the manifest is merged by whichever invocation finds every shard
complete (e.g. a final run without ``--shard``).
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from gsavatar.data_schema.dataset import ShardSpec, ShardStore, inputs_digest, plan_shards
from gsavatar.utils.progress import progress_bar


@dataclass(frozen=True)
class RankInfo:
    rank: int
    world: int
    torchrun: bool

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def parse_shard_arg(shard: str | None) -> RankInfo:
    """``"i/N"`` -> rank i of N; ``None`` -> torchrun's RANK/WORLD_SIZE if set, else 0/1."""
    if shard:
        try:
            i, n = (int(x) for x in shard.split("/"))
        except ValueError:
            raise ValueError(f"--shard must look like i/N (e.g. 0/4), got {shard!r}") from None
        if not 0 <= i < n:
            raise ValueError(f"--shard {shard}: need 0 <= i < N")
        return RankInfo(i, n, False)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        return RankInfo(int(os.environ.get("RANK", "0")), world, True)
    return RankInfo(0, 1, False)


def init_distributed(info: RankInfo) -> None:
    if info.torchrun:
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group("gloo")


def barrier(info: RankInfo) -> None:
    if info.torchrun:
        import torch.distributed as dist

        dist.barrier()


def config_hash(config: dict) -> str:
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()[:16]


def _run_one(
    fn: Callable[[list[int]], dict[str, np.ndarray]],
    store: ShardStore,
    spec: ShardSpec,
    chash: str,
    inputs: dict[str, str] | None = None,
) -> int:
    store.write(spec, fn(spec.frames), chash, inputs)
    return len(spec.frames)


def run_sharded(
    store: ShardStore,
    frames: list[int],
    shard_size: int,
    config: dict,
    compute: Callable[[list[int]], dict[str, np.ndarray]],
    info: RankInfo,
    workers: int = 1,
    label: str = "",
    shard_inputs: dict[int, dict[str, str]] | None = None,
) -> tuple[list[ShardSpec], bool]:
    """Compute the missing shards of this rank. Returns (all specs, whether all are complete).

    ``compute`` maps a list of frames to arrays with a leading frame axis; with
    ``workers > 1`` it must be picklable (a module-level function or functools.partial).
    ``shard_inputs``: input fingerprint per shard index (:mod:`gsavatar.prep.inputs`); a shard whose
    sidecar recorded another one is recomputed, not resumed.
    """
    chash = config_hash(config)
    specs = plan_shards(frames, shard_size)
    tokens = shard_inputs or {}
    ihash = {i: inputs_digest(t) for i, t in tokens.items()}
    mine = [s for s in specs if s.index % info.world == info.rank]
    todo = [s for s in mine if not store.is_complete(s, chash, ihash.get(s.index))]
    n_frames = sum(len(s.frames) for s in todo)
    with progress_bar(f"{label} ({len(mine) - len(todo)}/{len(mine)} shards done)", total=n_frames) as bar:
        if workers > 1 and len(todo) > 1:
            # spawn, not fork: a fork after torch/open3d started their thread pools can deadlock
            with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as ex:
                futs = [ex.submit(_run_one, compute, store, s, chash, tokens.get(s.index)) for s in todo]
                for f in futs:
                    bar.advance(f.result())
        else:
            for s in todo:
                bar.advance(_run_one(compute, store, s, chash, tokens.get(s.index)))
    done = all(store.is_complete(s, chash, ihash.get(s.index)) for s in specs)
    return specs, done
