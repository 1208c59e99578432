"""Parity of the four runtimes of the DeepStereo network on the same inputs.

    python python/parity.py --bin target/release/deepstereo

For every model (the embedded one, a Rust-initialised `tiny` when the `init_weights`
example is built, and a Python-initialised variant config with three levels and no colour
skip), this script:

1. exports ONNX with `deepstereo export`, and checks it with
   `onnx.checker.check_model(full_check=True)` and `onnx.shape_inference.infer_shapes(
   strict_mode=True)` (names of inputs, outputs and initializers included);
2. loads the weights strictly into the PyTorch reference (`deepstereo_ref.py`);
3. runs, on the same inputs, candle (`deepstereo forward`), PyTorch (CPU), onnxruntime
   (Python) on the exported file and ort (`deepstereo forward --backend ort --onnx`), and
   compares every runtime with candle (the specification) and ort with onnxruntime.

Inputs: random volumes; extreme ones (all alpha zero, all zero, saturated, constant
colours, one plane, 128 planes, values around 1e4 and 1e-6); real plane-sweep volumes from
`deepstereo sweep --model` on a procedural scene (from `deepstereo synth` or `deepstereo
demo`) and on the scenes of ../shared/data when present. Also the issue-6 check: the
inputs `deepstereo sweep --model` writes, fed to onnxruntime, give candle's image.

Fails (exit 1) when a difference exceeds its tolerance: 1e-4 absolute for the image and the
selection, relative to the output's magnitude for inputs around 1e4.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from safetensors.numpy import load_file, save_file

import deepstereo_ref as ref

ROOT = Path(__file__).resolve().parent.parent
TOL = 1e-4
# Reordering the views or adding views that see nothing changes the output by at most this.
INVARIANCE_TOL = 1e-6
OUTPUTS = ("image", "selection")


def variant_config() -> ref.Config:
    """Exercises what `tiny` does not: three levels, towers reading different numbers of
    levels, 5x5 kernels, no colour skip, two views, and layers wide enough (32 output
    channels) for candle's Winograd convolutions (F(2x2, 5x5) and F(4x4, 3x3))."""
    C = ref.Conv
    return ref.Config(
        name="variant",
        views=2,
        planes=12,
        levels=3,
        tile=16,
        select=ref.TowerConfig(3, [C(3, 8), C(3, 8)], [C(5, 32), C(3, 8)]),
        depth_convs=[C(3, 8), C(5, 1)],
        colour=ref.TowerConfig(2, [C(3, 8)], [C(3, 32)]),
        colour_skip=False,
    )


def pooled_variant_config() -> ref.Config:
    """The any-number-of-views family with what `nviews` does not have: three encoder
    layers, no blend hidden layer, a 3x3 colour tower over two levels and a wide (32)
    select layer."""
    C = ref.Conv
    return ref.Config(
        name="pooled-variant",
        views=3,
        planes=10,
        levels=2,
        tile=8,
        select=ref.TowerConfig(2, [C(3, 8)], [C(3, 32), C(3, 8)]),
        depth_convs=[C(3, 4), C(3, 1)],
        colour=ref.TowerConfig(2, [C(3, 6)], [C(3, 6)]),
        colour_skip=False,
        pool=ref.ViewPool(encoder=[C(1, 6), C(1, 6), C(1, 5)], blend=[]),
    )


# --- running things --------------------------------------------------------------------


def run(cmd: list[str], what: str, check: bool = True) -> subprocess.CompletedProcess:
    p = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if check and p.returncode != 0:
        raise RuntimeError(f"{what} failed ({p.returncode}): {' '.join(map(str, cmd))}\n{p.stderr}")
    return p


@dataclass
class Model:
    name: str
    weights: Path
    onnx: Path
    cfg: ref.Config
    torch_model: ref.DeepStereo
    session: ort.InferenceSession
    notes: list[str] = field(default_factory=list)


@dataclass
class Row:
    case: str
    pair: str
    diffs: dict[str, tuple[float, float]]  # output -> (max, mean)
    tols: dict[str, float]

    @property
    def ok(self) -> bool:
        return all(self.diffs[o][0] <= self.tols[o] for o in OUTPUTS)


