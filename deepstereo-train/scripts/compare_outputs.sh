#!/bin/bash
# Byte identity of two builds: runs a baseline binary and a new one on the same small
# inputs (inspect, sweep, render with three models, pruning and a path, eval, mpi, export,
# forward, report, tune --steps, demo) into separate folders and compares every output
# file: JSON with timing fields stripped, text with seconds stripped, the rest byte for
# byte (stderr logs, and the report's plot and page, which draw seconds, are not compared).
# A refactoring that must not change behaviour passes with "different: 0".
# Usage: bash deepstereo-train/scripts/compare_outputs.sh BASE_BIN NEW_BIN [OUTDIR]
#        SCENE (default ../shared/data/val/stitch) is read at --downscale 4.
set -u
cd "$(dirname "$0")/../.."
BASE=$(realpath "${1:?usage: compare_outputs.sh BASE_BIN NEW_BIN [OUTDIR]}")
NEW=$(realpath "${2:?usage: compare_outputs.sh BASE_BIN NEW_BIN [OUTDIR]}")
OUT=${3:-/tmp/deepstereo-compare}
SCENE=$(realpath "${SCENE:-../shared/data/val/stitch}")
ASSETS=$PWD/deepstereo-train/assets
NV=$ASSETS/nviews-disagree-scratch.safetensors
TINY=$ASSETS/tiny.safetensors
export RAYON_NUM_THREADS=2
rm -rf "$OUT"; mkdir -p "$OUT/base" "$OUT/new"
S="--scene $SCENE --downscale 4"
run_both() { # name, args...
  local name=$1; shift
  for side in base new; do
    local bin=$BASE; [ $side = new ] && bin=$NEW
    local d=$OUT/$side/$name; mkdir -p "$d"
    local args=("${@//@OUT@/$d}")
    local t0=$(date +%s.%N)
    if ! (cd "$d" && nice -n 5 "$bin" "${args[@]}" >"$d/stdout.txt" 2>"$d/stderr.txt"); then
      echo "  [$side] $name exited non-zero" ; echo "rc=fail" >> "$d/stdout.txt"
    fi
    printf "  %-4s %-14s %6.1fs\n" $side $name $(echo "$(date +%s.%N) - $t0" | bc)
  done
}
run_both inspect   inspect $S --json
run_both sweep     sweep $S --target 3 --views 3 --planes 8 --model embedded --out @OUT@/sweep.safetensors --png @OUT@/png
run_both render    render $S --target 5 --planes 8 --out @OUT@/r
run_both render_nv render $S --target 5 --planes 8 --model $NV --out @OUT@/r
run_both render_tiny render $S --target 5 --planes 8 --model $TINY --out @OUT@/r
run_both render_prune render $S --target 7 --planes 16 --prune auto --out @OUT@/r
run_both render_path render $S --path circle --frames 2 --planes 8 --model $NV --out @OUT@/p
run_both eval      eval $S --holdout 3,11 --planes 8 --model $NV --json @OUT@/eval.json --images @OUT@/img
run_both eval_emb  eval $S --holdout 10 --planes 8 --json @OUT@/eval.json
run_both mpi       mpi $S --target 4 --planes 8 --margin 8 --model $NV --out @OUT@/m
run_both mpi_multi mpi $S --targets 4,9 --planes 8 --margin 0 --out @OUT@/m
run_both mpi_eval  mpi $S --holdout 12 --planes 8 --eval --model $NV --out @OUT@/m
run_both export    export --out @OUT@/net.onnx
run_both export_nv export --model $NV --out @OUT@/net.onnx
run_both sweep_nv  sweep $S --target 3 --views 3 --planes 8 --model $NV --out @OUT@/s.safetensors
run_both forward2  forward --model $NV --inputs ../sweep_nv/s.safetensors --out @OUT@/f.safetensors
run_both report    report $S --holdout 6 --model $NV --planes-grid 4,8 --views-grid 2,3 --out @OUT@/rep
run_both tune      tune $S --holdout 2 --model $NV --steps 3 --seed 7 --batch 1 --validate-every 2 --out @OUT@/tuned.safetensors --no-progress
run_both demo      demo --out @OUT@/d --size 64x48 --path-frames 2
# Compare: JSON with timing fields stripped, text logs with numbers of seconds stripped,
# everything else byte for byte.
python3 - "$OUT" <<'PY'
import json, os, re, sys, filecmp
out = sys.argv[1]
TIMING = re.compile(r'(second|_s$|^s$|time|elapsed|ms$|_ms|fps|speed|duration|per_s|_sec)', re.I)
def strip(v):
    if isinstance(v, dict):
        return {k: strip(x) for k, x in v.items() if not TIMING.search(k)}
    if isinstance(v, list):
        return [strip(x) for x in v]
    return v
bad = same = timing_only = 0
skipped = []
for root, _, files in os.walk(os.path.join(out, 'base')):
    for f in files:
        b = os.path.join(root, f); rel = os.path.relpath(b, os.path.join(out, 'base'))
        n = os.path.join(out, 'new', rel)
        if not os.path.exists(n):
            print('MISSING in new:', rel); bad += 1; continue
        if f in ('stderr.txt',):
            skipped.append(rel); continue
        if filecmp.cmp(b, n, shallow=False):
            same += 1; continue
        if f.endswith('.json') or f.endswith('.jsonl'):
            try:
                lb = [strip(json.loads(l)) for l in open(b)] if f.endswith('l') else strip(json.load(open(b)))
                ln = [strip(json.loads(l)) for l in open(n)] if f.endswith('l') else strip(json.load(open(n)))
            except Exception as e:
                print('DIFF (unparsable json)', rel, e); bad += 1; continue
            if lb == ln:
                timing_only += 1; continue
        if rel.endswith('report/rep/report.png') or rel.endswith('report/rep/index.html'):
            # The report's plot and page draw the measured seconds per image.
            skipped.append(rel); continue
        if f.endswith('.csv'):
            def norm(p):
                rows = [l.split(',') for l in open(p).read().splitlines()]
                drop = [i for i, h in enumerate(rows[0]) if TIMING.search(h)] if rows else []
                return [[c for i, c in enumerate(r) if i not in drop] for r in rows]
            if norm(b) == norm(n):
                timing_only += 1; continue
        if f.endswith('.md') or f.endswith('.txt') or f.endswith('.html'):
            def norm(p):
                t = open(p).read().replace('/base/', '/SIDE/').replace('/new/', '/SIDE/')
                t = re.sub(r'\| [0-9.]+ \|$', '| T |', t, flags=re.M)  # the s / image column
                if rel == 'demo/stdout.txt':  # the demo's table: its last column is seconds
                    t = re.sub(r'(\d\.\d{3}) +[0-9.]+$', r'\1 T', t, flags=re.M)
                return re.sub(r'\d+(\.\d+)? ?(s|ms)\b', 'T', t)
            if norm(b) == norm(n):
                timing_only += 1; continue
        print('DIFF', rel); bad += 1
for root, _, files in os.walk(os.path.join(out, 'new')):
    for f in files:
        rel = os.path.relpath(os.path.join(root, f), os.path.join(out, 'new'))
        if not os.path.exists(os.path.join(out, 'base', rel)):
            print('EXTRA in new:', rel); bad += 1
print(f'identical: {same}, equal but for timing fields / output paths: {timing_only}, different: {bad}, not compared: {len(skipped)} (stderr logs; the report plot and page, which draw timings)')
sys.exit(1 if bad else 0)
PY
