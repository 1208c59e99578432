"""Gives an any-number-of-views (`nviews`) model's first view-encoder layer a KxK kernel
without changing what it computes: the 1x1 weights become the kernel's centre tap, the
other taps zero (the encoder zero-pads, so the image size is kept). Used by
train_encoder3.sh (issue 20: does spatial context per view help?).

Usage: python spatial_encoder.py IN.safetensors OUT.safetensors CONFIG_OUT.json [K]
Needs numpy and safetensors (the test command's venv has both).
"""
import sys

import numpy as np

import model_file


def main():
    src, dst, cfg_out = sys.argv[1:4]
    k = int(sys.argv[4]) if len(sys.argv) > 4 else 3
    meta, t, cfg = model_file.load(src)
    w = t["views.encode.0.weight"]
    assert w.shape[2:] == (1, 1), f"{src}: the first encoder layer is not 1x1"
    out = np.zeros(w.shape[:2] + (k, k), np.float32)
    out[:, :, k // 2, k // 2] = w[:, :, 0, 0]
    t["views.encode.0.weight"] = out
    cfg["pool"]["encoder"][0]["kernel"] = k
    cfg["name"] = cfg["name"] + f"-enc{k}"
    model_file.save(dst, cfg_out, meta, t, cfg)
    print(f"{dst}: first encoder layer {out.shape}")


if __name__ == "__main__":
    main()
