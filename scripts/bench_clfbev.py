"""The detector's benchmarks (CPU, one torch thread per measuring process): a training step and
inference of the tiny model, one attention module, the paper model's size and FLOPs, and
`clfbev eval` (predict, write, evaluate) per 100 samples. Keys: see scripts/bench.py.

Each measurement runs in a fresh child process (``python scripts/bench_clfbev.py NAME ARGS``
prints one JSON line), so that its peak RSS and its thread count are its own.
"""
from __future__ import annotations

import resource
import sys
import tempfile
import time

import numpy as np

from bench_common import child_main, run_child, simgen_make


def bench_clfbev(quick: bool) -> dict:
    """Training and inference speed of the tiny model, attention, and the paper model's size."""
    with tempfile.TemporaryDirectory() as tmp:
        simgen_make(tmp, "--preset", "tiny", "--scenes", "2", "--samples-per-scene", "2")
        out = run_child("bench_clfbev", "train", tmp, 4 if quick else 10)
        if not quick:
            out["paper_gflops"] = run_child("bench_clfbev", "paper_flops", tmp)["gflops"]
    exact = run_child("bench_clfbev", "attention", "exact", 64)
    window = run_child("bench_clfbev", "attention", "window", 180)
    pooled = run_child("bench_clfbev", "attention", "pooled", 180)
    out.update({"attn_ms_exact_64x64": exact["ms"], "attn_peak_mb_exact_64x64": exact["peak_mb"],
                "attn_ms_scalable_180x180": window["ms"], "attn_peak_mb_scalable_180x180": window["peak_mb"],
                "attn_ms_pooled_180x180": pooled["ms"], "attn_peak_mb_pooled_180x180": pooled["peak_mb"]})
    from clfbev.config import paper
    from clfbev.model import CLFusionBEV, count_parameters
    out["paper_params_m"] = count_parameters(CLFusionBEV(paper(), "full")) / 1e6
    return out


def bench_eval(quick: bool) -> dict:
    """`clfbev eval`'s path (predict + write + the official DetectionEval), per 100 samples."""
    with tempfile.TemporaryDirectory() as tmp:
        n = 6 if quick else 12
        simgen_make(f"{tmp}/d", "--preset", "tiny", "--scenes", "2", "--samples-per-scene", str(n // 2),
                    "--val-fraction", "0.5", "--workers", "1")
        return run_child("bench_clfbev", "eval_timing", f"{tmp}/d", f"{tmp}/e")


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def train(data: str, steps: str) -> dict:
    """(Child) Tiny `full` on one generated sample: forward + backward + AdamW step, and predict;
    the first training step (warm-up) is left out of the median."""
    import torch
    torch.set_num_threads(1)
    from clfbev.config import tiny
    from clfbev.data import NuScenesDetection, collate
    from clfbev.model import CLFusionBEV
    from clfbev.supervision.targets import batch_loss
    cfg = tiny()
    ds = NuScenesDetection(data, "v1.0-sim", "sim-train", cfg.data_config())
    batch = collate([ds[0]])
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "full")
    opt = torch.optim.AdamW(model.parameters(), lr=2e-4, weight_decay=1e-2)
    times = []
    for _ in range(int(steps)):
        t = time.perf_counter()
        opt.zero_grad()
        batch_loss(model, batch)["loss"].backward()
        opt.step()
        times.append(time.perf_counter() - t)
    model.eval()
    with torch.no_grad():
        model.predict(batch)
        inference = []
        for _ in range(int(steps)):
            t = time.perf_counter()
            model.predict(batch)
            inference.append(time.perf_counter() - t)
    return {"train_tiny_samples_per_s": 1.0 / float(np.median(times[1:])),
            "infer_tiny_ms": 1000 * float(np.median(inference)), "train_tiny_peak_rss_mb": _peak_rss_mb()}


def attention(mode: str, side: str) -> dict:
    """(Child) One MCM-sized attention (B=1, 64 channels, 4 heads) on a side x side BEV: median ms
    of 3 and the peak memory it added."""
    import torch
    torch.set_num_threads(1)
    from clfbev.attention import BEVAttention
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    attn = BEVAttention(4, mode=mode, window=8, pool_stride=4)
    q = torch.randn(1, int(side), int(side), 64)
    with torch.no_grad():
        attn(q, q, q)
        times = []
        for _ in range(3):
            t = time.perf_counter()
            attn(q, q, q)
            times.append(time.perf_counter() - t)
    return {"ms": 1000 * float(np.median(times)),
            "peak_mb": (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024}


def paper_flops(data: str) -> dict:
    """(Child) FLOPs of one forward of the paper config's `full` model on one sample."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode
    torch.set_num_threads(2)
    from clfbev.config import paper
    from clfbev.data import NuScenesDetection, collate
    from clfbev.model import CLFusionBEV
    cfg = paper()
    model = CLFusionBEV(cfg, "full").eval()
    batch = collate([NuScenesDetection(data, "v1.0-sim", "sim-train", cfg.data_config())[0]])
    with torch.no_grad(), FlopCounterMode(display=False) as fc:
        model(batch)
    return {"gflops": fc.get_total_flops() / 1e9}


def eval_timing(data: str, out: str) -> dict:
    """(Child) ``evaluate_model`` on `sim-val` with an untrained tiny `full` model, per 100
    samples; its predict part timed by a prediction pass of its own just before it."""
    import torch
    torch.set_num_threads(1)
    from clfbev.config import tiny
    from clfbev.data import NuScenesDetection
    from clfbev.model import CLFusionBEV
    from clfbev.run.evaluate import evaluate_model, predict_split
    torch.manual_seed(0)
    cfg = tiny()
    model = CLFusionBEV(cfg, "full").eval()
    ds = NuScenesDetection(data, "v1.0-sim", "sim-val", cfg.data_config())
    t0 = time.perf_counter()
    predict_split(model, ds)
    t1 = time.perf_counter()
    evaluate_model(model, ds, out)
    t2 = time.perf_counter()
    per_100 = 100 / len(ds)
    return {"eval_s_per_100_samples": (t2 - t1) * per_100, "eval_predict_s_per_100_samples": (t1 - t0) * per_100,
            "eval_devkit_s_per_100_samples": ((t2 - t1) - (t1 - t0)) * per_100}


if __name__ == "__main__":
    sys.exit(child_main({"train": train, "attention": attention, "paper_flops": paper_flops,
                         "eval_timing": eval_timing}))
