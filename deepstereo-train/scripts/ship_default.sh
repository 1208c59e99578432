#!/usr/bin/env bash
# Makes the embedded default model (deepstereo-train/assets/nviews-disagree-scratch.safetensors) from
# a trained run's weights: the same tensors, bit for bit, with the config's default number
# of source views set to VIEWS (the any-number-of-views family takes any number; this is
# only what commands use without --views) and, when the config has none, the view falloff
# FALLOFF (`full:power`, config pool.falloff, deepstereo-core/src/view_weights.rs; it
# changes nothing at `full` views or fewer). Needs the test command's venv (safetensors).
# OUT (default: the asset) lets the same conversion write elsewhere, e.g. the README's
# "previous weights with the 1:2 falloff" column:
#   ship_default.sh deepstereo-train/runs/nviews-falloff/init.safetensors 4 1:2 /tmp/f1_2.safetensors
# Usage: bash deepstereo-train/scripts/ship_default.sh [MODEL] [VIEWS] [FALLOFF] [OUT]
set -euo pipefail
cd "$(dirname "$0")/../.."
# Default: the weights of the run with the per-view cue and the colour-disagreement channel
# (runs/nviews-disagree-scratch at step 8600, its config with pool.falloff 1:2). The
# default before it was runs/nviews-weigh-scratch at step 8600 (commit c4032f1), before
# that runs/nviews-prox at step 2000 (commit 0afcee9), and before that runs/nviews-real at
# step 8600 (commit 29f97d2), kept as runs/nviews-falloff/init.safetensors.
MODEL="${1:-deepstereo-train/runs/nviews-disagree-scratch/model.safetensors}"
VIEWS="${2:-4}"
FALLOFF="${3:-4:8}"
OUT="${4:-deepstereo-train/assets/nviews-disagree-scratch.safetensors}"
.venv/bin/python - "$MODEL" "$VIEWS" "$OUT" "$FALLOFF" <<'PY'
import json, os, sys
from safetensors import safe_open
from safetensors.numpy import save_file
src, views, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
full, power = (int(x) for x in sys.argv[4].split(":"))
with safe_open(src, "np") as f:
    meta = dict(f.metadata())
    tensors = {k: f.get_tensor(k) for k in f.keys()}
cfg = json.loads(meta["deepstereo.config"])
if cfg.get("pool") is None:
    sys.exit(f"{src}: not an any-number-of-views model (no pool in its config)")
cfg["views"] = views
cfg["pool"].setdefault("falloff", {"full": full, "power": power})
meta["deepstereo.config"] = json.dumps(cfg, separators=(",", ":"))
tmp = out + ".tmp"
save_file(tensors, tmp, metadata=meta)
os.replace(tmp, out)
print(f"{out}: {sum(t.size for t in tensors.values())} parameters, default views {views}, falloff {cfg['pool']['falloff']}")
PY
