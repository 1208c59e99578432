"""Averages the weights of models that share an architecture and a starting point (a
uniform "model soup", Wortsman et al. 2022): fine-tunes of one set of weights usually lie
in one basin, and their mean often scores better than each. The config (and metadata)
is the first model's; every model must have the same tensors with the same shapes.
Usage: python python/soup.py OUT.safetensors OUT_CONFIG.json MODEL.safetensors MODEL2... """
import sys

import numpy as np

import model_file


def main(argv):
    if len(argv) > 1 and argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        return
    if len(argv) < 4:
        sys.exit(__doc__.strip().splitlines()[-1])
    out, cfg_out, paths = argv[1], argv[2], argv[3:]
    meta, first, cfg = model_file.load(paths[0])
    acc = {k: v.astype(np.float64) for k, v in first.items()}
    for p in paths[1:]:
        _, t, c = model_file.load(p)
        if set(t) != set(acc) or any(t[k].shape != acc[k].shape for k in acc):
            sys.exit(f"{p}: its tensors differ from {paths[0]}'s (not the same architecture)")
        if {k: v for k, v in c.items() if k != "views"} != {
            k: v for k, v in cfg.items() if k != "views"
        }:
            sys.exit(f"{p}: its config differs from {paths[0]}'s beyond the default views")
        for k in acc:
            acc[k] += t[k]
    mean = {k: (v / len(paths)).astype(first[k].dtype) for k, v in acc.items()}
    model_file.save(out, cfg_out, meta, mean, cfg)
    print(f"{out}: the mean of {len(paths)} models")


if __name__ == "__main__":
    main(sys.argv)
