#!/usr/bin/env bash
# Documentation speaks to users: no numbers of a tracker they cannot see ("issue 13.2"), no dates of
# work ("2026-12-02"), no development diary ("ninth session", "branch w4-…", "stop 23") and no team
# roles ("the lead", "engineers", "helpers"). This script greps the pages listed below for those
# patterns and fails, listing every hit as FILE:LINE: TEXT.
#
#   bash scripts/check_docs.sh            # the pages listed in PAGES
#   bash scripts/check_docs.sh FILE...    # other files (e.g. to see what a page still holds)
#
# A page joins PAGES once it is clean. Dates that are part of a citation (a source's own release
# date) belong in the source's reference, not in prose; none of the listed pages needs one.
set -euo pipefail
cd "$(dirname "$0")/.."

PAGES=(
  README.md
  docs/accuracy_and_stability.md
  docs/algorithms.md
  docs/chaos.md
  docs/concepts.md
  docs/fuzzing.md
  docs/getting-started.md
  docs/imd.md
  docs/molecules.md
  docs/network_faults.md
  docs/performance.md
  docs/processes.md
  docs/devices.md
  docs/python.md
  docs/security.md
  docs/sessions.md
  docs/troubleshooting.md
  docs/viewer.md
)

files=("$@")
[ ${#files[@]} -gt 0 ] || files=("${PAGES[@]}")

# One Perl-compatible pattern per kind; each match is reported with the kind's name.
patterns=(
  'issue number|\b[Ii]ssues? #?[0-9]+(\.[0-9]+)?\b'
  'date of work|\b20[0-9]{2}-[01][0-9]-[0-3][0-9]\b'
  'development diary|\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth) session\b|\bbranch w[0-9]+|\bstop [0-9]+\b|\b[0-9]{1,2}:[0-9]{2}(:[0-9]{2})?[ –-]+[0-9]{0,2}:?[0-9]{0,2} ?UTC\b'
  'team role|\bthe lead\b(?! byte)|\blead'"'"'s\b|\b(engineers?|helpers?)\b'
)

status=0
for f in "${files[@]}"; do
  if [ ! -f "$f" ]; then
    echo "check_docs: $f: no such file" >&2
    status=1
    continue
  fi
  for p in "${patterns[@]}"; do
    kind=${p%%|*}
    re=${p#*|}
    while IFS= read -r hit; do
      [ -n "$hit" ] || continue
      echo "$f:$hit  [$kind]"
      status=1
    done < <(grep -nP -- "$re" "$f" || true)
  done
done
if [ $status -ne 0 ]; then
  echo "check_docs: the lines above speak of the project's history, not to its users: say the current" \
       "fact in the code's or the page's own terms (git log keeps the history)." >&2
else
  echo "check_docs: ${#files[@]} page(s) clean"
fi
exit $status