class Parity:
    def __init__(self, binary: Path, work: Path):
        self.bin = binary
        self.work = work
        self.rows: list[Row] = []
        self.failures: list[str] = []
        self.notes: list[str] = []
        self.count = 0

    def fail(self, msg: str) -> None:
        print(f"FAIL: {msg}", flush=True)
        self.failures.append(msg)

    def note(self, msg: str) -> None:
        print(f"note: {msg}", flush=True)
        self.notes.append(msg)

    # -- models --

    def export_and_check(self, name: str, weights: Path, opset: int = 17) -> Path:
        out = self.work / f"{name}.opset{opset}.onnx"
        run([self.bin, "export", "--model", weights, "--out", out, "--opset", opset], f"export {name}")
        m = onnx.load(str(out))
        onnx.checker.check_model(m, full_check=True)
        onnx.shape_inference.infer_shapes(m, check_type=True, strict_mode=True, data_prop=True)
        cfg = ref.read_config(str(weights))
        want_inputs = [f"level{l}" for l in range(cfg.levels)]
        got_inputs = [i.name for i in m.graph.input]
        if got_inputs != want_inputs:
            self.fail(f"{name}: graph inputs {got_inputs}, expected {want_inputs}")
        got_outputs = [o.name for o in m.graph.output]
        if got_outputs != list(OUTPUTS):
            self.fail(f"{name}: graph outputs {got_outputs}, expected {list(OUTPUTS)}")
        init = sorted(t.name for t in m.graph.initializer)
        all_names = load_file(str(weights)).keys()
        names = sorted(k for k in all_names if not k.startswith("features."))
        if init != names:
            self.fail(f"{name}: initializers {init} differ from the safetensors names {names}")
        self.check_features_graph(name, out, sorted(k for k in all_names if k.startswith("features.")))
        ops = sorted({n.op_type for n in m.graph.node})
        domains = {n.domain for n in m.graph.node} - {""}
        if domains:
            self.fail(f"{name}: non-standard domains {domains}")
        print(f"  {out.name}: checker (full) and strict shape inference pass; ops {', '.join(ops)}", flush=True)
        return out

    def check_features_graph(self, name: str, onnx_path: Path, names: list[str]) -> None:
        """The features family's second graph (`NAME.features.onnx`): there exactly when the
        model has `features.*` weights, valid, holding them."""
        path = features_onnx(onnx_path)
        if not names:
            if path.exists():
                self.fail(f"{name}: {path.name} written for a model without source features")
            return
        if not path.is_file():
            self.fail(f"{name}: no {path.name} beside {onnx_path.name}")
            return
        m = onnx.load(str(path))
        onnx.checker.check_model(m, full_check=True)
        onnx.shape_inference.infer_shapes(m, check_type=True, strict_mode=True, data_prop=True)
        if [i.name for i in m.graph.input] != ["image"] or [o.name for o in m.graph.output] != ["features"]:
            self.fail(f"{name}: {path.name} must map 'image' to 'features'")
        init = sorted(t.name for t in m.graph.initializer)
        if init != names:
            self.fail(f"{name}: {path.name} initializers {init}, expected {names}")
        print(f"  {path.name}: checker (full) and strict shape inference pass", flush=True)

    def load_model(self, name: str, weights: Path) -> Model:
        print(f"== model {name}: {weights}", flush=True)
        cfg = ref.read_config(str(weights))
        onnx_path = self.export_and_check(name, weights)
        tm = ref.load(str(weights))
        sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
        print(f"  config '{cfg.name}': {cfg.views} views, {cfg.levels} levels, {ref.parameter_count(tm)} parameters", flush=True)
        return Model(name, weights, onnx_path, cfg, tm, sess)

    # -- one comparison --

    def compare(self, model: Model, case: str, inputs: dict[str, np.ndarray], relative: bool = False) -> dict[str, dict[str, np.ndarray]]:
        """Runs the four runtimes on `inputs` (level0..) and records the differences."""
        self.count += 1
        path = self.work / f"in{self.count}.safetensors"
        save_file({k: np.ascontiguousarray(v, dtype=np.float32) for k, v in inputs.items()}, str(path))
        feeds = [inputs[f"level{l}"] for l in range(model.cfg.levels)]
        res: dict[str, dict[str, np.ndarray]] = {}
        out = self.work / f"candle{self.count}.safetensors"
        run([self.bin, "forward", "--model", model.weights, "--inputs", path, "--out", out], f"{case}: candle forward")
        res["candle"] = load_file(str(out))
        out = self.work / f"ort{self.count}.safetensors"
        run(
            [self.bin, "forward", "--backend", "ort", "--onnx", model.onnx, "--model", model.weights, "--inputs", path, "--out", out],
            f"{case}: ort forward",
        )
        res["ort"] = load_file(str(out))
        with torch.no_grad():
            img, sel = model.torch_model([torch.from_numpy(np.ascontiguousarray(x)) for x in feeds])
        res["torch"] = {"image": img.numpy(), "selection": sel.numpy()}
        img, sel = model.session.run(list(OUTPUTS), {f"level{l}": x for l, x in enumerate(feeds)})
        res["onnxruntime"] = {"image": img, "selection": sel}
        path.unlink()
        for pair in (("torch", "candle"), ("onnxruntime", "candle"), ("ort", "candle"), ("ort", "onnxruntime")):
            self.record(f"{model.name}/{case}", pair, res[pair[0]], res[pair[1]], relative)
        return res

    def record(self, case: str, pair: tuple[str, str], a: dict, b: dict, relative: bool, tol: float = TOL) -> None:
        diffs, tols = {}, {}
        for o in OUTPUTS:
            x, y = np.asarray(a[o], np.float64), np.asarray(b[o], np.float64)
            if x.shape != y.shape:
                self.fail(f"{case}: {pair[0]} {o} has shape {x.shape}, {pair[1]} {y.shape}")
                diffs[o], tols[o] = (float("inf"), float("inf")), TOL
                continue
            if not (np.isfinite(x).all() and np.isfinite(y).all()):
                self.fail(f"{case}: non-finite {o} from {pair[0]} or {pair[1]}")
            d = np.abs(x - y)
            diffs[o] = (float(d.max()) if d.size else 0.0, float(d.mean()) if d.size else 0.0)
            tols[o] = tol * max(1.0, float(np.abs(y).max())) if relative else tol
        row = Row(case, f"{pair[0]} vs {pair[1]}", diffs, tols)
        self.rows.append(row)
        if not row.ok:
            self.fail(f"{case}: {row.pair}: " + ", ".join(f"{o} max {diffs[o][0]:.3g} > {tols[o]:.3g}" for o in OUTPUTS if diffs[o][0] > tols[o]))

    # -- report --

    def table(self) -> str:
        head = f"| {'case':<36} | {'pair':<26} | {'image max':>9} | {'image mean':>10} | {'sel. max':>9} | {'sel. mean':>9} | ok |"
        lines = [head, "|" + "|".join("-" * (len(c)) for c in head.split("|")[1:-1]) + "|"]
        for r in self.rows:
            (im, imn), (sm, smn) = r.diffs["image"], r.diffs["selection"]
            lines.append(
                f"| {r.case:<36} | {r.pair:<26} | {im:9.2e} | {imn:10.2e} | {sm:9.2e} | {smn:9.2e} | {'ok' if r.ok else 'NO'} |"
            )
        return "\n".join(lines)


