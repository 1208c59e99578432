"""Gives an any-number-of-views (`nviews`) model's selection tower more resolution levels
without changing what it computes: each new level (1/8, 1/16, ... resolution) gets the
same per-level convolutions as the others, with fresh He-initialised weights, and the
first merge convolution gets zero weights on the new levels' channels, so the network
renders exactly what the original did until training moves it. Wider spatial context for
the depth selection: with 3 levels a level-0 output pixel sees about 28 pixels; each
extra level doubles the reach of the coarsest. Used by train_levels.sh (issue 20).

Usage: python add_levels.py IN.safetensors OUT.safetensors CONFIG_OUT.json LEVELS
Needs numpy and safetensors (the test command's venv has both).
"""
import sys

import numpy as np

import model_file


def main():
    if len(sys.argv) != 5:
        sys.exit(__doc__.strip().splitlines()[-2])
    src, dst, cfg_out, new_levels = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    rng = np.random.default_rng(11)
    meta, t, cfg = model_file.load(src)
    sel = cfg["select"]
    old = sel["levels"]
    if cfg.get("pool") is None or new_levels <= old or new_levels > 6:
        sys.exit(f"{src}: needs an nviews model with fewer than {new_levels} (<= 6) levels")
    for l in range(old, new_levels):
        for i in range(len(sel["level_convs"])):
            w = t[f"select.levels.0.{i}.weight"]
            fan_in = w.shape[1] * w.shape[2] * w.shape[3]
            t[f"select.levels.{l}.{i}.weight"] = rng.normal(
                0, np.sqrt(2.0 / fan_in), w.shape
            ).astype(np.float32)
            t[f"select.levels.{l}.{i}.bias"] = np.zeros(w.shape[0], np.float32)
    # The merge input is the levels' features concatenated in level order.
    w = t["select.merge.0.weight"]
    o, cin, kh, kw = w.shape
    per_level = cin // old
    grown = np.zeros((o, per_level * new_levels, kh, kw), np.float32)
    grown[:, :cin] = w
    t["select.merge.0.weight"] = grown
    sel["levels"] = new_levels
    cfg["levels"] = max(cfg["levels"], new_levels)
    cfg["name"] = f"{cfg['name']}-l{new_levels}"
    model_file.save(dst, cfg_out, meta, t, cfg)
    print(f"{dst}: {sum(v.size for v in t.values())} parameters, {new_levels} levels")


if __name__ == "__main__":
    main()
