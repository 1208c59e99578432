"""The view factor `1 + tanh(WEIGH_SCALE g(cue))` a model with `pool.weigh` gives a source,
against the angle between its ray and the target's.

For each angle, COUNT random unit directions of the ray difference and log distance ratios
uniform in [-0.5, 0.5], made into the cue of `deepstereo-core/src/sweep/cue.rs`
(`[delta / (n + EPS_DIR), ln(n + EPS_DIR), ln ratio]`, `delta = n u`), through the model's
`views.weigh.*` 1x1 layers (ReLU between); prints the smallest and largest factor.

    .venv/bin/python python/weigh_factor.py MODEL.safetensors [--angles 0,0.02,0.14,1]
"""

import argparse
import sys

import numpy as np
from safetensors.numpy import load_file

from deepstereo_ref import WEIGH_SCALE

EPS_DIR = 1e-3  # cue.rs


def factors(weights: dict, cues: np.ndarray) -> np.ndarray:
    """`cues` [N, 5] -> the factors [N]."""
    n_layers = len({k.split(".")[2] for k in weights if k.startswith("views.weigh.")})
    h = cues
    for i in range(n_layers):
        w = weights[f"views.weigh.{i}.weight"].reshape(-1, h.shape[1]).astype(np.float64)
        h = h @ w.T + weights[f"views.weigh.{i}.bias"].astype(np.float64)
        if i < n_layers - 1:
            h = np.maximum(h, 0.0)
    return 1.0 + np.tanh(WEIGH_SCALE * h[:, 0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--angles", default="0,0.02,0.14,1")
    ap.add_argument("--count", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    try:
        weights = load_file(a.model)
    except Exception as e:  # noqa: BLE001 - any unreadable file is one error
        print(f"error: cannot read {a.model}: {e}", file=sys.stderr)
        return 1
    if "views.weigh.0.weight" not in weights:
        print(f"error: {a.model} has no view weights (views.weigh.*)", file=sys.stderr)
        return 1
    rng = np.random.default_rng(a.seed)
    for angle in (float(x) for x in a.angles.split(",")):
        u = rng.normal(size=(a.count, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        cues = np.concatenate(
            [
                u * angle / (angle + EPS_DIR),
                np.full((a.count, 1), np.log(angle + EPS_DIR)),
                rng.uniform(-0.5, 0.5, size=(a.count, 1)),
            ],
            axis=1,
        )
        k = factors(weights, cues)
        print(f"angle {angle:g} rad: factor {k.min():.2f}-{k.max():.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
