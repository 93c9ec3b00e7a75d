#!/usr/bin/env bash
# Each ISA-specific kernel object (compiled with its own -march) defines exactly one global symbol,
# its entry point: an inline function (Eigen, the standard library) emitted there as a weak symbol
# could be picked by the linker for code that runs on any CPU, and fault on an older one.
# Usage: kernel_symbols_test.sh OBJECT...   (an argument may be a ';'-separated CMake list)
set -euo pipefail
objs=()
for a in "$@"; do IFS=';' read -ra part <<< "$a"; objs+=("${part[@]}"); done
[ ${#objs[@]} -gt 0 ] || { echo "FAIL: no kernel objects given"; exit 1; }
fail=0
for o in "${objs[@]}"; do
  syms=$(nm --defined-only -g --format=posix "$o" | awk '{print $1 " " $2}')
  n=$(printf '%s\n' "$syms" | grep -c . || true)
  if [ "$n" -ne 1 ] || ! printf '%s\n' "$syms" | grep -qE '^_ZN7haptree2ff6kernel[0-9]+cluster_rows_(avx2|avx512)E.* T$'; then
    echo "FAIL $o: $n global symbols:"; printf '%s\n' "$syms" | c++filt | head -20; fail=1
  else
    echo "ok   $o: $(printf '%s\n' "$syms" | c++filt)"
  fi
done
exit $fail
