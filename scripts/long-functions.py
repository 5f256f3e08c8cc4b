#!/usr/bin/env python3
"""Long Rust functions outside tests, longest first.

    python3 scripts/long-functions.py              # every fn over 80 lines: file:line name length
    python3 scripts/long-functions.py --over 150   # another threshold
    python3 scripts/long-functions.py --max 150    # also exit 1 if any is longer than 150

A function's length is its lines from the line of `fn` to the line of its closing brace, both
counted (doc comments and attributes above it are not). The files are every `.rs` under
`crates/`, less `tests/` folders and `target/`; inside a file, an item under a `#[cfg(test)]`
attribute (a `mod tests { … }`, a helper) and a `#[test]` function are left out. Braces in
strings, raw strings, char literals and comments do not count. Nested functions are listed on
their own and also count in the one around them.
"""

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FN = re.compile(r"\bfn\s+([A-Za-z_][A-Za-z0-9_]*)")
TEST_ATTR = re.compile(r"#\[\s*(test|tokio::test|cfg\s*\((?!.*not\s*\(\s*test).*\btest\b.*\))")


def code_mask(text: str) -> str:
    """The text with comments, string and char literals blanked (newlines kept), so that
    braces, `fn` and attributes can be found by plain scanning."""
    out = list(text)
    i, n = 0, len(text)

    def blank(a: int, b: int) -> None:
        for k in range(a, min(b, n)):
            if out[k] != "\n":
                out[k] = " "

    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            blank(i, j)
            i = j
        elif text.startswith("/*", i):
            depth, j = 1, i + 2
            while j < n and depth:
                if text.startswith("/*", j):
                    depth, j = depth + 1, j + 2
                elif text.startswith("*/", j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            blank(i, j)
            i = j
        elif (m := re.compile(r'b?r(#*)"').match(text, i)) and (i == 0 or not (text[i - 1].isalnum() or text[i - 1] == "_")):
            end = '"' + m.group(1)
            j = text.find(end, m.end())
            j = n if j < 0 else j + len(end)
            blank(i, j)
            i = j
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            blank(i, j + 1)
            i = j + 1
        elif c == "'":
            # A char literal ('x', '\n', '\u{..}', '{'), else a lifetime or label.
            m = re.compile(r"'(\\(u\{[0-9a-fA-F]*\}|x[0-9a-fA-F]{2}|.)|[^\\'\n])'").match(text, i)
            if m:
                blank(i, m.end())
                i = m.end()
            else:
                i += 1
        else:
            i += 1
    return "".join(out)


def matching_brace(code: str, open_at: int) -> int:
    depth = 0
    for k in range(open_at, len(code)):
        if code[k] == "{":
            depth += 1
        elif code[k] == "}":
            depth -= 1
            if depth == 0:
                return k
    return len(code) - 1


def body_start(code: str, after: int) -> int | None:
    """The `{` that opens the body of the fn whose name ends at `after`, or None for a
    declaration without a body (`fn f();` in a trait or extern block)."""
    depth = 0  # (), [] and <> of the signature; braces in a signature are rare (const generics)
    for k in range(after, len(code)):
        ch = code[k]
        if ch in "([":
            depth += 1
        elif ch in ")]":
            depth -= 1
        elif ch == ";" and depth == 0:
            return None
        elif ch == "{" and depth == 0:
            return k
    return None


def test_spans(code: str) -> list[tuple[int, int]]:
    """Character spans of items under a test attribute."""
    spans = []
    for m in TEST_ATTR.finditer(code):
        # The item follows the attribute (and perhaps more attributes): its first `{` or `;`.
        k = m.end()
        while k < len(code) and code[k] not in "{;":
            k += 1
        if k < len(code) and code[k] == "{":
            spans.append((m.start(), matching_brace(code, k)))
    return spans


def functions(path: Path) -> list[tuple[int, str, int]]:
    text = path.read_text(encoding="utf-8", errors="replace")
    code = code_mask(text)
    tests = test_spans(code)
    line_of = lambda pos: code.count("\n", 0, pos) + 1  # noqa: E731
    found = []
    for m in FN.finditer(code):
        if any(a <= m.start() <= b for a, b in tests):
            continue
        start = body_start(code, m.end())
        if start is None:
            continue
        end = matching_brace(code, start)
        first, last = line_of(m.start()), line_of(end)
        found.append((first, m.group(1), last - first + 1))
    return found


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--over", type=int, default=80, help="list functions longer than this (default 80)")
    ap.add_argument("--max", type=int, help="exit 1 if a function is longer than this")
    args = ap.parse_args()
    rows = []
    for f in sorted((ROOT / "crates").rglob("*.rs")):
        rel = f.relative_to(ROOT)
        if "target" in rel.parts or "tests" in rel.parts:
            continue
        for line, name, length in functions(f):
            if length > args.over:
                rows.append((length, f"{rel}:{line}", name))
    rows.sort(key=lambda r: (-r[0], r[1]))
    for length, where, name in rows:
        print(f"{where} {name} {length}")
    if args.max is not None:
        too_long = [r for r in rows if r[0] > args.max]
        if too_long:
            print(f"{len(too_long)} function(s) over {args.max} lines", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
