#!/usr/bin/env python3
"""Check that every relative link and image in the given Markdown files resolves to a file or
folder of the repository, and that #anchors name a heading of the target (GitHub's slugs).

    python3 docs/check_links.py . README.md CHANGELOG.md docs/*.md docs/benchmark/*.md
"""
import os, re, sys
root = os.path.abspath(sys.argv[1]); files = sys.argv[2:]
link_re = re.compile(r'!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+"[^"]*")?\)')
img_re = re.compile(r'<img[^>]*\bsrc="([^"]+)"')
def slugs(path):
    out = set(); counts = {}
    in_code = False
    for line in open(path, encoding='utf-8'):
        if line.startswith('```'): in_code = not in_code; continue
        if in_code: continue
        m = re.match(r'#{1,6}\s+(.*?)\s*#*\s*$', line)
        if not m: continue
        s = m.group(1).strip().lower()
        s = re.sub(r'[^\w\- ]', '', s).replace(' ', '-')
        n = counts.get(s, 0); counts[s] = n + 1
        out.add(s if n == 0 else f'{s}-{n}')
    return out
bad = 0; total = 0
for f in files:
    text = open(f, encoding='utf-8').read()
    # drop fenced code blocks
    text_nc = re.sub(r'```.*?```', '', text, flags=re.S)
    targets = link_re.findall(text_nc) + img_re.findall(text_nc)
    for t in targets:
        if re.match(r'[a-z]+://|mailto:', t): continue
        total += 1
        path, _, anchor = t.partition('#')
        base = os.path.dirname(os.path.abspath(f))
        full = os.path.normpath(os.path.join(base, path)) if path else os.path.abspath(f)
        ok = os.path.exists(full) and full.startswith(root)
        why = '' if ok else 'missing'
        if ok and anchor and full.endswith('.md') and anchor not in slugs(full):
            ok = False; why = f'no heading #{anchor}'
        if not ok:
            bad += 1; print(f'BROKEN {f}: {t} ({why})')
print(f'{total} relative links/images checked in {len(files)} files, {bad} broken')
sys.exit(1 if bad else 0)
