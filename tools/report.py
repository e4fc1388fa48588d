"""Shared by the benchmarks: replace one tool's section of a markdown report in place."""

from __future__ import annotations

from pathlib import Path


def replace_section(path: Path, name: str, body: str) -> None:
    """Put ``body`` between ``<!-- name:start -->`` and ``<!-- name:end -->`` of ``path``.

    The rest of the file (hand-written text, other tools' sections) is kept; a missing section is
    appended. Written atomically.
    """
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    old = path.read_text(encoding="utf-8") if path.is_file() else ""
    block = f"{start}\n{body.rstrip()}\n{end}\n"
    if start in old and end in old:
        rest = old[old.index(end) + len(end):]
        new = old[:old.index(start)] + block + (rest[1:] if rest.startswith("\n") else rest)
    else:
        new = (old.rstrip("\n") + "\n\n" if old.strip() else "") + block
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(new, encoding="utf-8")
    tmp.replace(path)
