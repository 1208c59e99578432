"""Adagrad and Adam exactly as `deepstereo-train/src/training/optim.rs` implements them, in torch.

`torch.optim.Adam` computes the same update in a different order (it divides by
`sqrt(bias_correction2)` after the square root and folds `1 / bias_correction1` into the
step size), which rounds differently in float32; this mirrors candle's operations one by
one, each a float32 tensor op with the constant rounded to float32 as candle's `affine`
does:

    Adagrad:  acc = acc + g*g;  w = w - (g / (sqrt(acc) + eps)) * lr
    Adam:     m = m*b1 + g*(1-b1);  s = s*b2 + (g*g)*(1-b2)
              mhat = m * (1/(1-b1^t));  shat = s * (1/(1-b2^t))
              w = w - (mhat / (sqrt(shat) + eps)) * lr

State tensors are named as in candle checkpoints: `optim.first.<param>` (Adagrad's
accumulator, Adam's first moment) and `optim.second.<param>` (Adam's second moment).
"""

from __future__ import annotations

import math

import torch

# optim.rs constants.
ADAGRAD_EPS = 1e-10
ADAM_EPS = 1e-8
ADAM_BETAS = (0.9, 0.999)
KINDS = ("adagrad", "adam")


class RefOptimizer:
    """An optimizer over a fixed, ordered list of named parameters (sorted by name, as
    candle's `named_vars`)."""

    def __init__(self, kind: str, lr: float, named_params: list[tuple[str, torch.nn.Parameter]]):
        if kind not in KINDS:
            raise ValueError(f"unknown optimizer '{kind}' (expected one of {', '.join(KINDS)})")
        if not (lr > 0 and lr < float("inf")):
            raise ValueError(f"the learning rate must be finite and positive, got {lr}")
        self.kind = kind
        self.lr = lr
        self.steps = 0
        self.params = sorted(named_params, key=lambda p: p[0])
        self.first = [torch.zeros_like(p) for _, p in self.params]
        self.second = [torch.zeros_like(p) for _, p in self.params] if kind == "adam" else []

    def zero_grad(self) -> None:
        for _, p in self.params:
            p.grad = None

    def grad_norm(self) -> float:
        """The L2 norm of all gradients (NaN or infinite when any is)."""
        sq = 0.0
        for _, p in self.params:
            if p.grad is not None:
                sq += float(p.grad.double().square().sum())
        return sq**0.5

    @torch.no_grad()
    def step(self) -> None:
        self.steps += 1
        t = self.steps
        for i, (_, p) in enumerate(self.params):
            g = p.grad
            if g is None:
                continue
            if self.kind == "adagrad":
                acc = self.first[i] + g * g
                upd = g / (acc.sqrt() + ADAGRAD_EPS)
                p.copy_(p - upd * self.lr)
                self.first[i] = acc
            else:
                b1, b2 = ADAM_BETAS
                m = self.first[i] * b1 + g * (1.0 - b1)
                s = self.second[i] * b2 + (g * g) * (1.0 - b2)
                mhat = m * (1.0 / (1.0 - b1**t))
                shat = s * (1.0 / (1.0 - b2**t))
                upd = mhat / (shat.sqrt() + ADAM_EPS)
                p.copy_(p - upd * self.lr)
                self.first[i] = m
                self.second[i] = s

    def state(self) -> dict[str, torch.Tensor]:
        out = {}
        for i, (name, _) in enumerate(self.params):
            out[f"optim.first.{name}"] = self.first[i]
            if self.second:
                out[f"optim.second.{name}"] = self.second[i]
        return out

    def restore(self, steps: int, tensors: dict[str, torch.Tensor]) -> None:
        for i, (name, p) in enumerate(self.params):
            for key, store in (("first", self.first), ("second", self.second)):
                if key == "second" and not self.second:
                    continue
                k = f"optim.{key}.{name}"
                if k not in tensors:
                    raise ValueError(f"the checkpoint has no '{k}' (was it made with another optimizer?)")
                v = tensors[k]
                if tuple(v.shape) != tuple(p.shape):
                    raise ValueError(f"'{k}' has shape {tuple(v.shape)}, expected {tuple(p.shape)}")
                store[i] = v.to(device=p.device, dtype=p.dtype).clone()
        self.steps = steps


# lr.rs: the learning rate against the step.
DEFAULT_LR_FINAL = 0.05


class LrSchedule:
    """`constant`, or `cosine:START-END`: the rate `lr` up to step START, then
    `lr * (f + (1 - f) * (1 + cos(pi * x)) / 2)` with `x = (done - START) / (END - START)`,
    then `lr * f` from END on (`f` = `final`), as `deepstereo train --lr-schedule`."""

    def __init__(self, spec: str, final: float = DEFAULT_LR_FINAL):
        if not (math.isfinite(final) and 0.0 < final <= 1.0):
            raise ValueError(f"--lr-final must be in (0, 1], got {final}")
        self.final = final
        self.span: tuple[int, int] | None = None
        if spec == "constant":
            return
        if not spec.startswith("cosine:") or "-" not in spec[7:]:
            raise ValueError(f"--lr-schedule '{spec}': expected 'constant' or 'cosine:START-END'")
        a, b = spec[7:].split("-", 1)
        try:
            start, end = int(a.strip()), int(b.strip())
        except ValueError:
            raise ValueError(f"--lr-schedule '{spec}': START and END must be step counts") from None
        if start < 0 or end <= start:
            raise ValueError(f"--lr-schedule '{spec}': END must be after START")
        self.span = (start, end)

    def lr_at(self, lr: float, done: int) -> float:
        """The rate of the update that follows `done` completed steps."""
        if self.span is None:
            return lr
        start, end = self.span
        if done <= start:
            return lr
        if done >= end:
            return lr * self.final
        x = (done - start) / (end - start)
        return lr * (self.final + (1.0 - self.final) * 0.5 * (1.0 + math.cos(math.pi * x)))
