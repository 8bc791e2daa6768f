"""Derived datasets written by ``avatar-prep`` (format ``gsavatar-dataset`` v1).

Layout::

    DATASET/dataset.json            {"format", "version", "capture", "stages": {name: record}}
    DATASET/<stage>/...             single-file stages (atlas, pca, points, masks)
    DATASET/<stage>/manifest.json   sharded per-frame stages (posed meshes, UV textures)
    DATASET/<stage>/shard-00003.npz + shard-00003.json  (sidecar: frames, sha256, arrays)

Stage record: ``{"version", "config", "inputs": {name: token}, "files": {relpath: sha256}, "seconds",
"completed"}``. ``inputs`` fingerprints what the stage read (capture files, upstream stages; see
:mod:`gsavatar.prep.inputs`): a stage is complete only while its version, config, inputs and output
checksums all still match. A record without ``inputs`` (written before fingerprints existed) whose
outputs verify is adopted: the current fingerprint is added, nothing recomputed (:func:`adopt_inputs`).
A shard's sidecar is written (atomically) only after its npz, so a shard is complete
iff its sidecar exists, the npz matches the sidecar's checksum and the sidecar's ``inputs_hash``
matches the current inputs of its frames. The manifest is a merge of the sidecars (without their
per-file ``inputs``); ranks of a distributed run each write their own shards and
rank 0 merges. All paths in records and manifests are relative and must stay inside
the dataset root.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import NPZ_READ_ERRORS, atomic_path, atomic_write_json, sha256_file
from gsavatar.utils.jsonio import read_json
from gsavatar.utils.paths import is_inside

DATASET_FORMAT = "gsavatar-dataset"
DATASET_VERSION = 1
SHARDS_FORMAT = "gsavatar-shards"
SHARDS_VERSION = 1

STAGE_VERSIONS: dict[str, int] = {
    "pose-template": 1,
    "uv-atlas": 2,
    "project-uv": 1,
    "fit-pca": 1,
    "sample-points": 1,
    "localize": 1,
}
"""Schema version of each stage's outputs; bump when a stage's file layout changes."""


def safe_join(root: Path, rel: str, file: Path, fld: str) -> Path:
    """``root / rel`` but refuse absolute paths and ``..`` escapes (manifests are untrusted)."""
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts:
        raise SchemaError(file, fld, f"path {rel!r} escapes the dataset root")
    if not is_inside(root / p, root):  # a symlink inside the dataset pointing out
        raise SchemaError(file, fld, f"path {rel!r} escapes the dataset root")
    return (root / p).resolve()


# --------------------------------------------------------------------------- dataset.json
def read_versioned_json(path: Path, fmt: str, version_key: str, version: int) -> dict:
    """Parse a JSON object (strictly: :func:`gsavatar.utils.jsonio.read_json`) whose ``format`` and
    ``version_key`` must match; SchemaError names the field."""
    obj = read_json(path)
    if not isinstance(obj, dict) or obj.get("format") != fmt:
        raise SchemaError(
            path, "format", f"expected {fmt!r}, got {obj.get('format') if isinstance(obj, dict) else obj!r}"
        )
    if obj.get(version_key) != version:
        raise SchemaError(path, version_key, f"unsupported {version_key} {obj.get(version_key)!r} (expected {version})")
    return obj


def read_dataset_json(root: Path) -> dict:
    path = root / "dataset.json"
    if not path.exists():
        return {"format": DATASET_FORMAT, "version": DATASET_VERSION, "capture": None, "stages": {}}
    return read_versioned_json(path, DATASET_FORMAT, "version", DATASET_VERSION)


def dataset_fingerprint(root: Path) -> str:
    """Content identity of a prepared dataset: sha256 over every stage's config and file checksums (not its
    path, timings or completion times). Two preparations of the same capture with the same settings agree;
    another subject's dataset at the same path does not."""
    obj = read_dataset_json(Path(root))
    ident = {name: {"config": st.get("config"), "files": st.get("files")} for name, st in sorted(obj["stages"].items())}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


def inputs_digest(tokens: dict[str, str]) -> str:
    """One sha256 over an input fingerprint ``{name: token}`` (order independent)."""
    return hashlib.sha256(json.dumps(tokens, sort_keys=True).encode()).hexdigest()


def first_changed_input(old: dict[str, str] | None, new: dict[str, str]) -> str | None:
    """Name of the first input (sorted) whose token differs between two fingerprints; None if they agree."""
    old = old or {}
    for k in sorted(set(old) | set(new)):
        if old.get(k) != new.get(k):
            return k
    return None


