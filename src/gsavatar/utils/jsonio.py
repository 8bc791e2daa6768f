"""Strict JSON reading for files a user hands us (captures, rigs, datasets, runs).

Python's ``json`` accepts things that are almost never what the author meant: a key given twice
(the last one silently wins), ``NaN``/``Infinity`` literals, nesting deep enough to overflow the
parser's recursion, any file size. :func:`read_json` refuses each of them with a
:class:`~gsavatar.utils.errors.SchemaError` naming the file (and the key or line). The type
helpers refuse ``true``/``false`` where a number is expected (in Python ``bool`` is an ``int``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path, PurePath

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.paths import check_regular_file

MAX_JSON_BYTES = 64 << 20
"""Largest JSON file read (64 MiB: a calibration of thousands of cameras is a few MB)."""
MAX_JSON_DEPTH = 64
"""Deepest nesting of objects/arrays accepted (ours need < 10)."""


class _DuplicateKey(ValueError):
    pass


def _no_duplicates(pairs: list[tuple[str, object]]) -> dict:
    out: dict = {}
    for k, v in pairs:
        if k in out:
            raise _DuplicateKey(k)
        out[k] = v
    return out


def _bad_constant(name: str):
    raise ValueError(f"non-standard JSON constant {name}")


def _too_deep(obj, limit: int) -> bool:
    """Whether parsed JSON nests objects/arrays more than ``limit`` levels (iterative walk over containers)."""
    stack = [(obj, 1)]
    while stack:
        node, depth = stack.pop()
        children = node.values() if isinstance(node, dict) else node
        for c in children:
            if isinstance(c, (dict, list)):
                if depth + 1 > limit:
                    return True
                stack.append((c, depth + 1))
    return False


def parse_json_text(text: str, file: str | Path):
    """Parse JSON text strictly (see module docstring); ``file`` names the source in errors."""
    too_deep = SchemaError(file, "", f"JSON nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        obj = json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_bad_constant)
    except _DuplicateKey as e:
        raise SchemaError(file, str(e), "key given twice (JSON keys must be unique)") from None
    except json.JSONDecodeError as e:
        raise SchemaError(file, f"line {e.lineno}", f"invalid JSON: {e.msg}") from None
    except ValueError as e:  # NaN / Infinity literals
        raise SchemaError(file, "", f"invalid JSON: {e}") from None
    except RecursionError:  # the C parser's guard, far deeper than MAX_JSON_DEPTH
        raise too_deep from None
    # Depth is checked on the parsed containers, not by scanning the text: a Python loop over every character
    # cost ~50 ns each (250 ms for a 5 MB dataset.json, read several times per prep run).
    if isinstance(obj, (dict, list)) and _too_deep(obj, MAX_JSON_DEPTH):
        raise too_deep
    return obj


def read_json(path: str | Path, max_bytes: int = MAX_JSON_BYTES):
    """Read and strictly parse a JSON file. SchemaError names the file for a missing file, a
    non-regular file (FIFO, device, directory), a file over ``max_bytes``, non-UTF-8 bytes, invalid
    JSON (with the line), a duplicate key (with the key), NaN/Infinity, or nesting over MAX_JSON_DEPTH."""
    path = check_regular_file(path, "JSON file", max_bytes)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise SchemaError(path, "", "not a UTF-8 JSON text file") from None
    return parse_json_text(text, path)


def is_int(v) -> bool:
    """A JSON integer (``true``/``false`` are not)."""
    return isinstance(v, int) and not isinstance(v, bool)


def is_number(v) -> bool:
    """A finite JSON number (``true``/``false`` are not)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def config_to_json(obj, exclude: tuple[str, ...] = ()):
    """Plain-JSON form of a config, the one serialisation of every config we record (run, model, predictor,
    prep stage, synthetic capture): dataclasses become dicts of their fields (recursively), tuples lists and
    paths strings; ``exclude`` drops top-level fields. Other values are returned as they are."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: config_to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.name not in exclude}
    if isinstance(obj, dict):
        return {k: config_to_json(v) for k, v in obj.items() if k not in exclude}
    if isinstance(obj, (list, tuple)):
        return [config_to_json(v) for v in obj]
    if isinstance(obj, PurePath):
        return str(obj)
    return obj


def dataclass_defaults(cls) -> dict:
    """JSON values of a config dataclass's fields that have a default: what a saved config written before a
    field existed meant (:func:`gsavatar.runs.checkpoint.load_checkpoint`'s ``defaults``)."""
    out = {f.name: f.default for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING}
    return json.loads(json.dumps(out, default=lambda v: list(v) if isinstance(v, tuple) else str(v)))
