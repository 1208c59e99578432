"""Checks of `train_ddp.py` against the candle trainer, for both model families.

    python python/ddp_check.py --bin target/release/deepstereo

For `tiny` (the paper's family), `nviews` (any number of views, 2-5 per shard),
`nviews-cue`, `nviews-weigh` and `nviews-disagree` (the same with each view's geometric cue,
and its colour disagreement, in the shards) and `nviews-features` (a per-source CNN whose
crops and warps the shards carry, run and warped in both trainers' graphs), from
the same Rust-initialised weights (`deepstereo train --steps 0`) and the shards of
`deepstereo samples` with the trainer's seed and a shard size equal to its batch:

(a) the update: `examples/candle_step` (candle, optim.rs) takes STEPS steps and writes
    its gradients; `optim_ref.py` applied to the same gradients gives the same weights
    (Adam and Adagrad, every tensor within 1e-6 of its largest magnitude); the gradients
    of PyTorch on the same batch agree with candle's (1e-4 over all tensors); and one step
    of `deepstereo train` (the online sampler) equals one step of `train_ddp.py` on the
    shards (every tensor within 1e-5 relative): the shards are the trainer's batches;
(b) `torchrun --nproc-per-node 2` (gloo, CPU) with half the batch per process gives the
    weights of one process with the whole batch;
(c) a DDP run stopped at a checkpoint and resumed gives the weights of the uninterrupted
    DDP run, and its log has one line per step;
(d) `deepstereo forward --model OUT/model.safetensors` on a shard equals PyTorch's forward
    of the same file (1e-4), and `deepstereo export --model` takes the file;
(e) the same `--lr-schedule cosine:...` and `--lr-final` give the same rate at every step
    in the logs of `deepstereo train` and of `train_ddp.py` (tiny only);
(f) `--loss l2`: one step of each trainer logs the same loss (1e-5 relative; not the L1
    run's) and gives the same weights (tiny only);
(g) `train_ddp.py --config PRESET` (a preset by name, as `deepstereo train --config`)
    writes the config `deepstereo train --config PRESET` does;
(h) bad input (unknown preset, missing shards directory or --init, a corrupt file, a bad
    number, --resume without a checkpoint) ends with an `error:` line and exit status 2
    or 1, no traceback.

Exit status 1 when any check fails.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

import deepstereo_ref as ref
import train_ddp
from optim_ref import RefOptimizer

ROOT = Path(__file__).resolve().parent.parent
WEIGHT_TOL = 1e-5
IMAGE_TOL = 1e-4
SEED = 3
BATCH = 4  # the global batch, and the shard size
STEPS = 2  # steps of the update check (a); (b) and (c) run STEPS + 1
# The update check feeds candle's gradients to optim_ref.py: the same float32 operations,
# so the weights agree to rounding.
UPDATE_LR = 1e-3
UPDATE_TOL = 1e-6
# The runs that compute their own gradients (candle against PyTorch, 2 processes against
# 1) use a smaller rate: Adam's and Adagrad's first steps are about lr * sign(g), so a
# weight whose gradient is at float32's noise floor (dead ReLUs, biases a softmax ignores:
# two thirds of tiny's select.merge.0 gradients are under 1e-7 at init) can move by up to
# lr differently in two correct implementations; that difference scales with lr.
LR = 1e-4
# Gradients of candle and PyTorch on the same batch, all tensors together: candle sums its
# float32 reductions in order (the output bias sums ~7e4 terms), PyTorch pairwise, so they
# differ by a few 1e-5 (measured 3.4e-5 for tiny, 2.0e-5 for nviews).
GRAD_TOL = 1e-4
# Scenes and sampling shared by `train` and `samples` (small, to keep the check short).
SCENES = ["--synthetic", "2", "--synth-size", "64x48", "--synth-views", "6"]
FAMILIES = {
    "tiny": [],
    "nviews": ["--views", "2-5"],
    "nviews-cue": ["--views", "2-5"],
    "nviews-weigh": ["--views", "2-5"],
    "nviews-disagree": ["--views", "2-5"],
    "nviews-features": ["--views", "2-5"],
}
# What a rank prints when gloo's teardown aborts it after its work is done.
TEARDOWN_ABORT = "terminate called without an active exception"


def run(cmd: list, what: str, env: dict | None = None) -> subprocess.CompletedProcess:
    p = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, env=env)
    if p.returncode != 0:
        raise RuntimeError(f"{what} failed ({p.returncode}): {' '.join(map(str, cmd))}\n{p.stdout}\n{p.stderr}")
    return p


# Differences are measured relative to a tensor's largest magnitude, but never to less than
# the scale of freshly initialised weights: a one-element tensor that happens to sit near
# zero would otherwise turn rounding into a large relative difference. (Seen on
# `select.depth.{last}.bias` of a fresh `nviews-cue`, |b| = 0.04: its gradient is a sum over
# planes that nearly cancels, so candle and PyTorch disagree on it by 8% while agreeing on
# every other tensor to 1e-4, and Adam turns that into steps that differ by 4% of its
# 4.5e-5 movement, 1.8e-6 in all.)
WEIGHT_SCALE_FLOOR = 0.25


# Adagrad's step is `lr g / (|g| + eps)` on the first step (eps = 1e-10, optim.rs): for a
# gradient within a few orders of eps (a nearly dead unit: 1.4e-10 was seen in
# `colour.blend.0.weight` of a fresh `nviews-weigh`), the two runtimes' rounding of g, a
# few percent there, becomes a few percent of the step. Such elements are left out of the
# end-to-end Adagrad comparison (their gradients are compared with the rest above, and
# optim_ref.py's update on candle's gradients is compared exactly). At |g| >= 100 eps a
# relative rounding r of g moves the step by at most r / 100 of it: 3e-7 of a weight at
# r = 3% and lr 1e-3, within the tolerance.
# Adam's first step is `lr g / (|g| + 1e-8)`: below |g| = 1e-8 it is proportional to g,
# and a gradient whose true value is 0 (the blend logits' shared bias: the softmax ignores
# a shift; 1.3e-9 of noise in a fresh `nviews-features`) has no significant digit, so the
# same elements are left out of the end-to-end Adam comparison.
ADAGRAD_EPS = 1e-10
ILL_CONDITIONED = 100 * ADAGRAD_EPS


def worst(a: Path, b: Path, floor: float, skip: dict | None = None) -> tuple[float, str]:
    """The largest per-tensor difference of two weights files, relative to the tensor's
    largest magnitude (at least `floor`), and the tensor's name; `skip` (name -> bool
    mask) leaves elements out."""
    x, y = load_file(str(a)), load_file(str(b))
    if set(x) != set(y):
        return float("inf"), f"different tensors: {sorted(set(x) ^ set(y))}"
    out = (0.0, "")
    for k in sorted(x):
        diff = (x[k].double() - y[k].double()).abs()
        if skip is not None and k in skip:
            diff = diff.masked_fill(skip[k], 0.0)
        d = float(diff.max()) / max(float(y[k].double().abs().max()), floor)
        out = max(out, (d, k))
    return out


class Check:
    def __init__(self, binary: Path, work: Path):
        self.bin, self.work = binary, work
        self.example = binary.parent / "examples" / "candle_step"
        if not self.example.is_file():
            raise SystemExit(f"error: {self.example} not found: build it with `cargo build --release -p deepstereo-train --examples`")
        self.failures: list[str] = []

    def expect(self, ok: bool, msg: str) -> None:
        print(("ok   " if ok else "FAIL ") + msg, flush=True)
        if not ok:
            self.failures.append(msg)

    def same_weights(self, what: str, a: Path, b: Path, tol: float = WEIGHT_TOL, floor: float = WEIGHT_SCALE_FLOOR, skip: dict | None = None) -> None:
        """Compares at the scale of initialised weights (the runs being compared sum in
        other orders); `floor=1e-12` for exact-arithmetic checks."""
        d, name = worst(a, b, floor, skip)
        left = f"; {sum(int(m.sum()) for m in skip.values())} elements with |g| < {ILL_CONDITIONED:.0e} left out" if skip else ""
        self.expect(d <= tol, f"{what}: worst tensor {name} differs by {d:.2e} relative (tolerance {tol:.0e}{left})")

    def same_gradients(self, preset: str, net: ref.DeepStereo, x: dict, candle: dict) -> None:
        net.zero_grad()
        xs = [x[f"level{l}"] for l in range(net.cfg.levels)]
        warps = train_ddp.shard_warps(net.cfg, x, range(xs[0].shape[0]), xs[0].shape[2], "cpu")
        loss = (net(xs, warps)[0] - x["target"]).abs().mean()
        loss.backward()
        diff = sum(float((p.grad.double() - candle[k].double()).square().sum()) for k, p in net.named_parameters())
        norm = sum(float(candle[k].double().square().sum()) for k, _ in net.named_parameters())
        rel = (diff / max(norm, 1e-30)) ** 0.5
        per = max((float((p.grad - candle[k]).norm() / max(float(candle[k].norm()), 1e-30)), k) for k, p in net.named_parameters())
        self.expect(rel <= GRAD_TOL, f"{preset}: gradients of candle and PyTorch on shard 0: {rel:.2e} relative over all tensors (tolerance {GRAD_TOL:.0e}; worst tensor {per[1]} {per[0]:.1e})")
        net.zero_grad()

    def ddp(self, args: list, procs: int = 1) -> None:
        if procs == 1:
            train_ddp.main([str(a) for a in args])
            return
        env = dict(os.environ, OMP_NUM_THREADS="1")
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={procs}", ROOT / "python" / "train_ddp.py"]
        try:
            run(cmd + args, f"torchrun --nproc-per-node {procs}", env)
        except RuntimeError as e:
            # gloo's teardown sometimes aborts a rank after the run has finished
            # ("terminate called without an active exception"); run the whole command once
            # more from scratch. Any other failure, or a second one, fails the check, and the
            # rerun's output is checked like any other.
            if TEARDOWN_ABORT not in str(e):
                raise
            print(f"note: a rank aborted in gloo's teardown; running it again\n{str(e)[-400:]}")
            run(cmd + args, f"torchrun --nproc-per-node {procs} (second run)", env)

    def family(self, preset: str, extra: list[str]) -> None:
        w = self.work / preset
        common = ["--config", preset, *SCENES, "--seed", SEED, *extra]
        run([self.bin, "train", *common, "--steps", "0", "--batch", BATCH, "--val-scenes", "0", "--val-batches", "0", "--no-progress", "--out", w / "init"], "train --steps 0")
        init = w / "init" / "model.safetensors"
        shards = w / "shards"
        run([self.bin, "samples", *common, "--count", BATCH * (STEPS + 2), "--shard-size", BATCH, "--out", shards], "samples")
        views = sorted({train_ddp.metadata_of(p)["views"] for p in shards.glob("shard-*")})
        print(f"== {preset}: shards of {BATCH} samples, views {', '.join(views)}", flush=True)
        # (a) the update: optim_ref.py on candle's own gradients gives candle's weights.
        x0 = load_file(str(shards / "shard-00000.safetensors"))
        for opt in ("adam", "adagrad"):
            ex = w / f"example-{opt}"
            run([self.example, init, opt, UPDATE_LR, ex, *[shards / f"shard-{s:05}.safetensors" for s in range(STEPS)]], "example candle_step")
            net = ref.load(str(init))
            ro = RefOptimizer(opt, UPDATE_LR, list(net.named_parameters()))
            for s in range(STEPS):
                g = load_file(str(ex / f"grads-{s}.safetensors"))
                if s == 0 and opt == "adam":
                    self.same_gradients(preset, net, x0, g)
                for k, p in net.named_parameters():
                    p.grad = g[k].clone()
                ro.step()
            mine = ex / "torch.safetensors"
            save_file({k: v.detach().contiguous() for k, v in net.state_dict().items()}, str(mine))
            self.same_weights(f"{preset} {opt}: optim_ref.py on candle's gradients, {STEPS} steps at lr {UPDATE_LR:g}", mine, ex / "model.safetensors", UPDATE_TOL, floor=1e-12)
        # (a) end to end: `deepstereo train` (online sampler) against train_ddp.py on the shards.
        for opt in ("adam", "adagrad"):
            hyper = ["--optimizer", opt, "--lr", LR, "--steps", 1]
            run([self.bin, "train", *common, *hyper, "--batch", BATCH, "--val-scenes", "0", "--val-batches", "0", "--no-progress", "--out", w / f"candle-{opt}"], "train")
            self.ddp(["--shards", shards, "--init", init, *hyper, "--batch", BATCH, "--out", w / f"torch-{opt}"])
            # Elements whose gradient is rounding noise (|g| < ILL_CONDITIONED: the blend
            # logits' shared bias, whose true gradient is 0 since the softmax ignores a
            # shift) take a normalised step of either sign in either optimizer.
            g0 = load_file(str(w / f"example-{opt}" / "grads-0.safetensors"))
            skip = {k: g.abs() < ILL_CONDITIONED for k, g in g0.items()}
            self.same_weights(f"{preset} {opt}: one step of `deepstereo train` and of train_ddp.py", w / f"torch-{opt}" / "model.safetensors", w / f"candle-{opt}" / "model.safetensors", skip=skip)
        # (b) two processes against one, the same global batch.
        hyper = ["--shards", shards, "--init", init, "--optimizer", "adam", "--lr", LR, "--batch", BATCH // 2]
        steps = STEPS + 1
        self.ddp(["--shards", shards, "--init", init, "--optimizer", "adam", "--lr", LR, "--batch", BATCH, "--steps", steps, "--out", w / "one"])
        self.ddp([*hyper, "--steps", steps, "--out", w / "two"], procs=2)
        self.same_weights(f"{preset}: 2 processes x {BATCH // 2} and 1 x {BATCH}, {steps} steps", w / "two" / "model.safetensors", w / "one" / "model.safetensors")
        # (c) resumed against uninterrupted, both in two processes.
        self.ddp([*hyper, "--steps", 1, "--checkpoint-every", 1, "--log-every", 1, "--out", w / "resumed"], procs=2)
        self.ddp([*hyper, "--steps", steps, "--log-every", 1, "--resume", "--out", w / "resumed"], procs=2)
        self.same_weights(f"{preset}: resumed at step 1 and uninterrupted DDP runs", w / "resumed" / "model.safetensors", w / "two" / "model.safetensors", tol=1e-7)
        log = [json.loads(l) for l in (w / "resumed" / "log.jsonl").read_text().splitlines()]
        keys = ["step", "loss", "lr", "samples_per_s", "grad_norm", "val_psnr", "skipped", "seconds"]
        self.expect(
            [l["step"] for l in log] == list(range(1, steps + 1)) and all(list(l) == keys for l in log) and log[-1]["val_psnr"] is not None,
            f"{preset}: resumed log has steps 1..{steps} with the trainer's keys and a final validation PSNR",
        )
        # (d) the Rust binary runs the DDP output (the features family's shards hold its
        # inputs without the warped maps, which `forward` does not compute: parity.py
        # checks that family's forward).
        model = w / "two" / "model.safetensors"
        inputs = sorted(shards.glob("shard-*"))[-1]
        if ref.read_config(str(model)).pool is not None and ref.read_config(str(model)).pool.source_features:
            run([self.bin, "export", "--model", model, "--out", w / "model.onnx"], "export")
            self.expect((w / "model.onnx").stat().st_size > 0 and (w / "model.features.onnx").is_file(), f"{preset}: `deepstereo export --model` takes the DDP model")
            self.ddp(["--shards", shards, "--config", preset, "--steps", 0, "--batch", BATCH, "--out", w / "preset"])
            ours = ref.read_config(str(w / "preset" / "model.safetensors"))
            self.expect(ours == ref.read_config(str(init)), f"{preset}: `train_ddp.py --config {preset}` writes the config of `deepstereo train --config {preset}`")
            return
        run([self.bin, "forward", "--model", model, "--inputs", inputs, "--out", w / "forward.safetensors"], "forward")
        rust = load_file(str(w / "forward.safetensors"))["image"]
        x = load_file(str(inputs))
        net = ref.load(str(model))
        with torch.no_grad():
            image = net([x[f"level{l}"] for l in range(net.cfg.levels)])[0]
        d = float((image - rust).abs().max())
        self.expect(d <= IMAGE_TOL, f"{preset}: `deepstereo forward` on the DDP model against PyTorch: max difference {d:.2e} (tolerance {IMAGE_TOL:.0e})")
        run([self.bin, "export", "--model", model, "--out", w / "model.onnx"], "export")
        self.expect((w / "model.onnx").stat().st_size > 0, f"{preset}: `deepstereo export --model` takes the DDP model")
        # (g) the preset by name: the config the Rust trainer writes for it.
        self.ddp(["--shards", shards, "--config", preset, "--steps", 0, "--batch", BATCH, "--out", w / "preset"])
        ours = ref.read_config(str(w / "preset" / "model.safetensors"))
        self.expect(ours == ref.read_config(str(init)), f"{preset}: `train_ddp.py --config {preset}` writes the config of `deepstereo train --config {preset}`")
        if preset == "tiny":
            self.schedule(w, common, init, shards)
            self.l2(w, common, init, shards)
            self.bad_input(w, init, shards)

    def bad_input(self, w: Path, init: Path, shards: Path) -> None:
        """(h) bad input: one `error:` line, exit status 2 (arguments) or 1 (files), no traceback."""
        corrupt = w / "corrupt.safetensors"
        corrupt.write_bytes(b"not a safetensors file")
        out = ["--out", w / "bad"]
        cases = [
            ("an unknown preset", 2, ["--shards", shards, "--config", "nosuchpreset", *out]),
            ("a missing shards directory", 2, ["--shards", w / "nosuchdir", *out]),
            ("a missing --init", 2, ["--shards", shards, "--init", w / "nosuchfile.safetensors", *out]),
            ("a bad number", 2, ["--shards", shards, "--steps", "many", *out]),
            ("--resume without a checkpoint", 2, ["--shards", shards, "--resume", *out]),
            ("a corrupt --init", 1, ["--shards", shards, "--init", corrupt, *out]),
        ]
        for what, want, args in cases:
            p = subprocess.run([sys.executable, ROOT / "python" / "train_ddp.py", *map(str, args)], capture_output=True, text=True)
            last = p.stderr.strip().splitlines()[-1] if p.stderr.strip() else ""
            ok = p.returncode == want and "Traceback" not in p.stderr and "error:" in last
            self.expect(ok, f"train_ddp.py with {what}: exit status {p.returncode} (want {want}), {last!r}")

    def l2(self, w: Path, common: list, init: Path, shards: Path) -> None:
        """(f) `--loss l2`: both trainers log the same loss and reach the same weights."""
        hyper = ["--optimizer", "adam", "--lr", LR, "--steps", 1, "--loss", "l2", "--log-every", 1]
        run([self.bin, "train", *common, *hyper, "--batch", BATCH, "--val-scenes", "0", "--val-batches", "0", "--no-progress", "--out", w / "candle-l2"], "train --loss l2")
        self.ddp(["--shards", shards, "--init", init, *hyper, "--batch", BATCH, "--out", w / "torch-l2"])
        self.same_weights("tiny adam --loss l2: one step of `deepstereo train` and of train_ddp.py", w / "torch-l2" / "model.safetensors", w / "candle-l2" / "model.safetensors")
        losses = {d: [json.loads(l)["loss"] for l in (w / d / "log.jsonl").read_text().splitlines()] for d in ("candle-l2", "torch-l2", "candle-adam")}
        c, t, l1 = losses["candle-l2"], losses["torch-l2"], losses["candle-adam"][0]
        ok = len(c) == 1 == len(t) and all(abs(a - b) <= 1e-5 * abs(b) for a, b in zip(c, t)) and abs(c[0] - l1) > 1e-3 * l1
        self.expect(ok, f"tiny --loss l2: the loss of step 1, candle {c}, train_ddp.py {t} (the L1 run's first: {l1})")

    def schedule(self, w: Path, common: list, init: Path, shards: Path) -> None:
        """(e) the rate per step of a cosine schedule, candle's log against train_ddp.py's."""
        steps, spec, final = 3, "cosine:1-3", 0.25
        hyper = ["--optimizer", "adam", "--lr", LR, "--steps", steps, "--lr-schedule", spec, "--lr-final", final, "--log-every", 1]
        run([self.bin, "train", *common, *hyper, "--batch", BATCH, "--val-scenes", "0", "--val-batches", "0", "--no-progress", "--out", w / "candle-cosine"], "train --lr-schedule")
        self.ddp(["--shards", shards, "--init", init, *hyper, "--batch", BATCH, "--out", w / "torch-cosine"])
        rates = [[json.loads(l)["lr"] for l in (w / d / "log.jsonl").read_text().splitlines()] for d in ("candle-cosine", "torch-cosine")]
        # After 0 and 1 steps the full rate, after 2 (halfway from 1 to 3) f + (1 - f) / 2.
        want = [LR, LR, LR * (final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * 0.5)))]
        ok = len(rates[0]) == steps and all(abs(a - b) <= 1e-12 * LR and abs(a - c) <= 1e-12 * LR for a, b, c in zip(rates[0], rates[1], want))
        self.expect(ok, f"tiny: {spec} --lr-final {final}: rates per step, candle {rates[0]}, train_ddp.py {rates[1]}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", type=Path, default=ROOT / "target" / "release" / "deepstereo")
    ap.add_argument("--keep", type=Path, help="work in this directory and keep it")
    ap.add_argument("--family", choices=list(FAMILIES), action="append", help="check only this preset (repeatable; default: all)")
    a = ap.parse_args()
    if not a.bin.is_file():
        print(f"error: {a.bin} not found: build it with `cargo build --release -p deepstereo-train`", file=sys.stderr)
        return 1
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        work = a.keep or Path(tmp)
        c = Check(a.bin.resolve(), work)
        for preset, extra in FAMILIES.items():
            if a.family is None or preset in a.family:
                c.family(preset, extra)
    print(f"ddp checks: {len(c.failures)} failures in {time.time() - t0:.0f} s", flush=True)
    return 1 if c.failures else 0


if __name__ == "__main__":
    sys.exit(main())