def features_onnx(onnx_path: Path) -> Path:
    """Where `deepstereo export` writes the feature graph of `NAME.onnx`."""
    return onnx_path.with_name(onnx_path.stem + ".features.onnx")


def features_check(p: Parity, model: Model, rng: np.random.Generator) -> None:
    """The per-source feature CNN in the four runtimes: `deepstereo forward` with a
    `source_image` (candle, and ort on the exported feature graph), PyTorch on the image
    zero-padded by R, onnxruntime on the feature graph. Images of odd sizes, one with
    values far outside [0, 1]."""
    pool = model.cfg.pool
    assert pool is not None and pool.source_features
    r = pool.feature_radius()
    sess = ort.InferenceSession(str(features_onnx(model.onnx)), providers=["CPUExecutionProvider"])
    for case, (h, w), scale in (("features-23x31", (23, 31), 1.0), ("features-1x2", (1, 2), 1.0), ("features-large", (9, 7), 1e3)):
        img = (rng.random((3, h, w)) * scale).astype(np.float32)
        inputs = make_inputs(model.cfg, 1, 2, 2 * model.cfg.tile_align(), 2 * model.cfg.tile_align(), lambda s, r: r.random(s), rng)
        inputs["source_image"] = img
        p.count += 1
        path = p.work / f"in{p.count}.safetensors"
        save_file({k: np.ascontiguousarray(v, dtype=np.float32) for k, v in inputs.items()}, str(path))
        res = {}
        for backend, extra in (("candle", []), ("ort", ["--backend", "ort", "--onnx", model.onnx])):
            out = p.work / f"{backend}{p.count}.safetensors"
            run([p.bin, "forward", "--model", model.weights, "--inputs", path, "--out", out, *extra], f"{case}: {backend} forward")
            res[backend] = load_file(str(out))["source_features"]
        padded = np.pad(img, ((0, 0), (r, r), (r, r)))[None]
        with torch.no_grad():
            res["torch"] = model.torch_model.features_forward(torch.from_numpy(padded)).numpy()[0]
        res["onnxruntime"] = sess.run(["features"], {"image": padded})[0][0]
        tol = TOL * max(1.0, float(np.abs(res["candle"]).max()))
        for a, b in (("torch", "candle"), ("onnxruntime", "candle"), ("ort", "candle")):
            d = float(np.abs(np.asarray(res[a], np.float64) - res[b]).max())
            status = "ok" if d <= tol and res[a].shape == res[b].shape else "NO"
            print(f"  {model.name}/{case}: {a} vs {b}: max |diff| {d:.2e} (tolerance {tol:.1e}) {status}", flush=True)
            if status != "ok":
                p.fail(f"{model.name}/{case}: source features {a} vs {b} differ by {d:.3g} (shapes {res[a].shape}, {res[b].shape})")


# --- inputs ----------------------------------------------------------------------------


def level_shapes(cfg: ref.Config, b: int, d: int, th: int, tw: int, v: int | None = None) -> list[tuple[int, ...]]:
    """`[B, D, 4V, H, W]`, or `[B, D, V, C_v, H, W]` for the any-number-of-views family
    (`C_v` 4, or 9 with the per-view cue)."""
    v = cfg.views if v is None else v
    sizes = [(cfg.input_size(l, th), cfg.input_size(l, tw)) for l in range(cfg.levels)]
    if cfg.pool is not None:
        return [(b, d, v, cfg.pool.view_channels(), h, w) for h, w in sizes]
    return [(b, d, 4 * v, h, w) for h, w in sizes]


