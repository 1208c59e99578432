"""PyTorch and onnxruntime side of the Rust benchmark `deepstereo-train/benches/network.rs`.

    python python/bench_network.py DIR THREADS

DIR holds what the Rust side wrote: `weights.safetensors` (the model), `model.onnx` (its
export), `tile.safetensors` (one render tile's inputs, `level0`..), `candle.safetensors`
(candle's image on that tile) and `batch.safetensors` (a training batch: `level0`.. and
`target`). Prints one JSON line: best seconds of PyTorch's forward (`torch.no_grad`), of a
PyTorch training step (forward, L1 loss, backward, Adam) and of onnxruntime's forward, and
the largest absolute difference of PyTorch's and onnxruntime's images from candle's.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
from safetensors.numpy import load_file

sys.path.insert(0, str(Path(__file__).resolve().parent))
import deepstereo_ref as ref  # noqa: E402


def timed(f, budget_s, max_reps=8):
    """Best wall time of f() in seconds: one warm-up run, then 2..max_reps runs."""
    t0 = time.perf_counter()
    f()
    first = time.perf_counter() - t0
    reps = int(min(max_reps, max(2, budget_s / max(first, 1e-6))))
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t0)
    return best


def levels(arrays, n):
    return [arrays[f"level{l}"] for l in range(n)]


def main():
    d, threads = Path(sys.argv[1]), int(sys.argv[2])
    torch.set_num_threads(threads)
    model = ref.load(str(d / "weights.safetensors"))
    n = model.cfg.levels
    tile = levels(load_file(str(d / "tile.safetensors")), n)
    xs = [torch.from_numpy(a) for a in tile]
    candle = load_file(str(d / "candle.safetensors"))["image"]

    with torch.no_grad():
        image = model(xs)[0].numpy()
        torch_fwd = timed(lambda: model(xs), 6.0, max_reps=30)

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    sess = ort.InferenceSession(str(d / "model.onnx"), opts, providers=["CPUExecutionProvider"])
    feed = {f"level{l}": a for l, a in enumerate(tile)}
    ort_image = sess.run(["image"], feed)[0]
    ort_fwd = timed(lambda: sess.run(None, feed), 6.0, max_reps=30)

    batch = load_file(str(d / "batch.safetensors"))
    bx = [torch.from_numpy(a) for a in levels(batch, n)]
    by = torch.from_numpy(batch["target"])
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step():
        opt.zero_grad(set_to_none=True)
        loss = (model(bx)[0] - by).abs().mean()
        loss.backward()
        opt.step()

    torch_step = timed(step, 8.0, max_reps=12)
    diff = max(float(np.abs(image - candle).max()), float(np.abs(ort_image - candle).max()))
    print(
        json.dumps(
            {
                "torch_fwd_s": torch_fwd,
                "torch_step_s": torch_step,
                "ort_fwd_s": ort_fwd,
                "max_abs_diff": diff,
            }
        )
    )


if __name__ == "__main__":
    main()
