"""An oracle's coarse pass for `eval` with oracle_guide.patch applied: from a plane-sweep
volume written by `deepstereo sweep` (the render's planes: the scene's bounds, the
model's plane count), the plane whose sources' mean colour best matches the *target
photograph* over a WIN x WIN window, for every pixel of the guide (pyramid level LEVEL,
the pixel at the centre of each 2^LEVEL block), written as one byte per guide pixel,
row-major. The patched renderer then keeps, per block, only the planes this map names
(and `--prune-margin` around them). An experiment, not a feature: the oracle sees the
target. Needs numpy and safetensors (the test command's venv has both).
Usage: python oracle_guide.py PSV.safetensors OUT.bin [WIN] [LEVEL]   (default 31, 2)
"""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "../../scripts"))
from oracle_depth import box  # noqa: E402
from safetensors.numpy import load_file  # noqa: E402


def main(argv):
    if len(argv) < 3:
        sys.exit(__doc__.strip().splitlines()[-1])
    win = int(argv[3]) if len(argv) > 3 else 31
    level = int(argv[4]) if len(argv) > 4 else 2
    d = load_file(argv[1])
    psv, target = d["psv"].astype(np.float64), d["target"].astype(np.float64)
    a = psv[:, :, 3:4]
    w = a.sum(1)
    mean = (psv[:, :, :3] * a).sum(1) / np.maximum(w, 1e-6)
    cost = np.where(w[:, 0] > 0, np.abs(mean - target[None]).mean(1), 1.0)
    k = box(cost, win).argmin(0)
    h, wd = k.shape
    s, c = 1 << level, (1 << level) // 2
    guide = k[c::s, c::s][: h >> level, : wd >> level].astype(np.uint8)
    tmp = argv[2] + ".tmp"
    guide.tofile(tmp)
    os.replace(tmp, argv[2])
    print(f"{argv[2]}: {guide.shape[1]}x{guide.shape[0]} guide pixels, planes {guide.min()}..{guide.max()}")


if __name__ == "__main__":
    main(sys.argv)