def make_inputs(cfg: ref.Config, b: int, d: int, th: int, tw: int, fill, rng: np.random.Generator, v: int | None = None) -> dict[str, np.ndarray]:
    out = {}
    for l, shape in enumerate(level_shapes(cfg, b, d, th, tw, v)):
        x = fill(shape, rng).astype(np.float32)
        out[f"level{l}"] = x
    return out


def rgb_alpha(shape, rng, rgb, alpha):
    """Volume with colour `rgb(shape)` premultiplied by `alpha(shape)` per source view
    (and, with the per-view cue, cue channels in the range the geometry gives, [-7, 5])."""
    if len(shape) == 6:
        b, d, v, cv, h, w = shape
    else:
        b, d, c, h, w = shape
        v, cv = c // 4, 4
    x = np.empty((b, d, v, cv, h, w), np.float64)
    a = alpha((b, d, v, 1, h, w))
    x[:, :, :, :3] = rgb((b, d, v, 3, h, w)) * a
    x[:, :, :, 3:4] = a
    x[:, :, :, 4:] = rng.random((b, d, v, cv - 4, h, w)) * 12.0 - 7.0
    return x.reshape(shape)


def cases(cfg: ref.Config):
    """(name, B, D, th, tw, fill, relative tolerance)."""
    a = cfg.tile_align()
    t = cfg.tile
    u = lambda s, r: r.random(s)  # noqa: E731
    psv = lambda s, r: rgb_alpha(s, r, r.random, lambda s2: np.clip(r.random(s2) * 1.6 - 0.3, 0, 1))  # noqa: E731
    return [
        ("random uniform", 2, cfg.planes, t, t, u, False),
        ("random sweep-like", 1, 9, a, 3 * a, psv, False),
        ("all alpha zero", 1, 6, t, t, lambda s, r: rgb_alpha(s, r, r.random, np.zeros), False),
        ("all zero", 1, 4, a * 2, a * 2, lambda s, r: np.zeros(s), False),
        ("saturated (all one)", 1, 5, t, t, lambda s, r: np.ones(s), False),
        ("constant colours", 1, 5, t, t, lambda s, r: rgb_alpha(s, r, lambda s2: np.broadcast_to(r.random((1, 1, s2[2], 3, 1, 1)), s2), np.ones), False),
        ("one plane", 1, 1, t, t, psv, False),
        ("128 planes", 1, 128, 2 * a, 2 * a, psv, False),
        ("large values (1e4)", 1, 6, t, t, lambda s, r: 1e4 * r.random(s), True),
        ("small values (1e-6)", 1, 6, t, t, lambda s, r: 1e-6 * r.random(s), False),
    ]


def pooled_cases(p: "Parity", model: "Model", rng: np.random.Generator) -> None:
    """The any-number-of-views family at V = 1, 2, 5 and 10, with the views shuffled, and
    with empty views added: every runtime against candle, and candle against itself."""
    cfg = model.cfg
    t = cfg.tile
    psv = lambda s, r: rgb_alpha(s, r, r.random, lambda s2: np.clip(r.random(s2) * 1.6 - 0.3, 0, 1))  # noqa: E731
    for v in (1, 2, 5, 10):
        x = make_inputs(cfg, 2, cfg.planes, t, t, psv, rng, v)
        base = p.compare(model, f"V={v}", x)
        print(f"  V={v}: done", flush=True)
        if v < 2:
            continue
        order = rng.permutation(v)
        shuffled = {k: np.ascontiguousarray(a[:, :, order]) for k, a in x.items()}
        res = p.compare(model, f"V={v} shuffled", shuffled)
        p.record(f"{model.name}/V={v} shuffled", ("candle", "candle unshuffled"), res["candle"], base["candle"], False, INVARIANCE_TOL)
        empty = {k: np.concatenate([a, np.zeros_like(a[:, :, :2])], 2) for k, a in x.items()}
        res = p.compare(model, f"V={v} + 2 empty", empty)
        p.record(f"{model.name}/V={v} + 2 empty", ("candle", "candle without"), res["candle"], base["candle"], False, INVARIANCE_TOL)
        print(f"  V={v}: shuffled and with empty views: done", flush=True)


# --- real sweeps -----------------------------------------------------------------------


