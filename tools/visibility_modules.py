#!/usr/bin/env python3
"""Module visibility of scanloc's library: every `pub mod` that no path from
outside the library (src/main.rs, tests/, examples/, benches/, python/src/)
goes through becomes `pub(crate) mod`. Run from the repository's root;
prints the modules kept public and those made crate-private."""
import pathlib, re, sys

ROOT = pathlib.Path('.')
CONSUMERS = [ROOT / 'src/main.rs'] + [p for d in ('tests', 'examples', 'benches', 'python/src')
                                      for p in sorted((ROOT / d).rglob('*.rs'))]
IDENT = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')

def strip_comments(text):
    return '\n'.join(line.split('//')[0] for line in text.split('\n'))

def parse(text, i, prefix, out):
    """Paths from text[i:] (just after `prefix::`), groups expanded."""
    while i < len(text) and text[i] in ' \n\t':
        i += 1
    if i < len(text) and text[i] == '{':
        i += 1
        while True:
            while i < len(text) and text[i] in ' \n\t,':
                i += 1
            if i >= len(text) or text[i] == '}':
                return i + 1
            i = parse(text, i, prefix, out)
    m = IDENT.match(text, i)
    if not m:
        if text.startswith('*', i):
            out.append(prefix)
        return i + 1
    name, i = m.group(0), m.end()
    path = prefix if name == 'self' else prefix + [name]
    out.append(path)
    if text.startswith('::', i):
        return parse(text, i + 2, path, out)
    return i

paths = []
for f in CONSUMERS:
    text = strip_comments(f.read_text())
    found = []
    for m in re.finditer(r'\bscanloc::', text):
        parse(text, m.end(), [], found)
    # Modules imported by name and then used through it (`cnn::data::x`).
    for p in list(found):
        for m in re.finditer(r'(?<![A-Za-z0-9_:])' + re.escape(p[-1]) + r'::', text) if p else []:
            parse(text, m.end(), p, found)
    paths += found
used = {tuple(p[:k]) for p in paths for k in range(1, len(p) + 1)}

def module_of(file):
    parts = list(file.relative_to(ROOT / 'src').with_suffix('').parts)
    if parts[-1] in ('mod', 'lib'):
        parts = parts[:-1]
    return parts

declaration = re.compile(r'^(\s*)pub mod (\w+)(;| \{)', re.M)
for file in sorted((ROOT / 'src').rglob('*.rs')):
    if file == ROOT / 'src/main.rs':
        continue
    text = file.read_text()
    def visibility(m):
        path = tuple(module_of(file) + [m.group(2)])
        if path in used:
            print('pub        ', '::'.join(path))
            return m.group(0)
        print('pub(crate) ', '::'.join(path))
        return f'{m.group(1)}pub(crate) mod {m.group(2)}{m.group(3)}'
    new = declaration.sub(visibility, text)
    if new != text:
        file.write_text(new)
