"""Training steps/s of a preset: this checkout's code against another commit's, in one run.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_train_step.py --dataset out/demo/dataset \
        --baseline f1bc3d8 --steps 40 --repeats 2 --threads 1

Both codes train the same dataset and preset with the correctives on from step 0 (the expensive
part of a step) in fresh subprocesses, alternating old/new ``--repeats`` times so they share the
machine's load; each measurement times ``--steps`` steps after ``--warmup`` steps. The new code's
view cache (decoded images kept in memory) is filled before timing, which is the steady state of
a run after its first pass over the views; ``--cold`` times it without (first pass).
Prints one line per measurement and the median ratio new/old, of wall-clock steps/s and of steps per
CPU-second of the process (the latter is less sensitive to other jobs on a shared box; with
``--threads 1`` both measure the same work). The baseline's source comes from
``git worktree`` into a temporary folder (removed at the end).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import json, sys, time, tempfile, inspect
import torch
try:
    from gsavatar.runs.config import TrainConfig
except ImportError:  # code before the runs/ package (e.g. f1bc3d8)
    from gsavatar.train.config import TrainConfig
from gsavatar.train.trainer import Trainer
a = json.loads(sys.argv[1])
kw = dict(dataset=a["dataset"], out=tempfile.mkdtemp(prefix="bench_step_"), preset=a["preset"], lpips="off",
          log_every=10**9)
fields = inspect.signature(TrainConfig).parameters
sched = dict(correctives_step=0, checkpoint_every=10**9)
if "schedule" in fields:  # the config tree (runs/config.py Schedule)
    from gsavatar.runs.config import Schedule
    kw["schedule"] = Schedule(**sched)
else:  # code before it: flat schedule fields
    kw.update(sched)
tr = Trainer(TrainConfig(**kw))
if "cache_views" in fields and not a["cold"]:
    for i in range(len(tr.data)):  # fill the view cache: the steady state after one pass over the views
        tr.data[i]
tr.cfg = type(tr.cfg)(**{**tr.cfg.__dict__, "max_steps_this_run": a["warmup"]})
tr.train()
tr.cfg = type(tr.cfg)(**{**tr.cfg.__dict__, "max_steps_this_run": a["steps"]})
t0, c0 = time.perf_counter(), time.process_time()
tr.train()
dt, dc = time.perf_counter() - t0, time.process_time() - c0
print(json.dumps({"steps_per_s": a["steps"] / dt, "cpu_steps_per_s": a["steps"] / dc,
                  "threads": torch.get_num_threads()}))
"""


def measure(src: Path, args: argparse.Namespace) -> tuple[float, float]:
    """(steps per wall-clock second, steps per CPU second of the process)"""
    env = {**os.environ, "PYTHONPATH": str(src), "OMP_NUM_THREADS": str(args.threads)}
    payload = json.dumps(
        {
            "dataset": str(args.dataset),
            "preset": args.preset,
            "steps": args.steps,
            "warmup": args.warmup,
            "cold": args.cold,
        }
    )
    r = subprocess.run([sys.executable, "-c", CHILD, payload], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"benchmark child failed ({src}):\n{r.stderr[-3000:]}")
    out = json.loads(r.stdout.strip().splitlines()[-1])
    return out["steps_per_s"], out["cpu_steps_per_s"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--baseline", default="HEAD", help="git revision of the old code")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cold", action="store_true", help="do not pre-fill the new code's view cache")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args()
    repo = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory(prefix="bench_base_") as tmp:
        wt = Path(tmp) / "base"
        subprocess.run(
            ["git", "-C", str(repo), "worktree", "add", "--detach", str(wt), args.baseline],
            check=True,
            capture_output=True,
        )
        try:
            old, new = [], []
            for i in range(args.repeats):
                old.append(measure(wt / "src", args))
                print(
                    f"[bench] old ({args.baseline}) run {i}: {old[-1][0]:.3f} steps/s, "
                    f"{old[-1][1]:.3f} steps per CPU-second",
                    flush=True,
                )
                new.append(measure(repo / "src", args))
                print(
                    f"[bench] new (working tree) run {i}: {new[-1][0]:.3f} steps/s, "
                    f"{new[-1][1]:.3f} steps per CPU-second",
                    flush=True,
                )
        finally:
            subprocess.run(["git", "-C", str(repo), "worktree", "remove", "--force", str(wt)], capture_output=True)
    med = [[statistics.median(r[k] for r in runs) for k in (0, 1)] for runs in (old, new)]
    res = {
        "preset": args.preset,
        "threads": args.threads,
        "steps": args.steps,
        "baseline": args.baseline,
        "old_steps_per_s": med[0][0],
        "new_steps_per_s": med[1][0],
        "ratio": med[1][0] / med[0][0],
        "old_steps_per_cpu_s": med[0][1],
        "new_steps_per_cpu_s": med[1][1],
        "cpu_ratio": med[1][1] / med[0][1],
        "cache": "cold" if args.cold else "warm",
    }
    print(json.dumps(res))
    if args.json:
        args.json.write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