def procedural_scene(p: Parity) -> Path | None:
    help_text = run([p.bin, "--help"], "help").stdout
    commands = {line.split()[0] for line in help_text.splitlines() if line.startswith("  ") and line.split()}
    if "synth" in commands:
        out = p.work / "synth"
        r = run([p.bin, "synth", "--out", out, "--scenes", "1", "--size", "96x72"], "synth", check=False)
        if r.returncode == 0:
            scenes = sorted(q for q in out.rglob("transforms.json")) or sorted(out.rglob("*"))
            for s in scenes:
                d = s.parent if s.is_file() else s
                if run([p.bin, "inspect", "--scene", d], "inspect", check=False).returncode == 0:
                    return d
        p.note(f"`deepstereo synth` did not give a scene ({r.stderr.strip()[-200:]}); trying `demo`")
    if "demo" in commands:
        out = p.work / "demo"
        r = run([p.bin, "demo", "--out", out, "--size", "96x72"], "demo", check=False)
        if r.returncode == 0 and (out / "scene").is_dir():
            return out / "scene"
        p.note(f"`deepstereo demo` did not give a scene: {r.stderr.strip()[-300:]}")
        return None
    p.note("the binary has neither `synth` nor `demo`: the procedural-scene case is skipped")
    return None


def check_disagreement(p: Parity, model: Model, name: str, st: dict[str, np.ndarray]) -> None:
    """The disagreement channel `sweep --model` writes (the cue's last), recomputed here from
    the sweep's own RGBA (sources nearest first, as `sweep` lists them): per plane point and view,
    sqrt(min |rgb_v - rgb_n|^2) over the other views n among the `near` nearest with alpha
    >= 0.5 (`view_weights.rs`). Needs a config without falloff or gate (the RGBA is then
    the sweep's own)."""
    pool = model.cfg.pool
    assert pool is not None and pool.disagree is not None
    if pool.falloff is not None or pool.agree is not None:
        p.note(f"sweep {name}: disagreement channel not recomputed (the config has a falloff or a gate)")
        return
    v = st["level0"].shape[2]
    near = np.arange(v) < pool.disagree["near"]  # `sweep` lists the sources nearest first
    worst = 0.0
    for l in range(model.cfg.levels):
        x = st[f"level{l}"][0].astype(np.float64)  # [D, V, 10, H, W]
        rgb, a = x[:, :, :3], x[:, :, 3]
        e = ((rgb[:, :, None] - rgb[:, None, :]) ** 2).sum(3)  # [D, V, V, H, W]
        ok = (near[None, None, :, None, None] & (a[:, None, :] >= 0.5)) & ~np.eye(v, dtype=bool)[None, :, :, None, None]
        e = np.where(ok, e, np.inf).min(2)
        want = np.where(np.isfinite(e), np.sqrt(np.where(np.isfinite(e), e, 0)), 0.0)
        worst = max(worst, float(np.abs(x[:, :, -1] - want).max()))
    status = "ok" if worst <= 1e-5 else "FAIL"
    print(f"  {name}: disagreement channel against numpy: max |diff| {worst:.2e} {status}", flush=True)
    if worst > 1e-5:
        p.fail(f"sweep {name}: disagreement channel differs from numpy by {worst}")


def sweep_case(p: Parity, model: Model, name: str, scene: Path, planes: int | None, extra: list[str]) -> None:
    out = p.work / f"sweep_{name}.safetensors"
    cmd = [p.bin, "sweep", "--scene", scene, "--target", "0", "--model", model.weights, "--out", out, *extra]
    if planes is not None:
        cmd += ["--planes", planes]
    r = run(cmd, f"sweep {name}", check=False)
    if r.returncode != 0:
        p.note(f"sweep of {name} failed, case skipped: {r.stderr.strip()[-300:]}")
        return
    st = load_file(str(out))
    want = {f"level{l}" for l in range(model.cfg.levels)} | {"tile_origin", "tile_size"}
    if not want <= st.keys():
        p.fail(f"sweep --model of {name} lacks {sorted(want - st.keys())}")
        return
    graph_inputs = {i.name for i in model.session.get_inputs()}
    if not graph_inputs <= st.keys():
        p.fail(f"sweep --model of {name} lacks graph inputs {sorted(graph_inputs - st.keys())}")
        return
    if model.cfg.pool is not None and model.cfg.pool.disagree is not None:
        check_disagreement(p, model, name, st)
    th, tw = (int(v) for v in st["tile_size"])
    d = st["level0"].shape[1]
    h, w = st["target"].shape[1:]
    print(f"  {name}: sweep {w}x{h}, tile {tw}x{th}, {d} planes, level0 {st['level0'].shape}", flush=True)
    # Issue 6: the graph's inputs straight from the file into onnxruntime give candle's image.
    feeds = {i.name: st[i.name] for i in model.session.get_inputs()}
    onnx_image, onnx_sel = model.session.run(list(OUTPUTS), feeds)
    res = p.compare(model, f"sweep {name}", {k: st[k] for k in feeds})
    if onnx_image.shape != (1, 3, th, tw) or onnx_sel.shape != (1, d, th, tw):
        p.fail(f"{name}: onnxruntime output shapes {onnx_image.shape}, {onnx_sel.shape} for tile {th}x{tw}")
    di = float(np.abs(onnx_image - res["candle"]["image"]).max())
    status = "ok" if di <= TOL else "FAIL"
    print(f"  issue-6 check ({name}): onnxruntime on `sweep --model` inputs vs candle forward: image max |diff| {di:.2e} {status}", flush=True)
    if di > TOL:
        p.fail(f"issue-6 check on {name}: {di}")
    # The rendered region is the image itself: sanity of the values there.
    img = res["candle"]["image"][0, :, :h, :w]
    sel = res["candle"]["selection"][0, :, :h, :w]
    if not np.allclose(sel.sum(0), 1.0, atol=1e-4):
        p.fail(f"{name}: selection does not sum to 1 over planes")
    print(f"  {name}: image range [{img.min():.3f}, {img.max():.3f}]", flush=True)


