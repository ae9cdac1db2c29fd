"""Shared fixtures: one small dataset made through the CLI, reused by the dataset tests."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

TINY_ARGS = ["--preset", "tiny", "--scenes", "2", "--samples-per-scene", "3", "--seed", "7", "--quiet"]


def script_module(name: str):
    """``scripts/NAME.py`` imported as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def run_simgen(*args, check=True, **kw) -> subprocess.CompletedProcess:
    """Run the simgen CLI in a subprocess, as a user would."""
    proc = subprocess.run([sys.executable, "-m", "simgen.cli", *map(str, args)], capture_output=True, text=True, **kw)
    if check and proc.returncode != 0:
        raise AssertionError(f"simgen {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr}")
    return proc


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """Two tiny scenes of three samples, made with one worker."""
    out = tmp_path_factory.mktemp("tiny") / "data"
    run_simgen("make", "--out", out, "--workers", "1", *TINY_ARGS)
    return out


@pytest.fixture(scope="session")
def tiny_nusc(tiny_dataset):
    from nuscenes import NuScenes
    return NuScenes("v1.0-sim", str(tiny_dataset), verbose=False)


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a test module, restored afterwards. Its tensors are small, and the 2
    cores are shared: multi-threaded kernels then spin and turn a 0.1 s step into seconds."""
    import torch
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# A model a few times smaller than tiny, for tests that train or load one in seconds.
MICRO_YAML = """\
preset: tiny
image_size: [64, 176]
cam_width: 8
fpn_ch: 32
context_ch: 16
vfe_ch: 16
fusion_dim: 32
attn_heads: 2
bev_channels: [16, 32]
bev_blocks: 1
bev_up_ch: 16
"""


@pytest.fixture(scope="session")
def micro(tmp_path_factory) -> Path:
    """A YAML config file of the micro model."""
    path = tmp_path_factory.mktemp("cfg") / "micro.yaml"
    path.write_text(MICRO_YAML)
    return path
