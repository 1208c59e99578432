"""Gives a model of the any-number-of-views family the per-view geometric cue
(`deepstereo-core/src/sweep/cue.rs`) without changing what it computes, so the new model
renders exactly as the old one until training moves the new weights:

- by default (`pool.cue`), the first encoder layer gains one input column per cue
  channel, all zero;
- with `--weigh` (`pool.weigh`), the model gains the view weights `views.weigh.*`: a
  hidden layer of `--hidden` channels (PyTorch's default initialisation, `--seed`) and a
  1-channel layer of zeros, so every view's weight `1 + tanh(0)` is 1;
- with `--disagree NEAR` on a model whose views are already weighed (`pool.weigh`), the
  cue gains its colour-disagreement channel (`pool.disagree`,
  `deepstereo-core/src/view_weights.rs`): the first `views.weigh` layer gains one zero
  input column; with `--prior S` also one more hidden unit `relu(q)` whose output weight
  is `-S`, so that `g` becomes `g - S q` and the weights start as a colour gate (`1 + tanh(-4 S q)`
  where the other units give `g` = 0).

    python python/add_cue.py IN.safetensors OUT.safetensors [--name NAME] [--weigh [--hidden 8] [--seed 0]]
    python python/add_cue.py IN.safetensors OUT.safetensors --disagree 4 [--prior S] [--name NAME]

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
    ap.add_argument("--name", default=None, help="the new config's name (default: the input's + '-cue' or '-weigh')")
    ap.add_argument("--weigh", action="store_true", help="the cue weighs the views (pool.weigh) instead of entering the encoder")
    ap.add_argument("--hidden", type=int, default=8, help="--weigh: channels of its hidden layer (0: none)")
    ap.add_argument("--seed", type=int, default=0, help="--weigh: seed of the hidden layer's initialisation")
    ap.add_argument("--disagree", type=int, default=None, metavar="NEAR", help="add the disagreement channel with NEAR reference views (1 to 64) to a model with pool.weigh")
    ap.add_argument("--prior", type=float, default=None, metavar="S", help="--disagree: a hidden unit relu(q) with output weight -S (the weights start as a gate)")
    args = ap.parse_args()
    if args.hidden < 0 or args.hidden > 1024:
        print(f"error: --hidden must be 0 to 1024, got {args.hidden}", file=sys.stderr)
        return 2
    meta, tensors, cfg = model_file.load(args.input)
    pool = cfg.get("pool")
    if not pool:
        print(f"error: {args.input}: not a model of the any-number-of-views family (no pool)", file=sys.stderr)
        return 1
    if args.disagree is not None:
        return add_disagree(args, meta, tensors, cfg)
    if pool.get("cue") or pool.get("weigh") is not None:
        print(f"error: {args.input}: the model already reads the cue", file=sys.stderr)
        return 1
    if args.weigh:
        return add_weigh(args, meta, tensors, cfg)
    w = tensors["views.encode.0.weight"]  # [C0, 7, 1, 1]
    zeros = np.zeros((w.shape[0], CUE_CHANNELS, 1, 1), dtype=w.dtype)
    tensors["views.encode.0.weight"] = np.ascontiguousarray(np.concatenate([w, zeros], axis=1))
    pool["cue"] = True
    return save(args, (meta, tensors, cfg), "-cue", f"encoder input {w.shape[1]} -> {w.shape[1] + CUE_CHANNELS} channels")


def add_weigh(args: argparse.Namespace, meta: dict, tensors: dict, cfg: dict) -> int:
    """`--weigh`: `views.weigh.0` (hidden, uniform in +-1/sqrt(fan_in) as PyTorch's
    `nn.Conv2d`) and the zero 1-channel layer after it."""
    rng = np.random.default_rng(args.seed)
    dtype = tensors["views.encode.0.weight"].dtype
    ch, i = CUE_CHANNELS, 0
    if args.hidden > 0:
        bound = 1.0 / np.sqrt(ch)
        tensors["views.weigh.0.weight"] = rng.uniform(-bound, bound, (args.hidden, ch, 1, 1)).astype(dtype)
        tensors["views.weigh.0.bias"] = rng.uniform(-bound, bound, (args.hidden,)).astype(dtype)
        ch, i = args.hidden, 1
    tensors[f"views.weigh.{i}.weight"] = np.zeros((1, ch, 1, 1), dtype)
    tensors[f"views.weigh.{i}.bias"] = np.zeros((1,), dtype)
    cfg["pool"]["weigh"] = [{"kernel": 1, "channels": args.hidden}] if args.hidden > 0 else []
    return save(args, (meta, tensors, cfg), "-weigh", f"views weighed by their cue, hidden layer {args.hidden}")


def add_disagree(args: argparse.Namespace, meta: dict, tensors: dict, cfg: dict) -> int:
    """`--disagree NEAR`: a zero input column for the disagreement channel in `views.weigh.0`."""
    pool = cfg["pool"]
    if not 1 <= args.disagree <= 64:
        print(f"error: --disagree must be 1 to 64 (MAX_VIEWS), got {args.disagree}", file=sys.stderr)
        return 2
    if pool.get("weigh") is None:
        print(f"error: {args.input}: --disagree needs a model whose cue weighs the views (pool.weigh; add it with --weigh first)", file=sys.stderr)
        return 1
    if pool.get("disagree") is not None:
        print(f"error: {args.input}: the model already has the disagreement channel", file=sys.stderr)
        return 1
    w = tensors["views.weigh.0.weight"]  # [C0, 5, 1, 1]
    if w.shape[1] != CUE_CHANNELS:
        print(f"error: {args.input}: views.weigh.0.weight has {w.shape[1]} input channels, expected {CUE_CHANNELS}", file=sys.stderr)
        return 1
    zeros = np.zeros((w.shape[0], 1, 1, 1), dtype=w.dtype)
    tensors["views.weigh.0.weight"] = np.ascontiguousarray(np.concatenate([w, zeros], axis=1))
    if args.prior is not None:
        if not (np.isfinite(args.prior) and len(pool["weigh"]) == 1):
            print(f"error: --prior needs a finite S and a model with one hidden weigh layer, got {args.prior}, {pool['weigh']}", file=sys.stderr)
            return 2
        unit = np.zeros((1, CUE_CHANNELS + 1, 1, 1), dtype=w.dtype)
        unit[0, CUE_CHANNELS] = 1.0
        tensors["views.weigh.0.weight"] = np.ascontiguousarray(np.concatenate([tensors["views.weigh.0.weight"], unit], axis=0))
        tensors["views.weigh.0.bias"] = np.concatenate([tensors["views.weigh.0.bias"], np.zeros(1, w.dtype)])
        out_w = tensors["views.weigh.1.weight"]  # [1, H, 1, 1]
        tensors["views.weigh.1.weight"] = np.ascontiguousarray(np.concatenate([out_w, np.full((1, 1, 1, 1), -args.prior, w.dtype)], axis=1))
        pool["weigh"][0]["channels"] += 1
    pool["disagree"] = {"near": args.disagree}
    return save(args, (meta, tensors, cfg), "-disagree", f"the views' weights read {CUE_CHANNELS + 1} cue channels, near {args.disagree}")


def save(args: argparse.Namespace, model: tuple, suffix: str, what: str) -> int:
    """Names the new config (`--name`, else the input's name + `suffix`), writes OUT and
    its config as `config.json` beside it, and says `what` changed."""
    meta, tensors, cfg = model
    cfg["name"] = args.name or cfg["name"] + suffix
    out_dir = os.path.dirname(os.path.abspath(args.output))
    model_file.save(args.output, os.path.join(out_dir, "config.json"), meta, tensors, cfg)
    print(f"wrote {args.output} ({cfg['name']}: {what})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
