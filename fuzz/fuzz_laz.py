"""Fuzz miem.io.read on .laz files (see fuzz/README.md)."""

import _harness

if __name__ == "__main__":
    _harness.main(_harness.reader(".laz"))