def record_stage(
    root: Path,
    stage: str,
    config: dict,
    files: list[Path],
    seconds: float,
    capture: Path | None = None,
    inputs: dict[str, str] | None = None,
) -> None:
    """Mark ``stage`` complete in dataset.json with checksums of its files and the fingerprint of its ``inputs``."""
    obj = read_dataset_json(root)
    if capture is not None:
        obj["capture"] = str(Path(capture).resolve())
    obj["stages"][stage] = {
        "version": STAGE_VERSIONS[stage],
        "config": config,
        "inputs": inputs,
        "files": {str(Path(f).resolve().relative_to(root.resolve())): sha256_file(f) for f in files},
        "seconds": round(float(seconds), 3),
        "completed": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    atomic_write_json(root / "dataset.json", obj)


def stage_identity(root: Path, stage: str) -> str | None:
    """What a stage's outputs are a function of: sha256 of its recorded version, config and inputs (None if
    not recorded). Downstream stages fingerprint it instead of the output bytes, which hold zip timestamps."""
    try:
        rec = read_dataset_json(Path(root))["stages"].get(stage)
    except SchemaError:
        return None
    if not isinstance(rec, dict):
        return None
    return inputs_digest({"version": rec.get("version"), "config": rec.get("config"), "inputs": rec.get("inputs")})


NO_INPUTS = "no input fingerprint recorded (prepared by an older gsavatar)"
""":func:`stage_status` of a record written before input fingerprints existed."""


def adopt_inputs(root: Path, stage: str, inputs: dict[str, str]) -> None:
    """Add the ``inputs`` fingerprint to a record written before fingerprints existed (its outputs verify):
    recomputing would change the output bytes, hence :func:`dataset_fingerprint`, and strand every run
    trained on the dataset. Whether the inputs changed before this upgrade cannot be known."""
    obj = read_dataset_json(root)
    obj["stages"][stage]["inputs"] = inputs
    atomic_write_json(root / "dataset.json", obj)


def stage_status(
    root: Path, stage: str, config: dict | None = None, inputs: dict[str, str] | None = None, check_files: bool = True
) -> str | None:
    """None if ``stage`` is complete: recorded with the current version (and ``config``, and ``inputs``
    fingerprint), its files verifying. Otherwise why not, e.g. ``inputs changed (calibration.json)``."""
    try:
        rec = read_dataset_json(root)["stages"].get(stage)
    except SchemaError as e:
        return str(e)
    if not isinstance(rec, dict):
        return "not run yet"
    if rec.get("version") != STAGE_VERSIONS[stage]:
        return f"recorded by stage version {rec.get('version')!r}, this gsavatar writes {STAGE_VERSIONS[stage]}"
    if config is not None and rec.get("config") != json.loads(json.dumps(config)):
        return "config changed"
    if inputs is not None:
        if not isinstance(rec.get("inputs"), dict):
            return NO_INPUTS
        changed = first_changed_input(rec["inputs"], inputs)
        if changed is not None:
            return f"inputs changed ({changed})"
    if check_files:
        files = rec.get("files")
        if not isinstance(files, dict):
            return "no output checksums recorded"
        for rel, digest in files.items():
            p = root / rel
            if not p.is_file() or sha256_file(p) != digest:
                return f"output {rel} missing or changed"
    return None


def stage_complete(
    root: Path, stage: str, config: dict | None = None, check_files: bool = True, inputs: dict[str, str] | None = None
) -> bool:
    """True if ``stage`` is recorded with the current version (and config and inputs), and its files verify."""
    return stage_status(root, stage, config, inputs, check_files) is None


def stage_dir(root: Path, stage: str) -> Path:
    """Folder of a stage's outputs (``fit-pca`` -> ``DATASET/fit_pca``)."""
    return Path(root) / stage.replace("-", "_")


def stage_path(root: Path, stage: str, name: str) -> Path:
    """Path of a stage output file; raises SchemaError if the stage has not been run or the file
    no longer matches the checksum its stage recorded (single-file outputs are small: cheap to hash)."""
    obj = read_dataset_json(root)
    if stage not in obj["stages"]:
        raise SchemaError(
            root / "dataset.json", f"stages.{stage}", f"stage not run yet: run `avatar-prep {stage}` first"
        )
    rel = f"{stage.replace('-', '_')}/{name}"
    path = root / rel
    digest = obj["stages"][stage].get("files", {}).get(rel)
    if digest is not None and path.exists() and sha256_file(path) != digest:
        raise SchemaError(
            path,
            "sha256",
            f"checksum mismatch with dataset.json stages.{stage}: the file is corrupt or was "
            f"changed; re-run `avatar-prep {stage} --force`",
        )
    return path


# --------------------------------------------------------------------------- shards
@dataclass
class ShardSpec:
    index: int
    frames: list[int]


def plan_shards(frames: list[int], shard_size: int) -> list[ShardSpec]:
    if shard_size <= 0:
        raise ValueError(f"shard_size must be > 0, got {shard_size}")
    return [ShardSpec(i, frames[s : s + shard_size]) for i, s in enumerate(range(0, len(frames), shard_size))]


class ShardStore:
    """Per-frame arrays of one stage, written as atomic, checksummed npz shards."""

    def __init__(self, directory: Path, stage: str) -> None:
        self.dir = Path(directory)
        self.stage = stage

    def npz(self, index: int) -> Path:
        return self.dir / f"shard-{index:05d}.npz"

    def sidecar(self, index: int) -> Path:
        return self.dir / f"shard-{index:05d}.json"

    def read_sidecar(self, index: int) -> dict | None:
        """The sidecar of shard ``index``, or None when it is missing or unreadable (= not written)."""
        sc = self.sidecar(index)
        if not sc.is_file():
            return None
        try:
            meta = read_json(sc)
        except SchemaError:
            return None
        return meta if isinstance(meta, dict) else None

    def is_complete(self, spec: ShardSpec, config_hash: str, inputs_hash: str | None = None) -> bool:
        """Sidecar and npz present and agreeing, same frames, config and (if given) inputs fingerprint."""
        meta = self.read_sidecar(spec.index)
        if meta is None or not self.npz(spec.index).exists():
            return False
        return (
            meta.get("frames") == spec.frames
            and meta.get("config_hash") == config_hash
            and meta.get("schema_version") == SHARDS_VERSION
            and (inputs_hash is None or meta.get("inputs_hash") == inputs_hash)
            and sha256_file(self.npz(spec.index)) == meta.get("sha256")
        )

    def changed_input(self, spec: ShardSpec, inputs: dict[str, str]) -> str | None:
        """First input of shard ``spec`` that differs from what its sidecar recorded (None: same, or no sidecar)."""
        meta = self.read_sidecar(spec.index)
        if meta is None or not isinstance(meta.get("inputs"), dict):
            return None
        return first_changed_input(meta["inputs"], inputs)

    def write(
        self, spec: ShardSpec, arrays: dict[str, np.ndarray], config_hash: str, inputs: dict[str, str] | None = None
    ) -> None:
        """Write shard npz then its sidecar, both atomically (sidecar last = commit point). ``inputs``: the
        fingerprint of what the shard's frames were computed from (recorded with its digest)."""
        for k, a in arrays.items():
            if a.shape[0] != len(spec.frames):
                raise ValueError(f"shard {spec.index}: array {k!r} has {a.shape[0]} rows for {len(spec.frames)} frames")
        self.dir.mkdir(parents=True, exist_ok=True)
        npz = self.npz(spec.index)
        with atomic_path(npz, suffix=".npz") as tmp:
            np.savez(tmp, frames=np.asarray(spec.frames, dtype=np.int64), **arrays)
        atomic_write_json(
            self.sidecar(spec.index),
            {
                "index": spec.index,
                "frames": spec.frames,
                "file": npz.name,
                "sha256": sha256_file(npz),
                "config_hash": config_hash,
                "schema_version": SHARDS_VERSION,
                "arrays": {k: [list(a.shape[1:]), str(a.dtype)] for k, a in arrays.items()},
                **({"inputs_hash": inputs_digest(inputs), "inputs": inputs} if inputs is not None else {}),
            },
        )

    def merge_manifest(self, specs: list[ShardSpec], extra: dict | None = None) -> Path:
        """Merge sidecars into manifest.json; raises if any planned shard is missing."""
        shards = []
        for s in specs:
            sc = self.sidecar(s.index)
            meta = self.read_sidecar(s.index)
            if meta is None:
                raise SchemaError(sc, "", f"shard {s.index} of stage {self.stage!r} is missing; re-run the stage")
            shards.append({k: v for k, v in meta.items() if k != "inputs"})  # per-file detail stays in the sidecar
        path = self.dir / "manifest.json"
        atomic_write_json(
            path,
            {
                "format": SHARDS_FORMAT,
                "schema_version": SHARDS_VERSION,
                "stage": self.stage,
                "num_frames": sum(len(s.frames) for s in specs),
                "shards": shards,
                **(extra or {}),
            },
        )
        return path


def read_manifest(directory: Path) -> dict:
    path = Path(directory) / "manifest.json"
    if not path.exists():
        raise SchemaError(path, "", "manifest not found; run the stage first")
    return read_versioned_json(path, SHARDS_FORMAT, "schema_version", SHARDS_VERSION)


class ShardReader:
    """Random access to per-frame arrays of a sharded stage (loads one shard at a time)."""

    def __init__(self, directory: Path, verify: bool = False) -> None:
        self.dir = Path(directory)
        self.manifest = read_manifest(self.dir)
        self.where: dict[int, tuple[int, int]] = {}
        mpath = self.dir / "manifest.json"
        for si, s in enumerate(self.manifest["shards"]):
            p = safe_join(self.dir, s["file"], mpath, f"shards[{si}].file")
            if verify and sha256_file(p) != s["sha256"]:
                raise SchemaError(p, "sha256", "checksum mismatch: shard is corrupt; re-run the stage")
            for k, f in enumerate(s["frames"]):
                self.where[int(f)] = (si, k)
        self._cache: tuple[int, dict[str, np.ndarray]] | None = None
        self._verified: set[int] = set()

    @property
    def frames(self) -> list[int]:
        return sorted(self.where)

    def get(self, frame: int) -> dict[str, np.ndarray]:
        if frame not in self.where:
            raise KeyError(f"frame {frame} not in {self.dir}")
        si, k = self.where[frame]
        if self._cache is None or self._cache[0] != si:
            s = self.manifest["shards"][si]
            p = safe_join(self.dir, s["file"], self.dir / "manifest.json", f"shards[{si}].file")
            if not p.exists():
                raise SchemaError(p, "", "shard listed in manifest.json is missing; re-run the stage")
            data = p.read_bytes()
            # each shard is checked once per reader, when first read (the bytes are in memory anyway)
            if si not in self._verified:
                if hashlib.sha256(data).hexdigest() != s["sha256"]:
                    raise SchemaError(
                        p, "sha256", "checksum mismatch with manifest.json: shard is corrupt; re-run the stage"
                    )
                self._verified.add(si)
            try:
                with np.load(io.BytesIO(data), allow_pickle=False) as z:
                    self._cache = (si, {n: z[n] for n in z.files})
            except NPZ_READ_ERRORS as e:
                raise SchemaError(p, "", f"cannot read shard: {e}") from None
        return {n: a[k] for n, a in self._cache[1].items() if n != "frames"}


# --------------------------------------------------------------------------- verify
def verify_dataset(root: str | Path) -> list[str]:
    """Check every recorded file and shard checksum. Returns a list of problems (empty = ok)."""
    root = Path(root)
    problems: list[str] = []
    djson = root / "dataset.json"
    try:
        obj = read_dataset_json(root)
    except SchemaError as e:
        return [str(e)]
    if not djson.exists():
        return [f"{djson}: not found (not a gsavatar dataset)"]
    for stage, rec in obj["stages"].items():
        if rec.get("version") != STAGE_VERSIONS.get(stage):
            problems.append(f"{djson}: stages.{stage}.version {rec.get('version')} != {STAGE_VERSIONS.get(stage)}")
        for rel, digest in rec.get("files", {}).items():
            try:
                p = safe_join(root, rel, djson, f"stages.{stage}.files")
            except SchemaError as e:
                problems.append(str(e))
                continue
            if not p.exists():
                problems.append(f"{p}: missing (recorded by stage {stage})")
            elif sha256_file(p) != digest:
                problems.append(f"{p}: checksum mismatch (recorded by stage {stage})")
    for mpath in sorted(root.glob("*/manifest.json")):
        try:
            m = read_manifest(mpath.parent)
        except SchemaError as e:
            problems.append(str(e))
            continue
        for si, s in enumerate(m["shards"]):
            try:
                p = safe_join(mpath.parent, s["file"], mpath, f"shards[{si}].file")
            except SchemaError as e:
                problems.append(str(e))
                continue
            if not p.exists():
                problems.append(f"{p}: missing shard")
            elif sha256_file(p) != s["sha256"]:
                problems.append(f"{p}: checksum mismatch")
    return problems
