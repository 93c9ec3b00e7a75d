#!/usr/bin/env bash
# Code comments say why the code is as it is, in the code's own terms: no numbers of a tracker the
# reader cannot see ("issue 13.2", "issue-13"). Lists each hit as FILE:LINE: TEXT and fails.
#   bash scripts/check_code_comments.sh
set -euo pipefail
cd "$(dirname "$0")/.."
dirs=(haptree sim_server coupler device_bridge viewer imd_bridge launcher tools bench tests fuzz python java scripts cmake
      examples packaging)
hits=$(grep -rnP --include='*.cpp' --include='*.hpp' --include='*.h' --include='*.c' --include='*.py' \
         --include='*.sh' --include='*.cmake' --include='CMakeLists.txt' --include='*.java' --include='*.toml' \
         --exclude-dir=vendor --exclude-dir=node_modules --exclude=check_docs.sh --exclude=check_code_comments.sh \
         '\b[Ii]ssues?[ -]#?[0-9]+(\.[0-9]+)?\b|\bissue #[0-9]' "${dirs[@]}" CMakeLists.txt 2>/dev/null || true)
hits+=$(grep -rnP --include='*.js' --include='*.html' --exclude-dir=vendor --exclude-dir=node_modules \
          '\b[Ii]ssues?[ -]#?[0-9]+(\.[0-9]+)?\b' viewer/web 2>/dev/null || true)
if [ -n "$hits" ]; then
  echo "$hits"
  echo "check_code_comments: tracker numbers in the code above: say what the code does and why instead" >&2
  exit 1
fi
echo "check_code_comments: no tracker numbers in code or scripts"
