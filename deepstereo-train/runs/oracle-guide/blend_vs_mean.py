"""Does the model's colour blend cost it on a view? Runs the PyTorch reference
(python/deepstereo_ref.py) on the network inputs `deepstereo sweep --model MODEL` writes
for one tile covering the target (`level0..`, `target`), and scores against the target
photograph the model's image, the same selection applied to the sources' plain
alpha-weighted mean colour instead of the model's colours, and mixes of the two. The
render is unpruned from the nearest views (`eval --prune off`'s sources). Run with the
test command's venv (torch, numpy, safetensors).
Usage: python blend_vs_mean.py MODEL.safetensors INPUTS.safetensors
"""
import os
import sys

import numpy as np
import torch
from safetensors.numpy import load_file

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "../../../python"))
import deepstereo_ref as ref  # noqa: E402

MIXES = (0.25, 0.5, 0.75)


def main(argv):
    if len(argv) != 3:
        sys.exit(__doc__.strip().splitlines()[-1])
    torch.set_grad_enabled(False)
    model = ref.load(argv[1])
    cfg = model.cfg
    d = load_file(argv[2])
    target = d["target"].astype(np.float64)
    inputs = [torch.from_numpy(d[f"level{l}"]) for l in range(cfg.levels)]
    image, sel = model(inputs)  # [1, 3, th, tw], [1, D, th, tw]
    p = cfg.pad(0)
    x0 = inputs[0][0][:, :, :, p : p + sel.shape[2], p : p + sel.shape[3]]  # [D, V, 4, th, tw]
    rgb, a = x0[:, :, :3], x0[:, :, 3:4]
    mean = (rgb * a).sum(1) / (a.sum(1) + 1e-6)  # [D, 3, th, tw]
    mean_image = (mean * sel[0].unsqueeze(1)).sum(0)
    h, w = target.shape[1:]

    def psnr(x):
        x = x[..., :h, :w].double().numpy()
        return -10 * np.log10(((x - target) ** 2).mean())

    print(f"model {psnr(image[0]):.2f} dB; its selection on the sources' mean colour {psnr(mean_image):.2f} dB")
    for m in MIXES:
        print(f"  {m:.2f} of the mean: {psnr((1 - m) * image[0] + m * mean_image):.2f} dB")


if __name__ == "__main__":
    main(sys.argv)
