#!/usr/bin/env bash
# CTest fuzz smoke run: smoke.sh FUZZER WORKDIR SECONDS CORPUS_DIR...
# New inputs go into WORKDIR/corpus (never into the repository); a crash leaves WORKDIR/crash-* and fails.
set -euo pipefail
fuzzer=$1 work=$2 seconds=$3
shift 3
rm -rf "$work"
mkdir -p "$work/corpus"
exec "$fuzzer" -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 \
  -print_final_stats=1 -artifact_prefix="$work/" "$work/corpus" "$@"
