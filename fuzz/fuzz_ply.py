"""Fuzz miem.io.read on .ply files (see fuzz/README.md)."""

import _harness

if __name__ == "__main__":
    _harness.main(_harness.reader(".ply"))
