"""Plane-sweep warps with torch.nn.functional.grid_sample, timed for the Rust benchmark
`deepstereo-core/benches/sweep.rs`, which writes the inputs and compares the outputs.

Usage: bench_sweep.py META.json. META names `dir` holding `images.npy` (`[V*H, W*3]` f32,
interleaved RGB per view) and `homographies.npy` (`[D*V, 9]` f64, row-major 3x3 pixel
homographies target -> source, plane-major, pixel centres at i + 0.5). Builds the
`[D, V, 4, H, W]` volume (RGB and coverage alpha; zero where the plane point is behind
the source) the way a PyTorch implementation would: per plane, a batch of V warps with
bilinear `grid_sample(padding_mode="zeros", align_corners=False)` of the images with a
ones channel appended. Prints JSON `{"median_ms", "cpu_ms", "threads", "torch"}` (wall
median and mean CPU time per run) and writes the
`check_planes` slices to `check.npy` (`[len * V * 4, H * W]` f32).
"""

import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

EPS = 1e-9


def main():
    meta = json.loads(Path(sys.argv[1]).read_text())
    torch.set_num_threads(int(meta.get("threads", 2)))
    d, v, h, w = meta["planes"], meta["views"], meta["height"], meta["width"]
    root = Path(meta["dir"])
    images = np.load(root / "images.npy").reshape(v, h, w, 3)
    hom = torch.from_numpy(np.load(root / "homographies.npy").reshape(d, v, 3, 3)).float()

    src = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2)
    src = torch.cat([src, torch.ones(v, 1, h, w)], dim=1).contiguous()  # [V, 4, H, W]
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32) + 0.5,
                            torch.arange(w, dtype=torch.float32) + 0.5, indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1).reshape(1, h * w, 3)
    scale = torch.tensor([2.0 / w, 2.0 / h])
    out = torch.empty(d, v, 4, h, w)

    def run():
        with torch.no_grad():
            for p in range(d):
                q = pix @ hom[p].transpose(1, 2)  # [V, HW, 3]
                z = q[..., 2:3]
                front = z > EPS * q.norm(dim=-1, keepdim=True)
                grid = (q[..., :2] / z) * scale - 1.0
                grid = torch.where(front, grid, torch.full_like(grid, -4.0))  # off-image
                out[p] = F.grid_sample(src, grid.view(v, h, w, 2), mode="bilinear",
                                       padding_mode="zeros", align_corners=False)

    run()
    times = []
    cpu0 = time.process_time()
    for _ in range(5):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    cpu_ms = 1e3 * (time.process_time() - cpu0) / len(times)
    check = out[meta["check_planes"]].reshape(-1, h * w).numpy()
    np.save(root / "check.npy", check.astype("<f4"))
    print(json.dumps({"median_ms": 1e3 * statistics.median(times), "cpu_ms": cpu_ms,
                      "threads": torch.get_num_threads(), "torch": torch.__version__}))


if __name__ == "__main__":
    main()