def render_difference(p: Parity, tag: str, *runs: tuple[Path, dict[str, np.ndarray]]) -> float:
    """The largest difference between the images `deepstereo forward` renders for two
    (weights, inputs) pairs."""
    images = []
    for i, (model, inputs) in enumerate(runs):
        f, out = p.work / f"{tag}_{i}.safetensors", p.work / f"{tag}_{i}_out.safetensors"
        save_file(inputs, str(f))
        run([p.bin, "forward", "--model", model, "--inputs", f, "--out", out], "forward")
        images.append(load_file(str(out))["image"])
    return float(np.abs(images[0] - images[1]).max())


def add_cue_check(p: Parity, weights: Path, rng: np.random.Generator, weigh: bool) -> None:
    """`python/add_cue.py` (with `--weigh`: the cue weighs the views) on a model without
    the cue: the new model, fed the same RGBA with any cue beside it, renders exactly what
    the old one does (its new weights start at zero), in candle (`deepstereo forward`);
    and the file's config reads the cue."""
    tag = "weigh" if weigh else "cue"
    out = p.work / f"with_{tag}" / "model.safetensors"
    out.parent.mkdir(exist_ok=True)
    run([sys.executable, ROOT / "python" / "add_cue.py", weights, out] + (["--weigh"] if weigh else []), "add_cue.py")
    cfg = ref.read_config(str(out))
    if cfg.pool is None or not (cfg.pool.weigh is not None if weigh else cfg.pool.cue):
        p.fail(f"add_cue.py: {out} does not read the cue ({tag})")
        return
    old = ref.read_config(str(weights))
    t = old.tile
    psv = lambda s, r: rgb_alpha(s, r, r.random, lambda s2: np.clip(r.random(s2) * 1.6 - 0.3, 0, 1))  # noqa: E731
    x = make_inputs(old, 1, old.planes, t, t, psv, rng, 5)
    xc = {k: np.concatenate([a, (rng.random(a.shape[:3] + (5,) + a.shape[4:]) * 12 - 7).astype(np.float32)], 3) for k, a in x.items()}
    d = render_difference(p, f"add_{tag}", (weights, x), (out, xc))
    status = "ok" if d <= 1e-6 else "FAIL"
    print(f"  add_cue.py{' --weigh' if weigh else ''}: the model with zero cue weights against the model without the cue: image max |diff| {d:.2e} {status}", flush=True)
    if d > 1e-6:
        p.fail(f"add_cue.py changed what the model renders: {d}")


def add_disagree_check(p: Parity, weights: Path, rng: np.random.Generator) -> None:
    """`python/add_cue.py --disagree 4` on a model whose cue weighs the views: fed the
    same inputs with any disagreement channel after the cue, the new model renders exactly
    what the old one does (its new column starts at zero), in candle."""
    out = p.work / "with_disagree" / "model.safetensors"
    out.parent.mkdir(exist_ok=True)
    run([sys.executable, ROOT / "python" / "add_cue.py", weights, out, "--disagree", "4"], "add_cue.py --disagree")
    cfg = ref.read_config(str(out))
    old = ref.read_config(str(weights))
    if cfg.pool is None or cfg.pool.disagree != {"near": 4} or cfg.pool.view_channels() != old.pool.view_channels() + 1:
        p.fail(f"add_cue.py --disagree: {out} does not read the disagreement channel")
        return
    t = old.tile
    x = make_inputs(old, 1, old.planes, t, t, lambda s, r: rgb_alpha(s, r, r.random, r.random), rng, 5)
    xd = {k: np.concatenate([a, (rng.random(a.shape[:3] + (1,) + a.shape[4:]) * 1.7).astype(np.float32)], 3) for k, a in x.items()}
    d = render_difference(p, "add_disagree", (weights, x), (out, xd))
    status = "ok" if d <= 1e-6 else "FAIL"
    print(f"  add_cue.py --disagree: the model with a zero disagreement column against the model without it: image max |diff| {d:.2e} {status}", flush=True)
    if d > 1e-6:
        p.fail(f"add_cue.py --disagree changed what the model renders: {d}")


# --- main ------------------------------------------------------------------------------


