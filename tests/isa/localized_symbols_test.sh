#!/usr/bin/env bash
# An x86-64-v3 copy (haptree/dca_avx2.cpp, coupling_avx2.cpp; renamed by cmake/LocalizeObject.cmake) defines
# one global symbol under its own name, its entry point; every other one (its copies of the library's
# functions, and of Eigen's and the standard library's inline functions, weak) carries the suffix, so
# that the linker can never take one of them for the baseline code that runs on any CPU.
# Usage: localized_symbols_test.sh OBJECT ENTRY SUFFIX
set -euo pipefail
obj=$1 entry=$2 suffix=$3
syms=$(nm --defined-only -g --format=posix "$obj" | awk '{print $1 " " $2}')
total=$(printf '%s\n' "$syms" | grep -c . || true)
plain=$(printf '%s\n' "$syms" | awk -v s="$suffix" '{ if (substr($1, length($1) - length(s) + 1) != s) print }')
weak=$(printf '%s\n' "$syms" | awk -v s="$suffix" '$2 ~ /^[WVu]$/ && substr($1, length($1) - length(s) + 1) == s' | grep -c . || true)
fail=0
if [ "$plain" != "$entry T" ]; then
  echo "FAIL $obj: symbols without the suffix $suffix (expected only '$entry T'):"
  printf '%s\n' "$plain" | c++filt | head -20
  fail=1
fi
# An object that instantiated no inline function would make the check above vacuous.
if [ "$weak" -lt 10 ]; then echo "FAIL $obj: only $weak renamed weak symbols (inline functions)"; fail=1; fi
[ $fail = 1 ] || echo "ok   $obj: $total global symbols, $weak of them weak (inline), all renamed but $entry"
exit $fail
