"""The import rule of docs/architecture.md: a gsavatar module imports its own package or packages of
lower layers, never a higher layer or a sibling of its own layer.

Every import statement counts, at module level and inside functions (a deferred import hides the graph,
it does not change it), plus ``importlib.import_module("gsavatar...")`` with a literal name.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

LAYERS: dict[str, int] = {
    "utils": 0,  # files, JSON, CLI helpers, SchemaError: imports no other gsavatar package
    "geometry": 1,  # rotations, skinning, cameras, meshes: math on arrays
    "data_schema": 2,  # every artifact type with its load/save, the prepared-dataset reader
    "render": 3,  # Gaussian rasterization
    "metrics": 3,  # image and temporal metrics, LPIPS
    "motion": 3,  # BVH reading, retargeting, frame-rate resampling
    "models": 4,  # model math and assembly (AvatarNet)
    "runs": 5,  # a trained run: config, checkpoints, load_run, render_views
    "prep": 6,
    "synth": 6,
    "fitting": 6,  # body poses from multi-view 2D keypoints (avatar-prep fit-body)
    "importers": 6,  # real capture sources (SMPL-X bodies, THuman4.0/AvatarReX/ActorsHQ layouts)
    "train": 6,
    "drive": 7,
}
"""Layer of each subpackage of gsavatar (low to high). ``gsavatar/__init__.py`` itself imports none."""

ALLOWED: dict[tuple[str, str], str] = {
    (
        "gsavatar.prep.cli",
        "gsavatar.synth.cli",
    ): "`avatar-prep synth` registers the synthetic capture source's command; nothing else in prep sees synth",
    (
        "gsavatar.prep.cli",
        "gsavatar.importers.cli",
    ): "`avatar-prep import` registers the real capture sources' command; nothing else in prep sees importers",
    (
        "gsavatar.prep.cli",
        "gsavatar.fitting.cli",
    ): "`avatar-prep fit-body` registers the body fit's command; nothing else in prep sees fitting",
    (
        "gsavatar.fitting.cli",
        "gsavatar.importers.smplx_model",
    ): "`fit-body --smplx-model` reads the user's SMPL-X model file with the importers' reader",
    (
        "gsavatar.fitting.cli",
        "gsavatar.importers.smplx_body",
    ): "`fit-body --smplx-model` builds the shaped SMPL-X body and rig with the importers' body code",
}
"""Exceptions by (importer module, imported module), each with its reason."""


def module_name(path: Path, src: Path = SRC) -> str:
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imported_modules(path: Path, src: Path = SRC) -> list[tuple[str, int]]:
    """(absolute module name, line) of every gsavatar import in ``path``, anywhere in the file."""
    name = module_name(path, src)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:  # ``from gsavatar.train import losses`` imports the module gsavatar.train.losses
                sub = src.joinpath(*mod.split("."), a.name)
                is_module = sub.with_suffix(".py").exists() or (sub / "__init__.py").exists()
                out.append((f"{mod}.{a.name}" if is_module else mod, node.lineno))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, (ast.Attribute, ast.Name))
            and getattr(node.func, "attr", getattr(node.func, "id", None)) in ("import_module", "__import__")
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            out.append((node.args[0].value, node.lineno))
    return [(m, line) for m, line in out if m == "gsavatar" or m.startswith("gsavatar.")]


def package_of(module: str) -> str:
    """``gsavatar.train.data`` -> ``train``; the root module -> ``""``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def layer_of(package: str) -> int:
    return -1 if package == "" else LAYERS[package]


def violations(src: Path = SRC) -> list[str]:
    """Every import that breaks the rule, as ``importer:line -> imported (why)``."""
    found = []
    for path in sorted((src / "gsavatar").rglob("*.py")):
        importer = module_name(path, src)
        pi = package_of(importer)
        for imported, line in imported_modules(path, src):
            pt = package_of(imported)
            if pt == pi or (importer, imported) in ALLOWED:
                continue
            if pi == "":
                found.append(f"{importer}:{line} -> {imported} (gsavatar/__init__.py imports no subpackage)")
            elif layer_of(pt) == layer_of(pi):
                found.append(f"{importer}:{line} -> {imported} (sibling of layer {LAYERS[pi]}: {pi} -> {pt})")
            elif layer_of(pt) > layer_of(pi):
                found.append(
                    f"{importer}:{line} -> {imported} (upward: {pi} (layer {LAYERS[pi]}) -> {pt} (layer {LAYERS[pt]}))"
                )
    return found


def edges(src: Path = SRC) -> set[tuple[str, str]]:
    """(importer package, imported package) pairs of the whole source tree."""
    out = set()
    for path in (src / "gsavatar").rglob("*.py"):
        pi = package_of(module_name(path, src))
        out |= {(pi, package_of(m)) for m, _ in imported_modules(path, src)}
    return out


def test_every_subpackage_has_a_layer():
    packages = {p.name for p in (SRC / "gsavatar").iterdir() if (p / "__init__.py").exists()}
    assert packages == set(LAYERS), f"place new packages in LAYERS (and docs/architecture.md): {packages ^ set(LAYERS)}"


def test_imports_flow_downward_only():
    bad = violations()
    assert not bad, "imports against the layer rule (docs/architecture.md):\n" + "\n".join(bad)


def test_allowed_exceptions_are_still_needed():
    seen = {(module_name(p), m) for p in (SRC / "gsavatar").rglob("*.py") for m, _ in imported_modules(p)}
    stale = [f"{a} -> {b}" for a, b in ALLOWED if (a, b) not in seen]
    assert not stale, f"ALLOWED lists imports that no longer exist: {stale}"


@pytest.mark.parametrize(
    ("importer", "forbidden"),
    [
        ("models", {"prep", "train", "synth", "runs", "drive"}),
        ("drive", {"train", "synth", "prep"}),
        ("data_schema", {"render", "metrics", "motion", "models", "runs", "prep", "synth", "train", "drive"}),
        ("utils", set(LAYERS) - {"utils"}),
    ],
)
def test_named_boundaries(importer, forbidden):
    crossing = sorted(b for a, b in edges() if a == importer and b in forbidden)
    assert not crossing, f"{importer} imports {crossing}"


def test_checker_sees_deferred_relative_and_dynamic_imports(tmp_path):
    pkg = tmp_path / "gsavatar"
    for sub in ("models", "prep", "train"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "models" / "a.py").write_text(
        "import importlib\n"
        "from . import b\n"  # same package: fine
        "def f():\n"
        "    from gsavatar.prep.pca import fit\n"  # deferred, upward
        "    from ..train import losses\n"  # relative, upward
        "    return importlib.import_module('gsavatar.train.trainer')\n"
    )  # dynamic, upward
    (pkg / "models" / "b.py").write_text("from gsavatar import prep\n")  # attribute-style package import
    (pkg / "prep" / "c.py").write_text("from gsavatar.train import data\n")  # sibling layer
    found = violations(tmp_path)
    assert len(found) == 5, found
    assert any("gsavatar.models.a:4 -> gsavatar.prep.pca (upward" in v for v in found)
    assert any("gsavatar.models.a:5 -> gsavatar.train (upward" in v for v in found)
    assert any("gsavatar.models.a:6 -> gsavatar.train.trainer" in v for v in found)
    assert any("gsavatar.models.b:1 -> gsavatar.prep" in v for v in found)
    assert any("gsavatar.prep.c:1 -> gsavatar.train (sibling" in v for v in found)
