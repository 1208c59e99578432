"""Data-parallel training of the PyTorch reference (`deepstereo_ref.DeepStereo`) on the
samples `deepstereo samples` writes, with DistributedDataParallel.

    deepstereo samples --synthetic 64 --config tiny --count 4096 --shard-size 16 --seed 0 --out shards
    torchrun --nproc-per-node 2 python/train_ddp.py --shards shards --init runs/tiny/model.safetensors \\
        --optimizer adam --lr 1e-3 --steps 1000 --batch 8 --out runs/ddp

The model starts from `--init` weights, or is initialised afresh (`--seed`) for `--config`:
a preset by name as `deepstereo train --config` takes it (tiny, paper, nviews;
`deepstereo_ref.Config.preset`), a config JSON file, or a weights file holding one; by
default, the shards' config. Bad input (a missing shards directory, an unknown preset, an
unreadable or corrupt file, a checkpoint of other options) ends with one `error:` line:
exit status 2 for the arguments, 1 for what the files hold.

`--lr-schedule cosine:START-END --lr-final F` decays the rate as `deepstereo train` does
(`optim_ref.LrSchedule`, lr.rs), so the fine-tuning recipes of the default model
(`deepstereo-train/scripts/train.sh`) have a DDP equivalent.

One process without torchrun works too. The backend is `nccl` when CUDA is available
(one GPU per process, `LOCAL_RANK`), else `gloo` on the CPU.

Data: the training shards (all but the last `--val-shards`) are cut into chunks of the
global batch (`--batch` x processes); step `s` (0-based) uses chunk `s` (cycling), and
rank `r` takes samples `[r*batch, (r+1)*batch)` of it. The data of a step therefore
depends only on the global batch, not on the number of processes; with `--shard-size`
equal to the global batch, step `s` sees exactly the batch `s` of `deepstereo train` with
the same seed and options. Gradients are averaged over processes (the mean L1 loss of the
global batch, or its mean squared error with `--loss l2`, as `deepstereo train --loss`);
the optimizer (`optim_ref.py`) is optim.rs's update, op for op.

Files in --out (written by rank 0, atomically): `model.safetensors` (float32, metadata
`deepstereo.config` and `format`: what `deepstereo render/eval/export --model` load),
`checkpoint.safetensors` (weights, optimizer state `optim.first.*`/`optim.second.*` as
candle names them, step, run options), `log.jsonl` (training.rs `LogLine`s).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NoReturn

import torch
import torch.distributed as dist
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

import deepstereo_ref as ref
from optim_ref import DEFAULT_LR_FINAL, KINDS, LrSchedule, RefOptimizer

SHARD_FORMAT = "deepstereo-samples-v1"
SHARD_GLOB = "shard-*.safetensors"
TARGET = "target"
RUN_KEY = "deepstereo.ddp"
STEP_KEY = "deepstereo.step"
OPT_STEPS_KEY = "optimizer.steps"
MAX_CONSECUTIVE_BAD_STEPS = 5  # training.rs
SHARD_CACHE = 4  # shards kept in memory per process


@dataclass
class RunOptions:
    """What defines a run (saved in the checkpoint; a resume must match)."""

    shards: str
    config: str
    optimizer: str
    lr: float
    global_batch: int
    val_shards: int
    init: str | None
    seed: int
    loss: str = "l1"


# --- files ----------------------------------------------------------------------------


def write_atomic(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        save_file({k: v.detach().to("cpu", torch.float32).contiguous() for k, v in tensors.items()}, str(tmp), metadata=metadata)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def fail(msg: str) -> NoReturn:
    """Ends the process with `error: MSG` on stderr and exit status 1."""
    raise SystemExit(f"error: {msg}")


def metadata_of(path: Path) -> dict[str, str]:
    try:
        with safe_open(str(path), framework="pt") as f:
            return f.metadata() or {}
    except (OSError, SafetensorError) as e:
        fail(f"{path}: not a readable safetensors file ({e})")


def tensors_of(path: Path) -> dict[str, torch.Tensor]:
    try:
        return load_file(str(path))
    except (OSError, SafetensorError) as e:
        fail(f"{path}: not a readable safetensors file ({e})")


def parse_config(text: str, origin: str) -> ref.Config:
    try:
        return ref.Config.from_json(text)
    except (ValueError, KeyError, TypeError) as e:
        fail(f"{origin}: not a valid config ({type(e).__name__}: {e})")


def config_json_of(path: Path) -> str:
    """A config JSON (checked) from a JSON file or from a weights/shard file's metadata."""
    if path.suffix == ".json":
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as e:
            fail(f"{path}: cannot read it ({e})")
    else:
        meta = metadata_of(path)
        if ref.CONFIG_KEY not in meta:
            fail(f"{path}: no '{ref.CONFIG_KEY}' in the metadata")
        text = meta[ref.CONFIG_KEY]
    parse_config(text, str(path))
    return text


