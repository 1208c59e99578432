#!/usr/bin/env bash
# Regenerates every result and picture in the README (takes ~40 minutes on 2 cores).
# Usage: bash deepstereo-train/scripts/reproduce.sh [OUT_DIR]   (needs ../shared/data for the real scenes)
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT="${1:-/tmp/deepstereo-reproduce}"
FIG=deepstereo-train/assets/readme
DATA=../shared/data
mkdir -p "$OUT" "$FIG"
cargo build --release -p deepstereo-train
DS=target/release/deepstereo
# The tables and pictures of the README's sections on evaluation, pruning and run time
# were measured with `tiny`, the embedded model before `nviews-real` (the demo uses the
# embedded default); they pass it by file.
TINY=(--model deepstereo-train/assets/tiny.safetensors)

echo "== training curves (tiny's committed log, the default model's two runs)"
$DS curve --log "$FIG/training_log.jsonl" --out "$FIG/training_curve.png"
# The logs of the runs before the shipped one are in git (docs/experiments.md).
for run in nviews-real nviews-prox; do
  mkdir -p "$OUT/runs/$run"
  git show "781c573:deepstereo-train/runs/$run/log.jsonl" > "$OUT/runs/$run/log.jsonl"
done
$DS curve --log "$OUT/runs/nviews-real" --out "$FIG/nviews_curve.png"
$DS curve --log "$OUT/runs/nviews-prox" --out "$FIG/prox_curve.png"

echo "== procedural scenes (contact sheet, speed)"
$DS synth --out "$OUT/sheet" --scenes 4 --seed 99 --size 240x180 --sheet "$FIG/synth.png"
$DS synth --out "$OUT/speed" --scenes 64 --seed 5 --size 160x120

echo "== demo"
$DS demo --out "$OUT/demo" | tee "$OUT/demo.txt"
cp "$OUT/demo/comparison.png" "$FIG/demo.png"

echo "== eval on held-out procedural scenes (seeds never used in training)"
$DS synth --out "$OUT/eval_scenes" --scenes 8 --seed 777 --size 240x180
$DS eval "${TINY[@]}" --scene "$OUT/eval_scenes" --holdout 2,5,8 --json "$OUT/eval_procedural.json"

