"""Fuzz miem.io.read on .las files (see fuzz/README.md)."""

import _harness

if __name__ == "__main__":
    _harness.main(_harness.reader(".las"))
