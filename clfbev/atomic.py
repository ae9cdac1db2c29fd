"""Atomic file writes: a temporary file in the same folder, then one rename, so a reader (or a
run killed half-way) sees the old file or the new one, never a part."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


def write_text(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def write_json(path: Path, obj) -> None:
    """Replace ``path`` with ``obj`` as compact JSON, atomically."""
    write_text(path, json.dumps(obj))