if [ -d "$DATA" ]; then
  echo "== eval on the real scenes"
  $DS eval "${TINY[@]}" --scene "$DATA/templeRing" --holdout 5,15,25,35,45 --json "$OUT/eval_temple.json" --images "$OUT/temple"
  $DS eval "${TINY[@]}" --scene "$DATA/ethiopianHead" --downscale 4 --llffhold 8 --json "$OUT/eval_ethiopian.json" --images "$OUT/ethiopian"
  $DS eval "${TINY[@]}" --scene "$DATA/fox" --downscale 4 --near 1 --far 20 --holdout 8,24,40,56 --json "$OUT/eval_fox.json" --images "$OUT/fox"
  echo "== the same with --prune off (the plain renderer)"
  $DS eval "${TINY[@]}" --scene "$OUT/eval_scenes" --holdout 2,5,8 --prune off --json "$OUT/eval_procedural_off.json"
  $DS eval "${TINY[@]}" --scene "$DATA/templeRing" --holdout 5,15,25,35,45 --prune off --json "$OUT/eval_temple_off.json"
  $DS eval "${TINY[@]}" --scene "$DATA/ethiopianHead" --downscale 4 --llffhold 8 --prune off --json "$OUT/eval_ethiopian_off.json"
  $DS eval "${TINY[@]}" --scene "$DATA/fox" --downscale 4 --near 1 --far 20 --holdout 8,24,40,56 --prune off --json "$OUT/eval_fox_off.json"
  echo "== error against run time, with and without pruning, on real scenes"
  $DS report "${TINY[@]}" --scene "$DATA/templeRing" --downscale 2 --holdout 5,25 --planes-grid 16,32,64 --backends candle --prune-grid off,auto --out "$OUT/report_temple"
  cp "$OUT/report_temple/report.png" "$FIG/report_temple.png"
  $DS report "${TINY[@]}" --scene "$DATA/fox" --downscale 4 --near 1 --far 20 --holdout 8,24 --planes-grid 16,32,64 --backends candle --prune-grid off,auto --out "$OUT/report_fox"
  cp "$OUT/report_fox/report.png" "$FIG/report_fox.png"
  $DS report "${TINY[@]}" --scene "$DATA/ethiopianHead" --downscale 4 --llffhold 8 --planes-grid 16,32,64 --backends candle --prune-grid off,auto --out "$OUT/report_ethiopian"
  cp "$OUT/report_ethiopian/report.png" "$FIG/report_ethiopian.png"
  echo "== pruning off / auto / fast on every scene (32 planes; 96 on the procedural scenes too)"
  for prune in "--prune off" "--prune auto" "--prune auto --prune-keep 0.8 --prune-margin 0"; do
    tag=$(echo "$prune" | tr -cd 'a-z0-9.')
    $DS eval "${TINY[@]}" --scene "$OUT/eval_scenes" --holdout 2,5 --planes 32 $prune --json "$OUT/prune_proc32_$tag.json"
    $DS eval "${TINY[@]}" --scene "$OUT/eval_scenes" --holdout 2,5 --planes 96 $prune --json "$OUT/prune_proc96_$tag.json"
    $DS eval "${TINY[@]}" --scene "$DATA/templeRing" --downscale 2 --holdout 5,25 --planes 32 $prune --json "$OUT/prune_temple_$tag.json"
    $DS eval "${TINY[@]}" --scene "$DATA/ethiopianHead" --downscale 4 --llffhold 8 --planes 32 $prune --json "$OUT/prune_ethiopian_$tag.json"
    $DS eval "${TINY[@]}" --scene "$DATA/fox" --downscale 4 --near 1 --far 20 --holdout 8,24 --planes 32 $prune --json "$OUT/prune_fox_$tag.json"
  done
else
  echo "note: $DATA not found: real-scene results skipped"
fi

echo "== error against run time on a procedural scene"
$DS report "${TINY[@]}" --scene "$OUT/eval_scenes/scene_0000" --holdout 2,5 --planes-grid 8,16,32,64,96 --backends candle,ort --prune-grid off,auto --out "$OUT/report_procedural"
$DS report "${TINY[@]}" --scene "$OUT/eval_scenes/scene_0000" --holdout 2,5 --planes-grid 32 --downscale-grid 1,2,4 --backends ort --prune-grid off --out "$OUT/report_scale"
$DS report "${TINY[@]}" --scene "$OUT/eval_scenes/scene_0000" --holdout 2,5 --planes-grid 32 --views-grid 1,2,3,4 --backends ort --prune-grid off --out "$OUT/report_views"
cp "$OUT/report_procedural/report.png" "$FIG/report_procedural.png"
if [ -d "$DATA" ]; then
  echo "== error against run time with the embedded model, with and without pruning"
  $DS report --scene "$DATA/val/juicebox" --llffhold 8 --planes-grid 16,32,64,96 --backends candle --prune-grid off,auto --out "$OUT/report_juicebox"
  cp "$OUT/report_juicebox/report.png" "$FIG/report_juicebox.png"
fi
echo "== speed benchmarks (whole network against onnxruntime and PyTorch)"
cargo bench -p deepstereo-train --bench network | tee "$OUT/bench_network.txt"
echo "== convolution layers against onnxruntime and PyTorch"
CONV_BENCH_REF=0 cargo bench -p deepstereo-core --bench conv | tee "$OUT/bench_conv.txt"
echo "== implicit-GEMM kernels against im2col + gemm (tiny forward and step, alternated)"
cargo build --release -p deepstereo-train --example forward_probe
for round in 1 2 3 4; do
    for conv in auto im2col; do
        for what in "tiny 20" "tiny 5 32 step"; do
            echo "DEEPSTEREO_CONV=$conv $(DEEPSTEREO_CONV=$conv target/release/examples/forward_probe $what)"
        done
    done
done | tee "$OUT/kernels_ab.txt"
echo "results in $OUT, pictures in $FIG"
