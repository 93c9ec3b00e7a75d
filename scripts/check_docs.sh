#!/usr/bin/env bash
# Documentation speaks to users and points to what exists. For README.md and every page under docs/
# this script fails, listing each hit as FILE:LINE: TEXT [kind], on
#   * numbers of a tracker the reader cannot see ("issue 13.2", "issue-13", "issues #4");
#   * dates of work ("2026-12-02", a heading "## … (2 Dec"), a development diary ("ninth session",
#     "branch w4-…", "stop 23", "22:45–23:10 UTC");
#   * team roles ("the lead", "engineers", "helpers");
#   * dead relative links: a Markdown link or image whose file does not exist, or whose #anchor is
#     not a heading of that page (GitHub's anchors: lower case, punctuation dropped, spaces to
#     hyphens), and a `docs/NAME.md` named in the text that does not exist.
# Dates that are part of a citation (a source's own release date) belong in the source's reference,
# not in prose; no page needs one.
#
#   bash scripts/check_docs.sh            # README.md and docs/**/*.md
#   bash scripts/check_docs.sh FILE...    # other files (e.g. a page being written)
set -euo pipefail
cd "$(dirname "$0")/.."

files=("$@")
if [ ${#files[@]} -eq 0 ]; then
  mapfile -t files < <(find docs -name '*.md' -not -path '*/node_modules/*' | sort)
  files=(README.md "${files[@]}")
fi

# One Perl-compatible pattern per kind; each match is reported with the kind's name.
months='Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Oct|Nov|Dec'
patterns=(
  'issue number|\b[Ii]ssues?[ -]#?[0-9]+(\.[0-9]+)?\b|\bissue #[0-9]'
  'date of work|\b20[0-9]{2}-[01][0-9]-[0-3][0-9]\b|^#+ .*\((?:[0-9]{1,2} (?:'"$months"')|(?:'"$months"')[a-z]* [0-9]{1,2}\b)'
  'development diary|\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth) session\b|\bbranch w[0-9]+|\bstop [0-9]+\b|\b[0-9]{1,2}:[0-9]{2}(:[0-9]{2})?[ –-]+[0-9]{0,2}:?[0-9]{0,2} ?UTC\b'
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

# Links: relative files and anchors, outside fenced code blocks and code spans.
python3 - "${files[@]}" <<'PY' || status=1
import os, re, sys

def slugs(path, cache={}):
    if path not in cache:
        seen, out, fence = {}, set(), False
        for line in open(path, encoding="utf-8"):
            if line.lstrip().startswith("```"):
                fence = not fence
                continue
            m = None if fence else re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
            if not m:
                continue
            s = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
        cache[path] = out
    return cache[path]

bad = 0
for page in sys.argv[1:]:
    base = os.path.dirname(page)
    fence = False
    for no, line in enumerate(open(page, encoding="utf-8"), 1):
        if line.lstrip().startswith("```"):
            fence = not fence
            continue
        if fence:
            continue
        text = re.sub(r"`[^`]*`", "", line)
        targets = [m.group(1) for m in re.finditer(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text)]
        for t in targets:
            if re.match(r"[a-z][a-z0-9+.-]*:", t):      # http:, https:, mailto:, …
                continue
            path, _, anchor = t.partition("#")
            target = os.path.normpath(os.path.join(base, path)) if path else page
            if not os.path.exists(target):
                print(f"{page}:{no}: {line.strip()}  [dead link: {t}]")
                bad = 1
            elif anchor and target.endswith(".md") and anchor.lower() not in slugs(target):
                print(f"{page}:{no}: {line.strip()}  [dead anchor: {t}]")
                bad = 1
        for m in re.finditer(r"(?<![\w/.-])docs/[\w./-]+\.md\b", line):
            if not os.path.exists(m.group(0)):
                print(f"{page}:{no}: {line.strip()}  [names a missing page: {m.group(0)}]")
                bad = 1
sys.exit(bad)
PY

if [ $status -ne 0 ]; then
  echo "check_docs: the lines above speak of the project's history or point to nothing: say the" \
       "current fact in the code's or the page's own terms (git log keeps the history), and link to" \
       "what exists." >&2
else
  echo "check_docs: ${#files[@]} page(s) clean"
fi
exit $status
