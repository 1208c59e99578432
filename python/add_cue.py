"""Gives a model of the any-number-of-views family the per-view geometric cue
(`pool.cue`, `deepstereo-core/src/sweep/cue.rs`) without changing what it computes: the
first encoder layer gains one input column per cue channel, all zero, so the new model
renders exactly as the old one until training moves them.

    python python/add_cue.py IN.safetensors OUT.safetensors [--name NAME]

Writes OUT and its config alone beside it as `config.json` (the run directory's), each
atomically. Needs numpy and safetensors (python/requirements.txt)."""
import argparse
import os
import sys

import numpy as np

import model_file

CUE_CHANNELS = 5  # deepstereo-core/src/config.rs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("input")
    ap.add_argument("output")
    ap.add_argument("--name", default=None, help="the new config's name (default: the input's + '-cue')")
    args = ap.parse_args()
    meta, tensors, cfg = model_file.load(args.input)
    pool = cfg.get("pool")
    if not pool:
        print(f"error: {args.input}: not a model of the any-number-of-views family (no pool)", file=sys.stderr)
        return 1
    if pool.get("cue"):
        print(f"error: {args.input}: the model already reads the cue", file=sys.stderr)
        return 1
    w = tensors["views.encode.0.weight"]  # [C0, 7, 1, 1]
    zeros = np.zeros((w.shape[0], CUE_CHANNELS, 1, 1), dtype=w.dtype)
    tensors["views.encode.0.weight"] = np.ascontiguousarray(np.concatenate([w, zeros], axis=1))
    pool["cue"] = True
    cfg["name"] = args.name or cfg["name"] + "-cue"
    out_dir = os.path.dirname(os.path.abspath(args.output))
    model_file.save(args.output, os.path.join(out_dir, "config.json"), meta, tensors, cfg)
    print(f"wrote {args.output} ({cfg['name']}: encoder input {w.shape[1]} -> {w.shape[1] + CUE_CHANNELS} channels)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
