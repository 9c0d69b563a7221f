#!/usr/bin/env bash
# The CUDA benchmarks, run on a GPU machine that has Python with CUDA torch but no package
# registry, such as the lent device.
#
# On the CPU machine, once: `make gpu-stores` (renders out/bench-400.zarr and
# out/gpu-learn-64-1100.zarr) and `make gpu-wheels` (the packages the device lacks, as wheels in
# .whl/). Carry the store a part reads and .whl/ with the checkout (64 MiB a call at most, the
# checkout's own files too: `make gpu-carry` adds them up for learn), then there:
#
#     bash benchmarks/gpu.sh learn          # the default recipe and the paper's, each for the
#                                           # paper's 1.47 M image passes on
#                                           # out/gpu-learn-64-1100.zarr
#     bash benchmarks/gpu.sh infer [ARGS]   # benchmarks.infer at batch 1 and 128, compiled rows
#     bash benchmarks/gpu.sh train          # benchmarks.train, L1 (2,000 samples), then L1 + VGG16
#     bash benchmarks/gpu.sh viewer [ARGS]  # benchmarks.viewer --device cuda (carry benchmarks/.cache
#                                           # too: the screen UV layouts `make bench-viewer` renders)
#
# learn: benchmarks.learning's rows paper and default, at batch BATCH (128: the paper's 6
# would take hours of steps) for PASSES image passes (1470000, the paper's 30 epochs of 49,000
# images), the split held in the GPU's memory (trainer train --preload), each row scored on its
# held-out materials. The runs (checkpoints of 140-190 MB each) go to WORK (default: a new
# temporary folder; a row finished there is kept if a later one is cut off, and a WORK given
# again resumes its rows), and $OUT gets what a device call brings back (8 files at most, none
# over 16 MiB, 64 MiB in all): the table (learning-gpu.json), the side-by-side grid
# (learning-gpu.png), the log gpu-bench.txt, each row's grid and training log in
# learning-rows.tgz, and each row's network (trainer slim: float16, 23 MB for the default's)
# in parts of 15 MiB, learning-ROW.pt.0, .1, ...: eight files for both rows. Here, `make
# gpu-learn-back FROM=FOLDER` puts the table in place, joins each network into
# out/gpu-learn/ROW.pt (a checkpoint trainer eval, render, viewer and export take) and scores
# them here. A row's network that would pass 8 files or 60 MiB in all stays behind, and the
# log says so.
# The rows share LEARN_SECONDS (default 520: with the set-up, the rows, their scoring, the
# slimming and the copies fit a 600-second call; give less when the call has less) by
# benchmarks.learning --seconds: the paper's row first, for at most ROW_SECONDS ("paper=200",
# space-separated SECONDS or ROW=SECONDS: --row-seconds), then the default in what is left of
# the call; a row stopped by its limit is scored where it stopped and the table says after
# how many passes.
# Each row's scores are in the log as soon as it is scored, so a call killed later still
# brings them back.
# Each row's (peak) rate is scaled to BATCH by the rules in LR_SCALE (benchmarks.learning
# --lr-scale, space-separated: RULE for every row, ROW=RULE for one; sqrt, the rate times the
# square root of BATCH over the row's own batch; linear; none). The default, "sqrt paper=none",
# scales the default's peak by the root (1.13e-2 at batch 128) and keeps the paper's constant
# 1e-3; docs/training.md ("Larger batches") gives the CPU rows that chose these rules (tables
# learning-64-b128-default-* and learning-64-b128-paper-*).
# ROWS picks other rows of benchmarks.learning, each at batch BATCH (the rows pinned to fp32, as
# default-w32 and the sb-* ones are, train in fp32 there too): ROWS=default-w32, for one, trains
# the default at width 32 (table learning-64-64k-width), in a call of its own.
# Tried here first, on the CPU with a few steps: DEVICE=cpu PASSES=64 BATCH=8 PYTHON=.venv/bin/python
# LEARN_STORE=benchmarks/.cache/learning-64.zarr OUT=/tmp/learn bash benchmarks/gpu.sh learn
#
# ARGS go to benchmarks.infer after its defaults (e.g. --only "subpixel compiled", --fold-ring),
# or to benchmarks.viewer (e.g. --runtimes torch,graph: fp32, then the CUDA graph).
# Output is printed and appended to ${OUT:-out}/gpu-bench.txt. The compiled rows leave the
# convolutions to cuDNN and the GEMMs to cuBLAS, as the fast path does by default
# (trainer.rendering.infer.TUNED_BACKENDS): with Triton's templates autotuned too
# (CONV_BACKENDS=ATEN,TRITON or GEMM_BACKENDS=ATEN,TRITON) the infer part outlasts the device's
# 10-minute call.
#
# Autotuning across calls: Inductor's and Triton's caches live in .gpucache/ (ignored by git).
# Inductor writes each operation's autotuning timings there as soon as they are measured, so a
# run stopped part-way keeps what it tuned. The benchmark runs for at most BUDGET seconds
# (default 540: a device call lasts 600), then .gpucache/ is packed into
# ${OUT:-out}/gpucache.tgz (only Inductor's timings when the whole is over 15 MiB, the most a
# device call brings back). Unpack that into .gpucache/ here and carry .gpucache with the next
# call: its run skips the operations already tuned and goes on with the rest.
set -euo pipefail
cd "$(dirname "$0")/.."
py=${PYTHON:-python3}
store=out/bench-400.zarr
part=${1:-}
[[ $part == learn || $part == infer || $part == train || $part == viewer ]] || { echo "usage: bash benchmarks/gpu.sh learn|infer|train|viewer [ARGS]" >&2; exit 2; }
[[ $part == learn ]] && store=${LEARN_STORE:-out/gpu-learn-64-1100.zarr}
shift
[[ ($part != train && $part != learn) || $# -eq 0 ]] || { echo "gpu.sh: $part takes no arguments" >&2; exit 2; }
if [[ $part == viewer ]]; then
    compgen -G "benchmarks/.cache/screen_uv-*.npz" >/dev/null || { echo "gpu.sh: benchmarks/.cache has no screen UV layouts (make bench-viewer, then carry benchmarks/.cache)" >&2; exit 2; }
else
    [[ -f $store/zarr.json ]] || { echo "gpu.sh: $store is missing (make gpu-stores, then carry it)" >&2; exit 2; }
fi
if ! "$py" -c "import zarr, numcodecs, google_crc32c, PIL, click, tenacity, fsspec, tqdm, flip_evaluator" 2>/dev/null; then
    [[ -d .whl ]] || { echo "gpu.sh: zarr or the trainer's packages are not installed and .whl/ is missing (make gpu-wheels)" >&2; exit 2; }
    "$py" -m pip install --quiet --no-index --no-deps --find-links .whl .whl/*.whl
fi
out=${OUT:-out}
log=$out/gpu-bench.txt
mkdir -p "$out" .gpucache
export TORCHINDUCTOR_CACHE_DIR=$PWD/.gpucache/inductor TRITON_CACHE_DIR=$PWD/.gpucache/triton
budget=(timeout --signal=INT --kill-after=20 "${BUDGET:-540}")
work=${WORK:-}
[[ $part != learn || -n $work ]] || work=$(mktemp -d)
scales=()
for rule in ${LR_SCALE:-sqrt paper=none}; do scales+=(--lr-scale "$rule"); done
caps=()
for cap in ${ROW_SECONDS:-paper=200}; do caps+=(--row-seconds "$cap"); done
train=(-m benchmarks.train --store "$store" --batch 32 --workers 12 --log-every 10)
{
    # "-dirty": the tree differs from that commit (a device copy may carry an older .git)
    echo "== $part $(date -u +%FT%TZ) $(git describe --always --dirty 2>/dev/null || echo '?')"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
    "$py" -c 'import sys, torch; print("python", sys.version.split()[0], "torch", torch.__version__)'
    case $part in
        infer) TORCHINDUCTOR_MAX_AUTOTUNE_CONV_BACKENDS=${CONV_BACKENDS:-ATEN} \
                   TORCHINDUCTOR_MAX_AUTOTUNE_GEMM_BACKENDS=${GEMM_BACKENDS:-ATEN} \
                   "${budget[@]}" "$py" -m benchmarks.infer --store "$store" --batch 128 \
                   --iters 30 --compile "$@" || echo "benchmarks.infer ended with status $?" ;;
        # L1 on 2,000 samples (63 steps an epoch: the epoch-end stall, if any, shows), then
        # the paper's loss on 8,000 samples (docs/benchmarks.md)
        train) "$py" "${train[@]}" --replicate 50 --steps 240 --warmup 40 --sim-epochs 4
               "$py" "${train[@]}" --replicate 200 --loss l1+vgg --steps 120 --warmup 20 \
                   --sim-epochs 0 ;;
        viewer) "$py" -m benchmarks.viewer --device cuda "$@" ;;
        learn) "$py" -m benchmarks.learning --store "$store" --device "${DEVICE:-cuda}" --preload \
                   --budget "${PASSES:-1470000}" --batch "${BATCH:-128}" \
                   "${scales[@]}" --rows "${ROWS:-paper,default}" \
                   "${caps[@]}" --seconds "${LEARN_SECONDS:-520}" \
                   --work "$work" --results "$out" --name learning-gpu \
                   || echo "benchmarks.learning ended with status $?" ;;
    esac
} 2>&1 | tee -a "$log"
if [[ $part == learn ]]; then  # each row's grid and log in one archive, then its network
    runs=()
    for run in "$work"/*/*/*/; do
        [[ -f $run/log.jsonl ]] && runs+=("${run%/}")
    done
    ((${#runs[@]})) || exit 0
    kept=$(cd "$work" && ls -d */*/*/grid.png */*/*/log.jsonl 2>/dev/null)
    tar -czf "$out/learning-rows.tgz" -C "$work" $kept
    part=$((15 << 20))
    for run in "${runs[@]}"; do
        row=$(basename "$run") slim=$work/$row.pt
        "$py" -m trainer.cli slim --checkpoint "$run" -o "$slim" 2>&1 | tee -a "$log" || continue
        size=$(stat -c %s "$slim")
        files=$(($(find "$out" -type f | wc -l) + (size + part - 1) / part))
        if ((files > 8 || $(du -sb "$out" | cut -f1) + size > 60 << 20)); then
            echo "gpu.sh: $row's network stays behind (over 8 files or 60 MiB to bring back)" \
                | tee -a "$log"
            continue
        fi
        split -b "$part" -d -a 1 "$slim" "$out/learning-$row.pt."
    done
fi
[[ $part == infer ]] || exit 0
tar -czf "$out/gpucache.tgz" -C .gpucache .
held="Inductor's and Triton's caches"
if (($(stat -c %s "$out/gpucache.tgz") > 15 << 20)) && [[ -d .gpucache/inductor/cache ]]; then
    tar -czf "$out/gpucache.tgz" -C .gpucache inductor/cache
    # with cuDNN and cuBLAS alone (CONV_BACKENDS, GEMM_BACKENDS=ATEN) there is little to tune
    held="Inductor's autotuning timings alone: the caches are over 15 MiB"
fi
echo "caches: $out/gpucache.tgz ($(du -h "$out/gpucache.tgz" | cut -f1), $held); unpack into .gpucache/ and carry it"
