"""Training throughput: `train_ddp.py` with 1 and 2 processes against the candle trainer,
same config, same global batch, in one run.

    python python/bench_ddp.py --bin target/release/deepstereo [--configs tiny,nviews] [--batch 16] [--steps 30]

Samples per second are read from each run's `log.jsonl` (`samples_per_s`, the trainer's
own measure over each window of `--log-every` steps), the first window (warm-up) left
out, median of the rest. The candle trainer samples online (its loader thread shares the
cores); `train_ddp.py` reads shards written beforehand by `deepstereo samples` (the time
to write them is printed too). Prints a markdown table; `--json FILE` also writes it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENES = ["--synthetic", "8", "--synth-size", "160x120", "--synth-views", "10"]
VIEWS = {"nviews": ["--views", "2-6"]}
WINDOW = 5  # steps per log line


def run(cmd: list, env: dict | None = None) -> float:
    t0 = time.time()
    p = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, env=env)
    if p.returncode != 0:
        raise SystemExit(f"error: {' '.join(map(str, cmd))} failed:\n{p.stderr}")
    return time.time() - t0


def rate(log: Path) -> float:
    lines = [json.loads(l) for l in log.read_text().splitlines() if l.strip()]
    rates = [l["samples_per_s"] for l in lines[1:]]
    if not rates:
        raise SystemExit(f"error: {log}: too few log lines (raise --steps)")
    return statistics.median(rates)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", type=Path, default=ROOT / "target" / "release" / "deepstereo")
    ap.add_argument("--configs", default="tiny,nviews")
    ap.add_argument("--batch", type=int, default=16, help="global batch (2 processes take half each)")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    if a.steps < 2 * WINDOW or a.batch % 2:
        ap.error(f"--steps must be at least {2 * WINDOW} and --batch even")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        w = Path(tmp)
        for preset in a.configs.split(","):
            common = ["--config", preset, *SCENES, *VIEWS.get(preset, []), "--seed", "0"]
            hyper = ["--optimizer", "adam", "--lr", "1e-3", "--steps", a.steps, "--log-every", WINDOW]
            shards = w / preset / "shards"
            secs = run([a.bin, "samples", *common, "--count", a.batch * (a.steps + 1), "--shard-size", a.batch, "--out", shards])
            run([a.bin, "train", *common, *hyper, "--batch", a.batch, "--val-scenes", "0", "--val-batches", "0", "--validate-every", 10**6, "--no-progress", "--out", w / preset / "candle"])
            row = {"config": preset, "batch": a.batch, "samples_s_write": a.batch * (a.steps + 1) / secs, "candle": rate(w / preset / "candle" / "log.jsonl")}
            ddp = ["--shards", shards, "--config", shards / "shard-00000.safetensors", *hyper, "--validate-every", 10**6, "--checkpoint-every", 10**6]
            run([sys.executable, ROOT / "python" / "train_ddp.py", *ddp, "--batch", a.batch, "--out", w / preset / "one"])
            row["ddp1"] = rate(w / preset / "one" / "log.jsonl")
            env = dict(os.environ, OMP_NUM_THREADS="1")
            run([sys.executable, ROOT / "python" / "train_ddp.py", *ddp, "--batch", a.batch, "--threads", "1", "--out", w / preset / "one-1t"], env)
            row["ddp1_1t"] = rate(w / preset / "one-1t" / "log.jsonl")
            launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2"]
            run([*launcher, ROOT / "python" / "train_ddp.py", *ddp, "--batch", a.batch // 2, "--out", w / preset / "two"], env)
            row["ddp2"] = rate(w / preset / "two" / "log.jsonl")
            rows.append(row)
            print(f"{preset}: {row}", file=sys.stderr, flush=True)
    print(f"\ncpu cores: {os.cpu_count()}; global batch {a.batch}; {a.steps} steps; Adam; median samples/s over windows of {WINDOW} steps after the first\n")
    print("| config | candle `train` | train_ddp.py, 1 process x all cores | train_ddp.py, 1 process x 1 thread | train_ddp.py, 2 processes x 1 thread (gloo) | `deepstereo samples` writing |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['config']} | {r['candle']:.1f} | {r['ddp1']:.1f} | {r['ddp1_1t']:.1f} | {r['ddp2']:.1f} | {r['samples_s_write']:.0f} |")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
