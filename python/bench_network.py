"""PyTorch and onnxruntime side of the Rust benchmark `deepstereo-train/benches/network.rs`.

    python python/bench_network.py DIR THREADS

DIR holds what the Rust side wrote: `weights.safetensors` (the model), `model.onnx` (its
export), `tile.safetensors` (one render tile's inputs, `level0`..), `candle.safetensors`
(candle's image on that tile) and `batch.safetensors` (a training batch: `level0`.. and
`target`). After loading, prints one JSON line with the largest absolute difference of
PyTorch's and onnxruntime's images from candle's, then serves the Rust side, which
alternates its own runs with these so that a change in the machine's speed hits every
runtime alike: each line on stdin, `torch_fwd` (PyTorch forward, `torch.no_grad`),
`ort_fwd` (onnxruntime forward) or `torch_step` (forward, L1 loss, backward, Adam) and a
count N, runs N times back to back and answers the best wall time in seconds; `quit` (or
the end of stdin) ends it. After each turn it waits SETTLE_S before answering, so that
the runtimes' spinning worker threads are idle when the other side starts.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
from safetensors.numpy import load_file

import deepstereo_ref as ref


# Seconds to wait after a run before answering (OpenMP and onnxruntime workers spin for a
# while after each parallel region; they must not take the cores from the next runtime).
SETTLE_S = 0.3


def levels(arrays, n):
    return [arrays[f"level{l}"] for l in range(n)]


def main():
    if len(sys.argv) != 3 or not sys.argv[2].isdigit():
        print(__doc__.strip())
        sys.exit(0 if sys.argv[1:2] in (["-h"], ["--help"]) else 2)
    d, threads = Path(sys.argv[1]), int(sys.argv[2])
    torch.set_num_threads(threads)
    model = ref.load(str(d / "weights.safetensors"))
    n = model.cfg.levels
    tile = levels(load_file(str(d / "tile.safetensors")), n)
    xs = [torch.from_numpy(a) for a in tile]
    candle = load_file(str(d / "candle.safetensors"))["image"]

    with torch.no_grad():
        image = model(xs)[0].numpy()

    def torch_fwd():
        with torch.no_grad():
            model(xs)

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    sess = ort.InferenceSession(str(d / "model.onnx"), opts, providers=["CPUExecutionProvider"])
    feed = {f"level{l}": a for l, a in enumerate(tile)}
    ort_image = sess.run(["image"], feed)[0]

    batch = load_file(str(d / "batch.safetensors"))
    bx = [torch.from_numpy(a) for a in levels(batch, n)]
    by = torch.from_numpy(batch["target"])
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def torch_step():
        model.train()
        opt.zero_grad(set_to_none=True)
        loss = (model(bx)[0] - by).abs().mean()
        loss.backward()
        opt.step()

    diff = max(float(np.abs(image - candle).max()), float(np.abs(ort_image - candle).max()))
    print(json.dumps({"max_abs_diff": diff}), flush=True)
    runs = {"torch_fwd": torch_fwd, "ort_fwd": lambda: sess.run(None, feed), "torch_step": torch_step}
    for line in sys.stdin:
        cmd, *reps = line.split()
        if cmd == "quit":
            break
        best = float("inf")
        for _ in range(int(reps[0]) if reps else 1):
            t0 = time.perf_counter()
            runs[cmd]()
            best = min(best, time.perf_counter() - t0)
        time.sleep(SETTLE_S)
        print(best, flush=True)


if __name__ == "__main__":
    main()
