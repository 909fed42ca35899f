"""Shared code of the atheris harnesses in this directory (see fuzz/README.md).

A reader harness writes the fuzzer's bytes to a file with the format's suffix and reads it with
:func:`miem.io.read`: it must return a well-formed :class:`~miem.io.ScanData` or raise
:class:`~miem.io.ScanFileError`. Anything else (another exception, a crash, a hang past
``-timeout``, memory past ``-rss_limit_mb``) is a finding.
"""

from __future__ import annotations

import os
import sys
import tempfile

import atheris

with atheris.instrument_imports(include=["miem", "pypcd4", "plyfile", "laspy"]):
    import miem.io
    import numpy as np


def check_scan(scan) -> None:
    pts = scan.points
    assert pts.dtype in (np.float32, np.float64) and pts.dtype.isnative, pts.dtype
    assert pts.ndim in (2, 3) and pts.shape[-1] == 3 and pts.size > 0, pts.shape
    for name, value in scan.fields.items():
        assert value.shape == pts.shape[:-1], (name, value.shape, pts.shape)
        assert value.dtype.isnative or value.dtype.itemsize == 1, (name, value.dtype)


def reader(suffix: str, fmt: str | None = None):
    """The TestOneInput of a reader harness for files ending in `suffix`."""
    fd, name = tempfile.mkstemp(suffix=suffix, prefix="miem-fuzz-")
    os.close(fd)

    def test_one_input(data: bytes) -> None:
        with open(name, "wb") as fh:
            fh.write(data)
        try:
            scan = miem.io.read(name, format=fmt)
        except miem.io.ScanFileError:
            return
        check_scan(scan)

    return test_one_input


def main(test_one_input) -> None:
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()
