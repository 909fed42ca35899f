"""Write README.md's command-line session from a real run of its commands.

    python docs/readme_session.py          # rewrite the block marked 'snippet: cli-session'
    python docs/readme_session.py --check  # exit 1 when README.md differs from a fresh run

The commands run in a temporary directory with the ``miem`` of this interpreter's environment;
their output (stdout and stderr, as a terminal shows them) replaces the session in README.md.
tests/test_readme.py runs the same commands and compares, but for the timing columns.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MARK = "<!-- snippet: cli-session -->"

COMMANDS = [
    "miem simulate paper -o paper.pcd",
    "miem simulate scan --surface flange --shape 300 400 --step 0.2 --noise 0.03 "
    "--defects spike=4,cluster=2,ridge_across=1,spatter=2 --seed 3 -o part.ply",
    "miem detect paper.pcd part.ply -o out",
    "ls out",
    "head -3 out/part.defects.csv",
    "miem fit paper.pcd",
    "miem plot part.ply -o part.png",
    "miem detect part.png -o out; echo \"exit $?\"",
]


def run(workdir: Path) -> str:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["MPLBACKEND"] = "Agg"
    lines = []
    for i, cmd in enumerate(COMMANDS):
        proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], cwd=workdir, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"readme_session: `{cmd}` failed:\n{proc.stdout}")
        if i:
            lines.append("")
        lines.append(f"$ {cmd}")
        lines += [ln for ln in proc.stdout.splitlines() if ln.strip()]
    return "\n".join(lines) + "\n"


def replace(text: str, session: str) -> str:
    head, sep, rest = text.partition(MARK + "\n")
    if not sep:
        raise SystemExit(f"readme_session: README.md has no line {MARK!r}")
    fence, nl, rest = rest.partition("\n")
    if not fence.startswith("```"):
        raise SystemExit("readme_session: the marker must stand right before a fence")
    _, end, tail = rest.partition("```\n")
    if not end:
        raise SystemExit("readme_session: the session block is not closed")
    return head + sep + fence + nl + session + "```\n" + tail


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare only")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        session = run(Path(tmp))
    text = README.read_text(encoding="utf-8")
    new = replace(text, session)
    if args.check:
        return 0 if new == text else 1
    README.write_text(new, encoding="utf-8")
    print(f"README.md: session of {len(COMMANDS)} commands written")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
