"""The code blocks of README.md that a user runs as written, found by their markers.

A block is marked by an HTML comment on the line before its fence::

    <!-- snippet: quickstart -->
    ```python
    ...
    ```

Several blocks may share a name; they run in README order (a ``sh`` block, then the ``python``
block that uses its output). ``console`` blocks are sessions: lines starting with ``$ `` are
commands, the lines after each, up to the next command, are what it printed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

_MARK = re.compile(r"^<!--\s*snippet:\s*([\w-]+)\s*-->\s*$")
_FENCE = re.compile(r"^```(\w*)\s*$")


@dataclass(frozen=True)
class Block:
    name: str
    lang: str
    code: str
    line: int  # 1-based line of the opening fence in README.md


def blocks(name: str | None = None, path: Path = README) -> list[Block]:
    """The marked blocks (all, or those called `name`), in README order."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        m = _MARK.match(lines[i])
        if m and i + 1 < len(lines) and _FENCE.match(lines[i + 1]):
            lang = _FENCE.match(lines[i + 1]).group(1)
            j = i + 2
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            if m.group(1) == name or name is None:
                out.append(Block(m.group(1), lang, "\n".join(lines[i + 2:j]) + "\n", i + 2))
            i = j
        i += 1
    return out


def session(block: Block) -> list[tuple[str, list[str]]]:
    """A console block as (command, printed lines) pairs."""
    out: list[tuple[str, list[str]]] = []
    for line in block.code.splitlines():
        if line.startswith("$ "):
            out.append((line[2:], []))
        elif out and line.strip():
            out[-1][1].append(line)
    return out