def resolve_config(spec: str) -> str:
    """`--config`: a preset's JSON, as `deepstereo train --config` takes presets by name,
    else the config of a JSON file or of a weights file."""
    preset = ref.Config.preset(spec)
    if preset is not None:
        return preset.to_json()
    path = Path(spec)
    if not path.is_file():
        fail(f"--config '{spec}' is neither a preset ({', '.join(ref.PRESETS)}) nor a readable file")
    return config_json_of(path)


@dataclass
class Shard:
    path: Path
    samples: int
    views: int


def list_shards(d: Path) -> tuple[list[Shard], str]:
    paths = sorted(d.glob(SHARD_GLOB))
    if not paths:
        fail(f"{d}: no {SHARD_GLOB} (write them with `deepstereo samples`)")
    shards, cfg_json = [], None
    for p in paths:
        m = metadata_of(p)
        if m.get("format") != SHARD_FORMAT:
            fail(f"{p}: not a deepstereo samples shard (format {m.get('format')!r})")
        try:
            samples, views = int(m["samples"]), int(m["views"])
            text = m[ref.CONFIG_KEY]
        except (KeyError, ValueError) as e:
            fail(f"{p}: a shard without a valid {e} in its metadata")
        if cfg_json is not None and parse_config(text, str(p)) != parse_config(cfg_json, str(paths[0])):
            fail(f"{p}: made for another config than {paths[0]}")
        cfg_json = cfg_json or text
        shards.append(Shard(p, samples, views))
    parse_config(cfg_json, str(paths[0]))
    return shards, cfg_json


def shard_warps(cfg: ref.Config, t: dict[str, torch.Tensor], samples, views: int, device) -> list[dict] | None:
    """The features family's warps (`DeepStereo.warped_features`) of `samples` of a shard
    `t` (its `warp.K.L.V.*` tensors); None for other models."""
    if cfg.pool is None or not cfg.pool.source_features:
        return None
    warps = []
    for k in samples:
        w = {}
        for l in range(cfg.levels):
            for v in range(views):
                stem = f"warp.{k}.{l}.{v}"
                if f"{stem}.crop" in t:
                    w[(l, v)] = tuple(t[f"{stem}.{part}"].to(device) for part in ("crop", "index", "weight"))
        warps.append(w)
    return warps


class Shards:
    """Loads shards on demand, keeping the last few in memory."""

    def __init__(self, cfg: ref.Config):
        self.cfg = cfg
        self.cache: dict[Path, dict[str, torch.Tensor]] = {}

    def get(self, s: Shard) -> dict[str, torch.Tensor]:
        if s.path not in self.cache:
            if len(self.cache) >= SHARD_CACHE:
                self.cache.pop(next(iter(self.cache)))
            t = tensors_of(s.path)
            for name in [f"level{l}" for l in range(self.cfg.levels)] + [TARGET]:
                if name not in t:
                    fail(f"{s.path}: no tensor '{name}'")
            self.cache[s.path] = t
        return self.cache[s.path]

    def batch(self, s: Shard, start: int, n: int, device) -> tuple[list[torch.Tensor], torch.Tensor, list[dict] | None]:
        """Samples `[start, start + n)`: the inputs per level, the targets, and for the
        features family each sample's warps (`DeepStereo.warped_features`)."""
        t = self.get(s)
        xs = [t[f"level{l}"][start : start + n].to(device) for l in range(self.cfg.levels)]
        return xs, t[TARGET][start : start + n].to(device), shard_warps(self.cfg, t, range(start, start + n), xs[0].shape[2], device)


