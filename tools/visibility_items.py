#!/usr/bin/env python3
"""Item visibility, after visibility_modules.py: in the files of modules that stay
`pub`, a column-0 `pub` item (fn, struct, enum, const, static, type, trait)
whose name appears nowhere outside the library (src/main.rs, tests/,
examples/, benches/, python/src/) becomes `pub(crate)`. With
`--restore FILE`, FILE holds the compiler's output: items it reports as
`more private than` a public item they appear in, or re-exported (`only public
within the crate`), are made `pub` again."""
import pathlib, re, sys

src = pathlib.Path('src')
consumers = [pathlib.Path('src/main.rs')] + [p for d in ('tests', 'examples', 'benches', 'python/src')
                                            for p in sorted(pathlib.Path(d).rglob('*.rs'))]
words = set(re.findall(r'[A-Za-z_][A-Za-z0-9_]*', '\n'.join(p.read_text() for p in consumers)))

def module_of(f):
    parts = list(f.relative_to(src).with_suffix('').parts)
    return parts[:-1] if parts[-1] in ('mod', 'lib') else parts

def public_module(f):
    """Whether every module from the root to f's is declared `pub`."""
    parts = module_of(f)
    for k in range(1, len(parts) + 1):
        parent = src.joinpath(*parts[:k - 1])
        decl = [parent / 'mod.rs', parent.with_suffix('.rs')] if k > 1 else [src / 'lib.rs']
        text = ''.join(d.read_text() for d in decl if d.exists())
        if not re.search(r'^\s*pub mod ' + parts[k - 1] + r'\b', text, re.M):
            return False
    return True

item = r'^pub ((?:const |unsafe |async )?(?:fn|struct|enum|const|static|type|trait)) (NAME)\b'
if len(sys.argv) == 3 and sys.argv[1] == '--restore':
    log = pathlib.Path(sys.argv[2]).read_text()
    names = set(re.findall(r"(?:type|trait|struct|enum) `(?:[\w:]+::)?(\w+)(?:<[^`]*>)?` is more private than", log))
    names |= set(re.findall(r"`(\w+)` is only public within the crate, and cannot be re-exported", log))
    for f in sorted(src.rglob('*.rs')):
        text = f.read_text()
        new = re.sub(item.replace('^pub', r'^pub\(crate\)').replace('NAME', '|'.join(names) or 'NONE'),
                     r'pub \1 \2', text, flags=re.M)
        if new != text:
            f.write_text(new)
    print('restored', sorted(names))
    sys.exit()
for f in sorted(src.rglob('*.rs')):
    if f.name == 'main.rs' or not public_module(f):
        continue
    text = f.read_text()
    def visibility(m):
        if m.group(2) in words:
            return m.group(0)
        print('pub(crate)', '::'.join(module_of(f) + [m.group(2)]))
        return f'pub(crate) {m.group(1)} {m.group(2)}'
    new = re.sub(item.replace('NAME', r'\w+'), visibility, text, flags=re.M)
    if new != text:
        f.write_text(new)
