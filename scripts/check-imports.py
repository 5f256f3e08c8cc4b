#!/usr/bin/env python3
"""Import circles between the files of each crate: fails on a new one.

    python3 scripts/check-imports.py            # check (the test command runs it)
    python3 scripts/check-imports.py --list     # every circle now, in the allow file's format

Each `.rs` file under `crates/*/src` is a module; a file that names `crate::a::b…` (in a `use`
tree or a path in code) or `super::…` depends on the deepest module file that path reaches.
Two files depend on each other, directly or round a longer loop, when they lie in one strongly
connected component of that graph: a circle. Not counted: a module's own descendants and
ancestors (a `mod.rs` and the files it declares are one room), and the crate root (`lib.rs`,
`main.rs`: its `mod` lines and re-exports are the crate's table of contents).

`scripts/import-cycles.allow` lists the circles the code has today, one per line (the crate,
then its files sorted, space-separated). A circle that is not within one listed is an error;
a listed one that is gone or smaller is reported, to tighten the list.
"""

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ALLOW = ROOT / "scripts" / "import-cycles.allow"
IDENT = r"[A-Za-z_][A-Za-z0-9_]*"


def strip_comments_and_strings(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r'r#*"(?:.|\n)*?"#*', '""', text)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text)
    return re.sub(r"//[^\n]*", "", text)


def module_files(src: Path) -> dict[tuple[str, ...], Path]:
    """Module path (crate-relative segments) -> file, for every .rs file of a crate's src."""
    mods = {}
    for f in sorted(src.rglob("*.rs")):
        rel = f.relative_to(src).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "mod":
            parts = parts[:-1]
        if parts in (["lib"], ["main"]):
            continue  # the crate root
        if "bin" in parts[:1]:
            continue  # separate binaries are crates of their own
        mods[tuple(parts)] = f
    return mods


def use_paths(tree: str, prefix: list[str]) -> list[list[str]]:
    """The paths of a `use` tree: `a::{b, c::d}` -> [a::b, a::c::d] (globs and `self` end a path)."""
    tree = tree.strip()
    out = []
    depth, start, parts = 0, 0, []
    if "{" in tree:
        head, _, rest = tree.partition("{")
        body = rest[: rest.rfind("}")]
        head_segs = [s for s in head.split("::") if s.strip()]
        for i, ch in enumerate(body + ","):
            if ch == "{":
                depth += 1
            elif ch == "}":
                depth -= 1
            elif ch == "," and depth == 0:
                parts.append(body[start:i])
                start = i + 1
        for p in parts:
            if p.strip():
                out += use_paths(p, prefix + [s.strip() for s in head_segs])
        return out
    segs = [s.strip() for s in tree.split(" as ")[0].split("::") if s.strip()]
    segs = [s for s in segs if s not in ("self", "*")]
    return [prefix + segs]


def references(text: str, me: tuple[str, ...]) -> list[list[str]]:
    """Crate-relative paths named by a file whose module is `me`."""
    paths = []
    for m in re.finditer(r"\buse\s+((?:crate|super|self)\s*::[^;]*);", text):
        paths += use_paths(m.group(1), [])
    for m in re.finditer(rf"\b(?:crate|super)(?:\s*::\s*{IDENT})+", text):
        paths.append([s.strip() for s in m.group(0).split("::")])
    out = []
    for p in paths:
        if not p:
            continue
        if p[0] == "crate":
            out.append(p[1:])
        elif p[0] in ("super", "self"):
            base = list(me)
            while p and p[0] in ("super", "self"):
                if p[0] == "super":
                    base = base[:-1]
                p = p[1:]
            out.append(base + p)
    return out


def graph(crate: Path) -> tuple[dict, dict]:
    mods = module_files(crate / "src")
    edges = {m: set() for m in mods}
    for me, f in mods.items():
        # A file named mod.rs is the module itself; its `super` is its parent.
        text = strip_comments_and_strings(f.read_text(encoding="utf-8", errors="replace"))
        for path in references(text, me):
            target = None
            for k in range(len(path), 0, -1):
                if tuple(path[:k]) in mods:
                    target = tuple(path[:k])
                    break
            if target is None or target == me:
                continue
            # Ancestors and descendants are one room.
            if target[: len(me)] == me or me[: len(target)] == target:
                continue
            edges[me].add(target)
    return mods, edges


def components(edges: dict) -> list[list]:
    """Strongly connected components of more than one node (Tarjan, iterative)."""
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = [0]
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            node, it = work[-1]
            advanced = False
            for nxt in it:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter[0]
                    counter[0] += 1
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(sorted(edges[nxt]))))
                    advanced = True
                    break
                if nxt in on:
                    low[node] = min(low[node], index[nxt])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == node:
                        break
                if len(comp) > 1:
                    out.append(comp)
    return out


def circles() -> list[tuple[str, list[str]]]:
    found = []
    for crate in sorted((ROOT / "crates").iterdir()):
        if not (crate / "src").is_dir():
            continue
        mods, edges = graph(crate)
        for comp in components(edges):
            files = sorted(str(mods[m].relative_to(crate / "src")) for m in comp)
            found.append((crate.name, files))
    return found


def main() -> int:
    now = circles()
    if "--list" in sys.argv:
        for crate, files in now:
            print(crate, " ".join(files))
        return 0
    allowed = []
    if ALLOW.exists():
        for line in ALLOW.read_text(encoding="utf-8").splitlines():
            line = line.split("#", 1)[0].split()
            if line:
                allowed.append((line[0], set(line[1:])))
    bad = [(c, f) for c, f in now if not any(c == ac and set(f) <= af for ac, af in allowed)]
    for crate, files in bad:
        print(f"check-imports: a new import circle in crates/{crate}/src: {' <-> '.join(files)}", file=sys.stderr)
    for ac, af in allowed:
        if not any(c == ac and set(f) == af for c, f in now):
            print(f"check-imports: the listed circle in crates/{ac} ({' '.join(sorted(af))}) is gone or smaller: "
                  f"update {ALLOW.relative_to(ROOT)} (python3 scripts/check-imports.py --list)")
    total = sum(len(f) for _, f in now)
    print(f"check-imports: {len(now)} circles ({total} files) in {len(allowed)} listed; {len(bad)} new")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