# --- the run --------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shards", type=Path, required=True, help="directory of `deepstereo samples` shards")
    ap.add_argument("--init", type=Path, help="start from these weights (a model.safetensors or a candle checkpoint.safetensors)")
    ap.add_argument("--config", metavar="CONFIG", help=f"config of a freshly initialised model: a preset ({', '.join(ref.PRESETS)}), as `deepstereo train --config`, or a JSON file of a Config, or a weights file holding one; default: the shards' config")
    ap.add_argument("--seed", type=int, default=0, help="seed of the PyTorch initialisation (without --init)")
    ap.add_argument("--optimizer", choices=KINDS, default="adagrad")
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--lr-schedule", default="constant", help="`constant`, or `cosine:START-END` (the rate --lr up to step START, a cosine down to --lr-final times it at END), as `deepstereo train`; a resumed run may change it")
    ap.add_argument("--lr-final", type=float, default=DEFAULT_LR_FINAL, help="the final rate's share of --lr for a cosine --lr-schedule")
    ap.add_argument("--loss", choices=("l1", "l2"), default="l1", help="training loss: l1 (mean absolute error, the paper's) or l2 (mean squared error), as `deepstereo train --loss`")
    ap.add_argument("--steps", type=int, default=1000, help="total optimizer steps (a resumed run continues up to this count)")
    ap.add_argument("--batch", type=int, default=8, help="samples per process and step")
    ap.add_argument("--checkpoint-every", type=int, default=100)
    ap.add_argument("--validate-every", type=int, default=100)
    ap.add_argument("--log-every", type=int, default=10)
    ap.add_argument("--val-shards", type=int, default=1, help="the last N shards are held out for validation PSNR")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    ap.add_argument("--threads", type=int, default=0, help="torch threads per process (default: cores / local processes)")
    a = ap.parse_args(argv)
    for name in ("steps", "batch", "checkpoint_every", "validate_every", "log_every"):
        least = 0 if name == "steps" else 1
        if getattr(a, name) < least:
            ap.error(f"--{name.replace('_', '-')} must be at least {least}")
    for name in ("seed", "threads", "val_shards"):
        if getattr(a, name) < 0:
            ap.error(f"--{name.replace('_', '-')} must not be negative")
    if not (math.isfinite(a.lr) and a.lr > 0):
        ap.error(f"--lr must be a positive number, got {a.lr}")
    if a.init is not None and a.config is not None:
        ap.error("pass --init or --config, not both")
    if not a.shards.is_dir():
        ap.error(f"--shards {a.shards}: not a directory")
    if a.init is not None and not a.init.is_file():
        ap.error(f"--init {a.init}: no such file")
    if a.config is not None and ref.Config.preset(a.config) is None and not Path(a.config).is_file():
        ap.error(f"--config '{a.config}' is neither a preset ({', '.join(ref.PRESETS)}) nor a readable file")
    if a.out.exists() and not a.out.is_dir():
        ap.error(f"--out {a.out}: not a directory")
    if a.resume and not (a.out / "checkpoint.safetensors").is_file():
        ap.error(f"--resume: no checkpoint.safetensors in {a.out}")
    try:
        a.schedule = LrSchedule(a.lr_schedule, a.lr_final)
    except ValueError as e:
        ap.error(str(e))
    return a


