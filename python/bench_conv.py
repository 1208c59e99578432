"""Times valid, stride-1 Conv2d shapes in PyTorch (forward, forward + backward) and in
onnxruntime (forward), on 2 threads, for the Rust benchmark `benches/conv.rs`.

Reads one JSON shape `[n, cin, h, w, cout, kh, kw]` per line on stdin and answers each with
one JSON line `{"shape": [...], "torch_fwd_ms": .., "torch_fwdbwd_ms": .., "ort_fwd_ms": ..}`
(best of several runs), so that the caller can interleave its own timings shape by shape.
"""

import json
import sys
import time

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import TensorProto, helper, numpy_helper

THREADS = 2


def timed(f, budget_s=1.5, max_reps=10):
    """Best wall time of f() in ms: one warm-up run, then 2..max_reps runs within the budget
    (the best run is the least disturbed by other processes on a shared machine)."""
    t0 = time.perf_counter()
    f()
    first = time.perf_counter() - t0
    reps = int(min(max_reps, max(2, budget_s / max(first, 1e-6))))
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times)


def torch_times(n, cin, h, w, cout, kh, kw):
    conv = torch.nn.Conv2d(cin, cout, (kh, kw))
    x = torch.randn(n, cin, h, w)
    with torch.no_grad():
        fwd = timed(lambda: conv(x))
    xg = x.clone().requires_grad_(True)

    def fwd_bwd():
        conv.zero_grad(set_to_none=True)
        xg.grad = None
        conv(xg).sum().backward()

    return fwd, timed(fwd_bwd), conv


def ort_time(n, cin, h, w, cout, kh, kw, conv):
    weight = numpy_helper.from_array(conv.weight.detach().numpy(), "W")
    bias = numpy_helper.from_array(conv.bias.detach().numpy(), "B")
    node = helper.make_node("Conv", ["X", "W", "B"], ["Y"], kernel_shape=[kh, kw], pads=[0, 0, 0, 0], strides=[1, 1])
    graph = helper.make_graph(
        [node],
        "conv",
        [helper.make_tensor_value_info("X", TensorProto.FLOAT, [n, cin, h, w])],
        [helper.make_tensor_value_info("Y", TensorProto.FLOAT, [n, cout, h - kh + 1, w - kw + 1])],
        [weight, bias],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = THREADS
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    x = np.random.randn(n, cin, h, w).astype(np.float32)
    return timed(lambda: sess.run(None, {"X": x}))


def main():
    torch.set_num_threads(THREADS)
    for line in sys.stdin:
        if not line.strip():
            continue
        shape = json.loads(line)
        fwd, fwd_bwd, conv = torch_times(*shape)
        row = {"shape": shape, "torch_fwd_ms": fwd, "torch_fwdbwd_ms": fwd_bwd, "ort_fwd_ms": ort_time(*shape, conv)}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
