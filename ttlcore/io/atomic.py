"""Atomic file writes: everything is written to a temporary name beside the target and
renamed into place, so a reader never sees a half-written file and a failure loses nothing
(the previous file, if any, stays)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .hdf5 import temporary_path


def write_text(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    path = Path(path)
    tmp = temporary_path(path)
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        # name the file the user asked for, not the temporary name beside it
        raise OSError(exc.errno, f"cannot write {path}: {exc.strerror}") from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def json_default(obj):
    """``json.dump`` fallback for numpy scalars and arrays and paths."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json(path, content, indent: int = 2) -> Path:
    """Write ``content`` as JSON (NaN allowed, numpy values converted) atomically."""
    return write_text(path, json.dumps(content, indent=indent, allow_nan=True, default=json_default) + "\n")