def setup(a: argparse.Namespace) -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
    cuda = a.device == "cuda" or (a.device == "auto" and torch.cuda.is_available())
    if cuda:
        torch.cuda.set_device(local)
        device = torch.device("cuda", local)
    else:
        device = torch.device("cpu")
        threads = a.threads or max(1, (os.cpu_count() or 1) // local_world)
        torch.set_num_threads(threads)
    if world > 1:
        dist.init_process_group(backend="nccl" if cuda else "gloo")
    return rank, world, device


def psnr(model: ref.DeepStereo, shards: Shards, val: list[Shard], batch: int, device) -> float | None:
    se, n = 0.0, 0
    with torch.no_grad():
        for s in val:
            for start in range(0, s.samples, batch):
                xs, y, warps = shards.batch(s, start, min(batch, s.samples - start), device)
                d = model(xs, warps)[0].clamp(0, 1) - y
                se += float(d.double().square().sum())
                n += d.numel()
    if n == 0:
        return None
    return -10.0 * math.log10(max(se / n, 1e-12))


def main(argv=None) -> int:
    a = parse_args(argv)
    rank, world, device = setup(a)
    shards_all, shard_cfg = list_shards(a.shards)
    if not 0 <= a.val_shards < len(shards_all):
        fail(f"--val-shards {a.val_shards} leaves no training shard ({len(shards_all)} shards)")
    train_shards = shards_all[: len(shards_all) - a.val_shards]
    val_shards = shards_all[len(shards_all) - a.val_shards :]
    cfg_json = config_json_of(a.init) if a.init else resolve_config(a.config) if a.config else shard_cfg
    cfg = ref.Config.from_json(cfg_json)
    check_geometry(cfg, ref.Config.from_json(shard_cfg), a.shards)
    gbatch = a.batch * world
    chunks = [(s, c * gbatch) for s in train_shards for c in range(s.samples // gbatch)]
    if not chunks:
        fail(f"no training shard holds a global batch of {gbatch} samples (--batch {a.batch} x {world} processes)")
    run = RunOptions(str(a.shards.resolve()), cfg_json, a.optimizer, a.lr, gbatch, a.val_shards, str(a.init) if a.init else None, a.seed, a.loss)

    torch.manual_seed(a.seed)
    model = ref.DeepStereo(cfg).to(device)
    if a.init is not None:
        state = {k: v for k, v in tensors_of(a.init).items() if not k.startswith("optim.")}
        load_weights(model, state, a.init)
    opt = RefOptimizer(a.optimizer, a.lr, list(model.named_parameters()))
    out = a.out
    ckpt, log_path = out / "checkpoint.safetensors", out / "log.jsonl"
    start = 0
    if a.resume:
        start = restore(ckpt, run, model, opt)
    elif ckpt.exists():
        fail(f"{out} already holds a checkpoint: pass --resume to continue it, or choose another --out")
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        if a.resume:
            keep = [l for l in log_path.read_text().splitlines() if l.strip() and json.loads(l)["step"] <= start] if log_path.exists() else []
            write_text_atomic(log_path, "".join(l + "\n" for l in keep))
            print(f"resuming {out} at step {start}", file=sys.stderr)
        else:
            write_text_atomic(log_path, "")
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    shards = Shards(cfg)
    log = open(log_path, "a") if rank == 0 else None
    t0 = time.time()
    window_t, window_n, bad, step = time.time(), 0, 0, start
    while step < a.steps:
        shard, base = chunks[step % len(chunks)]
        xs, y, warps = shards.batch(shard, base + rank * a.batch, a.batch, device)
        opt.zero_grad()
        diff = net(xs, warps)[0] - y
        loss = diff.abs().mean() if a.loss == "l1" else diff.square().mean()
        loss.backward()
        loss_v = loss.detach().double()
        if world > 1:
            dist.all_reduce(loss_v)
            loss_v /= world
        loss_v = float(loss_v)
        gnorm = opt.grad_norm()
        step += 1
        window_n += gbatch
        skipped = not (math.isfinite(loss_v) and math.isfinite(gnorm))
        if skipped:
            bad += 1
            print(f"step {step}: non-finite loss {loss_v} or gradient norm {gnorm}: step skipped", file=sys.stderr)
            if bad >= MAX_CONSECUTIVE_BAD_STEPS:
                fail(f"{bad} consecutive non-finite steps: training stopped; the last good checkpoint is {ckpt}")
        else:
            bad = 0
            opt.lr = a.schedule.lr_at(a.lr, opt.steps)
            opt.step()
        validate_now = step % a.validate_every == 0 or step == a.steps
        if rank == 0 and (step % a.log_every == 0 or validate_now or skipped):
            secs = time.time() - window_t
            line = {
                "step": step,
                "loss": loss_v if math.isfinite(loss_v) else None,
                "lr": opt.lr,
                "samples_per_s": window_n / max(secs, 1e-9),
                "grad_norm": gnorm if math.isfinite(gnorm) else None,
                "val_psnr": psnr(model, shards, val_shards, a.batch, device) if validate_now else None,
                "skipped": skipped,
                "seconds": time.time() - t0,
            }
            log.write(json.dumps(line) + "\n")
            log.flush()
            val = f" val {line['val_psnr']:.2f} dB" if line["val_psnr"] is not None else ""
            print(f"step {step}: loss {loss_v:.5f} ({line['samples_per_s']:.1f} samples/s){val}", file=sys.stderr)
            window_t, window_n = time.time(), 0
        if rank == 0 and (step % a.checkpoint_every == 0 or step == a.steps):
            save(out, run, cfg_json, model, opt, step)
    if rank == 0 and step == 0:
        save(out, run, cfg_json, model, opt, 0)
    if log is not None:
        log.close()
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    if rank == 0:
        print(f"model: {out / 'model.safetensors'}", file=sys.stderr)
    return 0


def check_geometry(cfg: ref.Config, shard_cfg: ref.Config, d: Path) -> None:
    """The model must read the shards' inputs: same levels, planes, tile, input sizes and
    family (and views, for the paper's family)."""
    same = (
        cfg.levels == shard_cfg.levels
        and cfg.planes == shard_cfg.planes
        and cfg.tile == shard_cfg.tile
        and all(cfg.input_size(l, cfg.tile) == shard_cfg.input_size(l, shard_cfg.tile) for l in range(cfg.levels))
        and (cfg.pool is None) == (shard_cfg.pool is None)
        and (cfg.pool is not None or cfg.views == shard_cfg.views)
    )
    if not same:
        fail(f"the model '{cfg.name}' does not read the inputs of the shards in {d} (made for '{shard_cfg.name}')")


def save(out: Path, run: RunOptions, cfg_json: str, model: ref.DeepStereo, opt: RefOptimizer, step: int) -> None:
    weights = dict(model.state_dict())
    for k, v in weights.items():
        if not torch.isfinite(v).all():
            fail(f"tensor '{k}' holds non-finite values: not saved")
    meta = {ref.CONFIG_KEY: cfg_json, ref.FORMAT_KEY: ref.FORMAT_VALUE}
    ck_meta = dict(meta, **{RUN_KEY: json.dumps(asdict(run)), STEP_KEY: str(step), OPT_STEPS_KEY: str(opt.steps)})
    write_atomic(out / "checkpoint.safetensors", {**weights, **opt.state()}, ck_meta)
    write_atomic(out / "model.safetensors", weights, meta)


def load_weights(model: ref.DeepStereo, state: dict[str, torch.Tensor], path: Path) -> None:
    """Loads `state` strictly; a missing, unexpected or misshapen tensor is an error."""
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as e:
        detail = " ".join(str(e).split())
        fail(f"{path}: its tensors do not fit the config '{model.cfg.name}' ({detail[:300]})")


def restore(ckpt: Path, run: RunOptions, model: ref.DeepStereo, opt: RefOptimizer) -> int:
    if not ckpt.exists():
        fail(f"--resume: no {ckpt}")
    meta = metadata_of(ckpt)
    try:
        saved = RunOptions(**json.loads(meta[RUN_KEY]))
        step, opt_steps = int(meta[STEP_KEY]), int(meta[OPT_STEPS_KEY])
    except KeyError as e:
        fail(f"{ckpt}: no {e} in its metadata (not a train_ddp.py checkpoint)")
    except (ValueError, TypeError) as e:
        fail(f"{ckpt}: unreadable run options or step ({e})")
    if saved != run:
        fail(f"{ckpt}: the checkpoint was made with different options:\n  saved: {saved}\n  now:   {run}")
    tensors = tensors_of(ckpt)
    device = next(model.parameters()).device
    load_weights(model, {k: v for k, v in tensors.items() if not k.startswith("optim.")}, ckpt)
    try:
        opt.restore(opt_steps, {k: v.to(device) for k, v in tensors.items() if k.startswith("optim.")})
    except (KeyError, RuntimeError, ValueError) as e:
        fail(f"{ckpt}: its optimizer state does not fit the model ({e})")
    return step


if __name__ == "__main__":
    code = main()
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        # Every output is written and closed and the process group destroyed. Leaving
        # without the interpreter's finalization: there, gloo's worker threads can still
        # hold work whose tensors need the GIL, and a rank then aborts ("terminate called
        # without an active exception") after a run that succeeded.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)
