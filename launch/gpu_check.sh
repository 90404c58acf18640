#!/usr/bin/env bash
# The one-GPU acceptance run: the GPU figures of docs/results/gpu_check.md, into one markdown file
# (runs/gpu_check/gpu_check.md). Run from the repository root on a machine with one GPU:
#
#   launch/gpu_check.sh                # about 10-20 minutes on an H100
#   launch/gpu_check.sh --dry_run      # no GPU: resolve every config and print the commands
#
# It is `omg bench gpu` (omg/tools/gpu.py); any of its options may follow.
set -euo pipefail
cd "$(dirname "$0")/.."
exec python -m omg.cli bench gpu "$@"