def reference_loader_checks(p: Parity, weights: Path) -> None:
    """The reference and the Rust loader both refuse missing and unexpected tensors."""
    from safetensors import safe_open

    with safe_open(str(weights), framework="np") as f:
        meta = f.metadata()
    st = load_file(str(weights))
    first = sorted(st)[0]
    for label, bad in (
        ("missing", {k: v for k, v in st.items() if k != first}),
        ("unexpected", {**st, "select.extra.weight": np.zeros(1, np.float32)}),
    ):
        path = p.work / f"bad_{label}.safetensors"
        save_file(bad, str(path), metadata=meta)
        try:
            ref.load(str(path))
            p.fail(f"the PyTorch reference accepted a weights file with a {label} tensor")
        except RuntimeError:
            pass
        r = run([p.bin, "export", "--model", path, "--out", p.work / "bad.onnx"], "export", check=False)
        if r.returncode == 0:
            p.fail(f"`deepstereo export` accepted a weights file with a {label} tensor")
    print("  strict loading: missing and unexpected tensors are refused by PyTorch and Rust", flush=True)


def newest_opset(p: Parity, model: Model) -> None:
    """The newest opset both the exporter and onnxruntime take, on a random case."""
    for opset in range(onnx.defs.onnx_opset_version(), 17, -1):
        r = run([p.bin, "export", "--model", model.weights, "--out", p.work / "probe.onnx", "--opset", opset], "export", check=False)
        if r.returncode != 0:
            continue
        try:
            ort.InferenceSession(str(p.work / "probe.onnx"), providers=["CPUExecutionProvider"])
        except Exception:  # noqa: BLE001 - onnxruntime raises various types for unsupported opsets
            continue
        path = p.export_and_check(model.name, model.weights, opset)
        m = Model(f"{model.name}@opset{opset}", model.weights, path, model.cfg, model.torch_model,
                  ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]))
        rng = np.random.default_rng(17)
        p.compare(m, "random uniform", make_inputs(m.cfg, 1, 7, m.cfg.tile, m.cfg.tile, lambda s, r: r.random(s), rng))
        return
    p.note("no opset above 17 loads in this onnxruntime")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", required=True, type=Path, help="the deepstereo binary")
    ap.add_argument("--weights", type=Path, action="append", default=[], help="extra weights files to check")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data", help="real scenes (skipped when absent)")
    ap.add_argument("--keep", type=Path, help="keep the intermediate files here")
    args = ap.parse_args()
    torch.set_num_threads(max(1, min(4, os.cpu_count() or 1)))
    binary = args.bin.resolve()
    if not binary.is_file():
        print(f"error: {binary} not found: build it with `cargo build --release -p deepstereo-train`", file=sys.stderr)
        return 2
    t0 = time.time()
    work = Path(tempfile.mkdtemp(prefix="deepstereo-parity-"))
    p = Parity(binary, work)
    try:
        models: list[Model] = []
        # The embedded model, and `deepstereo export` without --model exports exactly it.
        asset = ROOT / "deepstereo-train" / "assets" / "nviews-disagree-scratch.safetensors"
        if asset.is_file():
            m = p.load_model("embedded", asset)
            run([binary, "export", "--out", work / "default.onnx"], "export of the embedded model")
            if (work / "default.onnx").read_bytes() != m.onnx.read_bytes():
                p.fail(f"`deepstereo export` without --model differs from the export of {asset.relative_to(ROOT)}")
            else:
                print("  `deepstereo export` without --model writes the same file", flush=True)
            models.append(m)
        else:
            p.note(f"{asset} not found: no embedded model to check")
        # The shipped weights of the paper-family `tiny` (the embedded model before).
        tiny_asset = ROOT / "deepstereo-train" / "assets" / "tiny.safetensors"
        if tiny_asset.is_file():
            models.append(p.load_model("tiny", tiny_asset))
        # Rust-initialised tiny (the `init_weights` example, built by `cargo test --release`).
        example = binary.parent / "examples" / "init_weights"
        if example.is_file():
            w = work / "rust_tiny.safetensors"
            run([example, "tiny", w], "init_weights")
            models.append(p.load_model("rust-init", w))
        else:
            p.note(f"{example} not built (`cargo build --release -p deepstereo-export --examples`): no Rust-initialised model")
        # Python-initialised variant config (three levels, no colour skip).
        w = work / "variant.safetensors"
        ref.init_weights(variant_config(), str(w), seed=3)
        models.append(p.load_model("py-variant", w))
        # The any-number-of-views family: Rust-initialised `nviews`, Python-initialised variant.
        if example.is_file():
            w = work / "rust_nviews.safetensors"
            run([example, "nviews", w], "init_weights nviews")
            models.append(p.load_model("rust-nviews", w))
        w = work / "pooled_variant.safetensors"
        ref.init_weights(pooled_variant_config(), str(w), seed=4)
        models.append(p.load_model("py-pooled", w))
        # The per-view cue: Rust-initialised `nviews-cue`, and the Python variant with it.
        if example.is_file():
            w = work / "rust_nviews_cue.safetensors"
            run([example, "nviews-cue", w], "init_weights nviews-cue")
            models.append(p.load_model("rust-nviews-cue", w))
        cue_cfg = pooled_variant_config()
        assert cue_cfg.pool is not None
        cue_cfg.name, cue_cfg.pool.cue = "pooled-variant-cue", True
        w = work / "pooled_variant_cue.safetensors"
        ref.init_weights(cue_cfg, str(w), seed=5)
        models.append(p.load_model("py-pooled-cue", w))
        cue_model = models[-1]
        # The cue weighing the views: the Python variant with `pool.weigh` (all its weights
        # random, so the weights are not 1).
        weigh_cfg = pooled_variant_config()
        assert weigh_cfg.pool is not None
        weigh_cfg.name, weigh_cfg.pool.weigh = "pooled-variant-weigh", [ref.Conv(1, 5)]
        w = work / "pooled_variant_weigh.safetensors"
        ref.init_weights(weigh_cfg, str(w), seed=7)
        models.append(p.load_model("py-pooled-weigh", w))
        weigh_model = models[-1]
        # And with the colour-disagreement channel (a sixth cue channel the weights read).
        weigh_cfg.name, weigh_cfg.pool.disagree = "pooled-variant-disagree", {"near": 2}
        w = work / "pooled_variant_disagree.safetensors"
        ref.init_weights(weigh_cfg, str(w), seed=11)
        models.append(p.load_model("py-pooled-disagree", w))
        disagree_model = models[-1]
        # The features family: a per-source CNN whose warped maps follow each view's
        # RGBA and cue (Python-initialised variant, and Rust-initialised `nviews-features`).
        weigh_cfg.name, weigh_cfg.pool.source_features = "pooled-variant-features", [ref.Conv(3, 4), ref.Conv(5, 3)]
        w = work / "pooled_variant_features.safetensors"
        ref.init_weights(weigh_cfg, str(w), seed=13)
        models.append(p.load_model("py-pooled-features", w))
        feature_models = [models[-1]]
        if example.is_file():
            w = work / "rust_nviews_features.safetensors"
            run([example, "nviews-features", w], "init_weights nviews-features")
            models.append(p.load_model("rust-nviews-features", w))
            feature_models.append(models[-1])
        for extra in args.weights:
            models.append(p.load_model(extra.stem, extra))
        reference_loader_checks(p, models[0].weights)
        # add_cue.py on the first pooled model without the cue (the shipped one, when it has none).
        plain = [m for m in models if m.cfg.pool is not None and m.cfg.pool.view_channels() == 4]
        if plain:
            add_cue_check(p, plain[0].weights, np.random.default_rng(8), weigh=False)
            add_cue_check(p, plain[0].weights, np.random.default_rng(9), weigh=True)
        else:
            p.fail("no pooled model without the cue to check add_cue.py on")
        weighed = [m for m in models if m.cfg.pool is not None and m.cfg.pool.weigh is not None and m.cfg.pool.disagree is None]
        add_disagree_check(p, weighed[0].weights, np.random.default_rng(10))

        for m in models:
            print(f"== cases for {m.name}", flush=True)
            rng = np.random.default_rng(6)
            for name, b, d, th, tw, fill, relative in cases(m.cfg):
                p.compare(m, name, make_inputs(m.cfg, b, d, th, tw, fill, rng), relative)
                print(f"  {name}: done", flush=True)
            if m.cfg.pool is not None:
                pooled_cases(p, m, rng)
        for m in feature_models:
            features_check(p, m, np.random.default_rng(14))
        newest_opset(p, models[0])

        # Real plane sweeps, through `deepstereo sweep --model`.
        main_model = models[0]
        print(f"== plane sweeps with {main_model.name}", flush=True)
        scene = procedural_scene(p)
        if scene is not None:
            sweep_case(p, main_model, "procedural", scene, None, [])
            # The cue's channels as `sweep --model` writes them, through every runtime.
            sweep_case(p, cue_model, "procedural-cue", scene, None, ["--views", "5"])
            sweep_case(p, weigh_model, "procedural-weigh", scene, None, ["--views", "5"])
            sweep_case(p, disagree_model, "procedural-disagree", scene, None, ["--views", "5"])
        # Real scenes: few planes so that a whole-image tile stays small.
        real = [("templeRing", 4, []), ("ethiopianHead", 2, [])]
        for name, planes, extra in real:
            d = args.data / name
            if d.is_dir():
                sweep_case(p, main_model, name, d, planes, extra)
            else:
                p.note(f"{d} not found: real-scene case skipped")
    finally:
        if args.keep:
            shutil.copytree(work, args.keep, dirs_exist_ok=True)
        shutil.rmtree(work, ignore_errors=True)

    print()
    print(p.table())
    print()
    for n in p.notes:
        print(f"note: {n}")
    print(f"{len(p.rows)} comparisons in {time.time() - t0:.0f} s; tolerance {TOL:g} (relative to the output for 1e4 inputs)")
    if p.failures:
        print(f"PARITY FAILED: {len(p.failures)} problem(s)")
        for f in p.failures:
            print(f"  - {f}")
        return 1
    print("parity: all checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
