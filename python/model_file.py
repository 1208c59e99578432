"""Reading and writing a model file (safetensors with its config in the metadata) for
the scripts that rewrite one (soup.py; the architecture-changing tools of the runs at
commit fda1758 used it too). Needs numpy and safetensors (python/requirements.txt)."""
import json
import os

from safetensors import safe_open
from safetensors.numpy import save_file


def load(path):
    """The file's metadata, tensors (name -> array) and config (parsed)."""
    with safe_open(path, "np") as f:
        meta = dict(f.metadata())
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    return meta, tensors, json.loads(meta["deepstereo.config"])


def save(path, cfg_path, meta, tensors, cfg):
    """Writes the tensors with `cfg` as their config to `path`, and `cfg` alone as JSON to
    `cfg_path` (the run's config.json), each atomically (temp file, then rename)."""
    meta = dict(meta, **{"deepstereo.config": json.dumps(cfg, separators=(",", ":"))})
    save_file(tensors, path + ".tmp", metadata=meta)
    os.replace(path + ".tmp", path)
    with open(cfg_path + ".tmp", "w") as f:
        json.dump(cfg, f, indent=1)
    os.replace(cfg_path + ".tmp", cfg_path)
