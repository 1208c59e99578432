"""How much of a view's error is the choice of depth? Reads a plane-sweep volume written
by `deepstereo sweep` (`psv` [D, V, 4, H, W], `target` [3, H, W]) and scores, against the
target photograph, the mean colour of the sources (alpha-weighted) at the plane an
*oracle* picks: for every pixel, the plane whose mean colour is closest (L1) to the
target's over a WIN x WIN window around it. The oracle sees the target, so this is an
upper bound for any renderer that blends the sources at one depth per window; the gap to
the model's PSNR on the same view is what a better depth selection could gain. Beside it:
the same for each source alone; the plane where the sources agree best over the window
(mean absolute deviation from their mean; a classical windowed plane sweep, which does
not see the target); and the one plane that is best for the whole image (an oracle).
Needs numpy and safetensors (python/requirements.txt).
Usage: python python/oracle_depth.py PSV.safetensors [WIN...] (default 1 9 31)
"""
import sys

import numpy as np
from safetensors.numpy import load_file


# Sources (summed alpha) a plane needs at a pixel for their agreement to count.
MIN_AGREEING = 1.5


def box(x, win):
    """Mean over a win x win window (edge-clamped) of each [H, W] slice of x [..., H, W]."""
    r = win // 2
    p = np.pad(x, [(0, 0)] * (x.ndim - 2) + [(r + 1, r), (r + 1, r)], mode="edge")
    s = p.cumsum(-1).cumsum(-2)
    return (s[..., win:, win:] - s[..., :-win, win:] - s[..., win:, :-win] + s[..., :-win, :-win]) / (win * win)


def psnr(a, b):
    return -10 * np.log10(((a - b) ** 2).mean())


def oracle(colours, valid, target, win):
    """colours [D, 3, H, W], valid [D, H, W] -> PSNR of the colour at the oracle's plane."""
    cost = np.where(valid, np.abs(colours - target[None]).mean(1), 1.0)
    if win > 1:
        cost = box(cost, win)
    k = cost.argmin(0)
    return psnr(np.take_along_axis(colours, k[None, None].repeat(3, 1), 0)[0], target)


def main(argv):
    if len(argv) > 1 and argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        return
    if len(argv) < 2:
        sys.exit(__doc__.strip().splitlines()[-1])
    try:
        d = load_file(argv[1])
    except (OSError, ValueError) as e:
        sys.exit(f"{argv[1]}: not a readable safetensors file ({e})")
    if "psv" not in d or "target" not in d or d["psv"].ndim != 5:
        sys.exit(f"{argv[1]}: no `psv` [D, V, 4, H, W] and `target` (write it with `deepstereo sweep`)")
    psv, target = d["psv"].astype(np.float64), d["target"].astype(np.float64)
    wins = [int(w) for w in argv[2:]] or [1, 9, 31]
    a = psv[:, :, 3:4]
    mean = (psv[:, :, :3] * a).sum(1) / np.maximum(a.sum(1), 1e-6)
    print(f"sources {[int(s) for s in d['sources']]}, {psv.shape[0]} planes")
    w = a.sum(1)[:, 0]  # [D, H, W] summed alpha
    spread = (np.abs(psv[:, :, :3] - mean[:, None]) * a).sum(1).mean(1) / np.maximum(w, 1e-6)
    spread = np.where(w >= MIN_AGREEING, spread, 1.0)
    for win in wins:
        per = [oracle(psv[:, v, :3], psv[:, v, 3] > 0.5, target, win) for v in range(psv.shape[1])]
        m = oracle(mean, w > 0, target, win)
        k = (box(spread, win) if win > 1 else spread).argmin(0)
        agree = psnr(np.take_along_axis(mean, k[None, None].repeat(3, 1), 0)[0], target)
        print(f"window {win:3d}: oracle {m:.2f} dB (each source alone "
              + ", ".join(f"{p:.2f}" for p in per) + f"); sources agree best {agree:.2f} dB")
    whole = max(psnr(mean[z], target) for z in range(psv.shape[0]))
    print(f"best single plane for the whole image (oracle): {whole:.2f} dB")


if __name__ == "__main__":
    main(sys.argv)
