#!/usr/bin/env bash
# Makes the embedded default model (deepstereo-train/assets/nviews-real.safetensors) from
# a trained run's weights: the same tensors, bit for bit, with the config's default number
# of source views set to VIEWS (the any-number-of-views family takes any number; this is
# only what commands use without --views). Needs the test command's venv (safetensors).
# Usage: bash deepstereo-train/scripts/ship_default.sh [MODEL] [VIEWS]
set -euo pipefail
cd "$(dirname "$0")/../.."
MODEL="${1:-deepstereo-train/runs/nviews-real/model.safetensors}"
VIEWS="${2:-4}"
OUT=deepstereo-train/assets/nviews-real.safetensors
.venv/bin/python - "$MODEL" "$VIEWS" "$OUT" <<'PY'
import json, os, sys
from safetensors import safe_open
from safetensors.numpy import save_file
src, views, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
with safe_open(src, "np") as f:
    meta = dict(f.metadata())
    tensors = {k: f.get_tensor(k) for k in f.keys()}
cfg = json.loads(meta["deepstereo.config"])
if cfg.get("pool") is None:
    sys.exit(f"{src}: not an any-number-of-views model (no pool in its config)")
cfg["views"] = views
meta["deepstereo.config"] = json.dumps(cfg, separators=(",", ":"))
tmp = out + ".tmp"
save_file(tensors, tmp, metadata=meta)
os.replace(tmp, out)
print(f"{out}: {sum(t.size for t in tensors.values())} parameters, default views {views}")
PY
