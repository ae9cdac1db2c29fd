"""The one atomic file writer: a temporary file in the target's folder, flushed to disk, then
one rename over the target. A reader, or a run killed half-way, sees the old file or the new
one, never a part of one. Every file the detector writes goes through here.

A leaf: imports nothing of the project (torch, cv2 and matplotlib only where used).
"""
from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

# mkstemp creates its file readable by the owner only; a written file gets the mode any new file
# gets (0666 less the umask), as open() would give it.
_UMASK = os.umask(0)
os.umask(_UMASK)
FILE_MODE = 0o666 & ~_UMASK


def write_with(path: str | Path, write: Callable[[IO[bytes]], None]) -> Path:
    """Replace ``path`` with what ``write(f)`` writes to a binary file object, atomically.
    The parent folders are created. The temporary file keeps ``path``'s suffix, so writers that
    choose the format by the name (matplotlib) see the right one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}")
    try:
        os.chmod(tmp, FILE_MODE)
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Replace ``path`` with ``data``, atomically."""
    return write_with(path, lambda f: f.write(data))


def write_text(path: str | Path, text: str) -> Path:
    """Replace ``path`` with ``text`` (UTF-8), atomically."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: Any, indent: int | None = None) -> Path:
    """Replace ``path`` with ``obj`` as JSON (compact unless ``indent``), atomically."""
    return write_text(path, json.dumps(obj, indent=indent))


def save_torch(path: str | Path, obj: Any) -> Path:
    """Replace ``path`` with ``torch.save(obj)``, atomically."""
    import torch
    return write_with(path, lambda f: torch.save(obj, f))


def write_image(path: str | Path, bgr) -> Path:
    """Replace ``path`` with the (H, W, 3) uint8 BGR image ``bgr`` encoded by OpenCV in the format
    of ``path``'s suffix (.png, .jpg, ...), atomically. ValueError for a suffix OpenCV cannot
    encode (the caller names the option)."""
    import cv2
    ok, buf = cv2.imencode(Path(path).suffix or ".png", bgr)
    if not ok:
        raise ValueError(f"cannot encode an image as {Path(path).suffix!r}")
    return write_bytes(path, buf.tobytes())


def save_figure(path: str | Path, fig) -> Path:
    """Replace ``path`` with the matplotlib figure ``fig`` (format from the suffix), atomically."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    return write_with(path, lambda f: fig.savefig(f, format=fmt))
