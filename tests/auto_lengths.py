"""Checks shared by the tests of the lengths "auto" measures on the sample rows (z_resolution,
z_noise): the core is the reference, the stream decides them as batch does, miem.dask resolves
them as batch does."""

from __future__ import annotations

import miem
import numpy as np
import pytest
from miem import _core
from miem import reference as ref
from miem.params import resolve_params
from stream_batch import stream_labels


def assert_core_is_reference(g: np.ndarray, **kw) -> None:
    """miem.detect's labels are the reference's for these overrides: 1 and 2 threads, and the
    grid as float32."""
    oracle = ref.detect(g, **kw)
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect(g, num_threads=nt, **kw).labels, oracle.labels)
    f32 = g.astype(np.float32)
    np.testing.assert_array_equal(miem.detect(f32, **kw).labels, ref.detect(f32, **kw).labels)


def assert_stream_measures(g: np.ndarray, kw: dict, name: str) -> miem.DetectResult:
    """With the stream's defaults and the overrides `kw`, on a scan with one spike: the stream's
    labels are batch's (one ABNORMAL cell), and its property `name` is None until the 256
    sample rows are in, then batch's value; None when off, a given length as given. Returns
    batch's result."""
    p, _ = resolve_params(miem.default_params("stream"), None, kw, "stream")
    batch = miem.detect(g, params=p)
    assert (batch.labels == miem.ABNORMAL).sum() == 1
    np.testing.assert_array_equal(stream_labels(g, p), batch.labels)
    want = batch.params[name]
    s = miem.ProfileStream(g.shape[1], params=p)
    assert s.lag >= 256  # it waits for the rows it measures on
    for row in g[:255]:
        s.push(row)
    assert getattr(s, name) is None  # not decided yet
    for row in g[255:]:
        s.push(row)
    list(s.flush())  # decided by then (else over the pushes after the 256 rows)
    assert getattr(s, name) == want
    assert getattr(miem.ProfileStream(8, **{name: None}), name) is None
    assert getattr(miem.ProfileStream(8, **{name: 0.02}), name) == 0.02
    return batch


def assert_dask_resolves(g: np.ndarray, name: str) -> None:
    """miem.dask.auto_<name> and miem.dask.detect resolve `name` as miem.detect does, and the
    labels are batch's."""
    mdask = pytest.importorskip("miem.dask")
    import dask
    import dask.array as da

    want = miem.detect(g)
    arr = da.from_array(g, chunks=(128, 64, 3))
    with dask.config.set(scheduler="sync"):
        assert getattr(mdask, f"auto_{name}")(arr) == want.params[name]
        res = mdask.detect(arr)
        labels = res.labels.compute()
    assert res.params[f"{name}_auto"] and res.params[name] == want.params[name]
    np.testing.assert_array_equal(labels, want.labels)


def assert_given_none_and_bad(g: np.ndarray, name: str) -> None:
    """The length "auto" measured, given as a length, gives the same labels (and records it as
    given); the paper preset has None; bad values and a length with the C++ `_auto` flag on are
    refused, naming the field."""
    auto = miem.detect(g)
    given = miem.detect(g, **{name: auto.params[name]})
    np.testing.assert_array_equal(given.labels, auto.labels)
    assert not given.params[f"{name}_auto"]
    assert miem.detect(g, preset="paper").params[name] is None
    for bad in (-0.01, float("nan"), "often", [0.01]):
        with pytest.raises(ValueError, match=name):
            miem.detect(g, **{name: bad})
    p = _core.DetectParams()
    setattr(p, name, 0.01)  # a length with the _auto flag still on
    code, msg = p.check()
    assert code != 0 and msg.startswith(name)
    with pytest.raises(ValueError, match=name):
        _core.detect_organized(g, p)
