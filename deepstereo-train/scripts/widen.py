"""Widens an any-number-of-views (`nviews`) model without changing what it computes
(Net2Net-style): the encoder, the selection tower's level convolutions and first merge
convolution, the colour convolution and the blend's hidden layer get extra output
channels with fresh He-initialised weights (the depth layers and the outputs keep their
widths), and every weight from a new channel into an old one is zero, so the widened
network renders exactly what the original did until training moves it. Used by
train_wide.sh (issue 20: does capacity help?).

Usage: python widen.py IN.safetensors OUT.safetensors CONFIG_OUT.json
       ENC SEL MERGE COLOUR BLEND   (new widths: encoder, select level convs,
       first select merge conv, colour level conv, blend hidden layer)
Needs numpy and safetensors (the test command's venv has both).
"""
import sys

import numpy as np

import model_file


def widened(w, b, rows, cols_map, cin, rng):
    """`w` [o, i, kh, kw] -> [rows, cin, kh, kw]: old rows keep their weights at the
    columns `cols_map[i]`, zero elsewhere; new rows He-initialised over all `cin`."""
    o, i, kh, kw = w.shape
    out = np.zeros((rows, cin, kh, kw), np.float32)
    out[o:] = rng.normal(0, np.sqrt(2.0 / (cin * kh * kw)), (rows - o, cin, kh, kw))
    out[:o, cols_map] = w
    bias = np.zeros(rows, np.float32)
    bias[:o] = b
    return out, bias


def main():
    src, dst, cfg_out = sys.argv[1:4]
    enc, sel, merge, colour, blend = (int(a) for a in sys.argv[4:9])
    rng = np.random.default_rng(7)
    meta, t, cfg = model_file.load(src)
    pool = cfg["pool"]
    cf_old = pool["encoder"][-1]["channels"]
    sel_old = cfg["select"]["level_convs"][-1]["channels"]
    col_old = cfg["colour"]["level_convs"][-1]["channels"]
    assert len(pool["encoder"]) == 2 and len(cfg["select"]["level_convs"]) == 2
    assert len(cfg["colour"]["level_convs"]) == 1 and not cfg["colour"]["merge_convs"]
    assert len(pool["blend"]) == 1 and len(cfg["select"]["merge_convs"]) == 2

    def put(name, w, b):
        t[name + ".weight"], t[name + ".bias"] = w, b

    def grow(name, rows, cols_map, cin):
        put(name, *widened(t[name + ".weight"], t[name + ".bias"], rows, cols_map, cin, rng))

    # Encoder: 7 -> enc -> enc.
    e0 = pool["encoder"][0]["channels"]
    grow("views.encode.0", enc, list(range(7)), 7)
    grow("views.encode.1", enc, list(range(e0)), enc)
    # Pooled stats [rgb, cover, mean_e, var_e]: old columns move with the wider C_f.
    stats_map = list(range(4)) + [4 + j for j in range(cf_old)] + [4 + enc + j for j in range(cf_old)]
    s_in = 4 + 2 * enc
    levels = cfg["select"]["levels"]
    s0 = cfg["select"]["level_convs"][0]["channels"]
    for l in range(levels):
        grow(f"select.levels.{l}.0", sel, stats_map, s_in)
        grow(f"select.levels.{l}.1", sel, list(range(s0)), sel)
    merge_map = [l * sel + j for l in range(levels) for j in range(sel_old)]
    grow("select.merge.0", merge, merge_map, levels * sel)
    m0 = cfg["select"]["merge_convs"][0]["channels"]
    m1 = cfg["select"]["merge_convs"][1]["channels"]
    grow("select.merge.1", m1, list(range(m0)), merge)  # keeps its width: depth convs unchanged
    grow("colour.levels.0.0", colour, stats_map, s_in)
    grow("colour.out", 3, list(range(col_old)), colour)
    # Blend input [e_v, f].
    blend_map = list(range(cf_old)) + [enc + j for j in range(col_old)]
    b0 = pool["blend"][0]["channels"]
    grow("colour.blend.0", blend, blend_map, enc + colour)
    grow("colour.blend.1", 1, list(range(b0)), blend)
    for c in pool["encoder"]:
        c["channels"] = enc
    for c in cfg["select"]["level_convs"]:
        c["channels"] = sel
    cfg["select"]["merge_convs"][0]["channels"] = merge
    cfg["colour"]["level_convs"][0]["channels"] = colour
    pool["blend"][0]["channels"] = blend
    cfg["name"] = cfg["name"] + "-wide"
    model_file.save(dst, cfg_out, meta, t, cfg)
    print(f"{dst}: {sum(v.size for v in t.values())} parameters")


if __name__ == "__main__":
    main()
