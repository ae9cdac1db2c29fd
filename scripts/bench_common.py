"""What the benchmark parts share: the repository root, timing, and running a command or a
measurement in a fresh process.

Measurements that report a process's own peak memory, or that must run on one torch thread
whatever the parent does, run in a child: ``run_child(module, name, *args)`` runs
``python scripts/<module>.py name args...``, whose ``__main__`` calls the measurement ``name``
and prints its result as one JSON line.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = ROOT / "scripts"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``fn()`` over ``repeats`` calls, in ms."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(times))


def simgen_make(out: Path | str, *options: str) -> None:
    """``simgen make --out OUT --quiet OPTIONS`` in a child process; its progress discarded."""
    cmd = [sys.executable, "-m", "simgen.cli", "make", "--out", str(out), *options, "--quiet"]
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def run_make(out: Path, scenes: int, samples: int, workers: int, resolution: str, preset: str = "urban",
             flags: tuple[str, ...] = ()) -> float:
    """Seconds of one ``simgen make`` (``resolution`` "" keeps the preset's; ``flags`` are added)."""
    cmd = [sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--scenes", str(scenes),
           "--samples-per-scene", str(samples), "--workers", str(workers), "--preset", preset, "--quiet", *flags]
    if resolution:
        cmd += ["--resolution", resolution]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def run_child(module: str, name: str, *args) -> dict:
    """The JSON that measurement ``name`` of ``scripts/<module>.py`` prints as its last line,
    run in a fresh process."""
    cmd = [sys.executable, str(SCRIPTS / f"{module}.py"), name, *map(str, args)]
    proc = subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True, text=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def child_main(measurements: dict[str, Callable[..., dict]]) -> None:
    """The ``__main__`` of a module with child measurements: ``NAME ARGS...`` -> one JSON line."""
    name, *args = sys.argv[1:]
    print(json.dumps(measurements[name](*args)))
