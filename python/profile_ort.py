"""onnxruntime's own per-node profile of an exported model on one random render tile.

    deepstereo export --out model.onnx          # the embedded tiny model
    python python/profile_ort.py model.onnx [TILE] [THREADS]

Runs the model 30 times to warm up and 30 times with `enable_profiling`, then prints the
best wall time and, per graph node, the first quartile of its kernel times (the slowest
40), so that onnxruntime's layers can be set against `DEEPSTEREO_CONV_PROFILE=1
target/release/examples/forward_probe tiny 30` (ours, layer by layer). The inputs are
the levels of a TILE x TILE tile (default 64) for the config in the model's metadata,
random values in [0, 1).
"""

import collections
import json
import os
import sys
import tempfile
import time

import numpy as np
import onnxruntime as ort

import deepstereo_ref as ref


def main():
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help") or len(sys.argv) > 4:
        print(__doc__.strip())
        sys.exit(0 if len(sys.argv) > 1 and sys.argv[1] in ("-h", "--help") else 2)
    path = sys.argv[1]
    tile = int(sys.argv[2]) if len(sys.argv) > 2 else 64
    threads = int(sys.argv[3]) if len(sys.argv) > 3 else os.cpu_count()
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.enable_profiling = True
    opts.profile_file_prefix = os.path.join(tempfile.mkdtemp(), "ort")
    sess = ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])
    cfg = ref.Config.from_json(sess.get_modelmeta().custom_metadata_map["deepstereo.config"])
    rng = np.random.default_rng(0)
    feed = {}
    for inp in sess.get_inputs():
        level = int(inp.name.removeprefix("level"))
        size = cfg.input_size(level, tile)
        shape = (1, cfg.planes, inp.shape[2], size, size)
        feed[inp.name] = rng.random(shape, dtype=np.float32)
    for _ in range(30):
        sess.run(None, feed)
    best = float("inf")
    for _ in range(30):
        t0 = time.perf_counter()
        sess.run(None, feed)
        best = min(best, time.perf_counter() - t0)
    print(f"best {best * 1e3:.1f} ms ({threads} threads, {tile}x{tile} tile)")
    events = json.load(open(sess.end_profiling()))
    times = collections.defaultdict(list)
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            times[(e["name"][: -len("_kernel_time")], e["args"].get("op_name"))].append(e["dur"])
    rows = sorted(((sorted(v)[len(v) // 4], k) for k, v in times.items()), reverse=True)
    for us, (name, op) in rows[:40]:
        print(f"{us / 1e3:8.2f} ms  {op:14s} {name}")
    print(f"sum over nodes {sum(us for us, _ in rows) / 1e3:.1f} ms")


if __name__ == "__main__":
    main()
