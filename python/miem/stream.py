"""Streaming detection for line scanners: push profiles as they arrive, get final labels and
heights back.

The labels equal those of :func:`miem.detect` on all rows pushed so far, and the heights equal
its heights up to rounding (see :class:`ProfileStream`); the work runs in the C++ core
(``miem::ProfileStream``), which allocates nothing per profile.
"""

from __future__ import annotations

import os
from typing import Any, List, NamedTuple, Optional

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from . import _core
from ._api import (Defect, _as_float_array, _check_range, _grid_defects, _params_record,
                   _threads)
from .params import DetectParams, _int, resolve_params

__all__ = ["ProfileStream", "StreamRow"]

# StatusCode values of the C++ core (miem/nothrow.hpp) that push() can return.
_OK = 0
_EMPTY_PROFILE = 6


def _check_storage(width: int, dtype: np.dtype, lag: int, reach: int, half: int,
                   edge: tuple[int, int] | None = None, wait: int = 0,
                   rays: bool = False, pooled: bool = False) -> None:
    """ValueError naming `width` when the stream's buffers (about ``lag + 2 h + 2`` profiles of
    coordinates, state, labels and heights, ``wait`` more for min_step="auto"; with the edge
    test, ``edge = (P, r)``, ``lag + 64 + 2 r + 3`` profiles and the edge test's integral
    images, README "Guarantees"; with min_step, ``rays``, 4 bytes more per kept point; with
    z_resolution="auto", ``pooled``, 16 bytes per pooled z value: at most 32 profiles and 65,536
    points) exceed half of the machine's memory, so that a typo never gets the process killed
    for memory."""
    rows = wait + max(2 * reach, 2 * half) + (
        lag + half + 3 if edge is None else max(lag + half + 3, lag + 64 + 2 * edge[1] + 3))
    need = width * rows * (3 * dtype.itemsize + 17 + (4 if rays else 0)) + (
        16 * min(32 * width, 65536) if pooled else 0)
    if edge is not None:  # (P + 1) rings of 2 r + 2 image rows of 11 moments per tile column
        P, r = edge
        cols = min(width, 128 + 2 * r)
        need += 8 * 11 * (P + 1) * (-(-width // 128)) * ((2 * r + 2) * (cols + 1) + cols)
    try:
        limit = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (AttributeError, ValueError, OSError):  # pragma: no cover - not POSIX
        limit = 1 << 34
    if need > limit:
        raise ValueError(
            f"width: a stream of {width:,} points per profile with a lag of {lag} profiles "
            f"keeps about {need / 2**30:.1f} GiB, more than half of this machine's memory "
            f"({limit / 2**30:.1f} GiB); lower max_iterations, edge_extent or window, or split "
            f"the profile")


class StreamRow(NamedTuple):
    """One finished profile.

    Attributes
    ----------
    row : int
        Row number: 0 is the first profile pushed (since construction or :meth:`reset`).
    labels : ndarray, shape (width,), uint8
        :class:`miem.Label` values of that profile's points.
    heights : ndarray, shape (width,), float64
        Local heights (as :attr:`miem.DetectResult.height`; NaN where none, and everywhere but
        the ABNORMAL points with ``heights="abnormal"``).
    defects : list of Defect
        The defects that became final with this row (:class:`miem.Defect`, as
        :attr:`miem.DetectResult.defects` holds them: no later profile can change them),
        ordered by their first point. ``indices`` and ``cells`` count rows from the first
        profile pushed; ``id`` numbers the stream's defects in the order reported (not by
        height: the stream cannot rank what it has not seen yet).
    """

    row: int
    labels: np.ndarray
    heights: np.ndarray
    defects: List[Defect]


class ProfileStream:
    """Streaming MIEM over laser profiles (rows of an organized scan), one at a time.

    Each :meth:`push` takes one profile and, once ``lag`` profiles have followed a row, hands
    that row's final labels and heights back. The labels are exactly those :func:`miem.detect`
    gives for the same rows with the same parameters, for every input; the heights equal its
    heights up to rounding (the same window planes, summed in another order). The whole
    detector runs: the angle passes, the height test with its compact EDGE groups, the edge
    test, heights, and the defects (:attr:`StreamRow.defects`: each reported once no later
    profile can change it; over a scan, the same set as :attr:`miem.DetectResult.defects`).
    The lag (docs/SPEC.md "Streaming") is::

        L = P R + E + (P + 1) h            (height test on;  L = P R + h without it)
        L = max(H + max(2 r, q), h) + (P - 1) r + h  (with the edge test; H = P R + E + P h,
                          q = max(r, h); or H = P R, q = 0 without the height test)
        L = max(L, 256)                    (with min_step, z_resolution or z_noise "auto")

    with ``R = max(scales) + max_gap`` (``+ max_reach`` with ``min_step``, a length or
    ``"auto"``) the rows one angle judgment reads, ``P = max_iterations``,
    ``E = edge_extent + max_gap`` (the rows that decide whether an EDGE group is compact),
    ``h = window // 2`` and ``r = edge_window // 2`` (the edge test's step 9 runs row by row
    ``r`` profiles behind the height passes, each edge pass ``r`` profiles behind the one
    before): (10 * 35 + 13 + 10 * 10 + 2 * 7) + 9 * 7 + 10 = 550 profiles
    with the defaults, 256 with ``min_step=None`` (230 with ``z_resolution=None`` and
    ``z_noise=None`` too),
    10 * 2 + 10 = 30 with ``preset="paper"``.
    ``min_step="auto"`` is decided on the 256 profiles from the first one with a finite point
    (docs/SPEC.md "min_step='auto'"), the value :func:`miem.detect` resolves on the same rows:
    the stream waits for them and decides it over the next pushes (48 at the defaults, each
    visiting 16 of the 256 profiles again), then catches up on their work a few profiles a
    push, so that no push carries it whole (docs/SPEC.md "Streaming"). A lower ``max_iterations``,
    ``edge_extent``, ``window`` or ``edge_window``, or a ``min_step`` length or None, shortens
    the lag;
    ``edge_tolerance=None`` takes 70 profiles off (and most of the time: bench/RESULTS.md).

    The parameters are a :class:`miem.DetectParams` as for :func:`miem.detect` (``params``, a
    ``preset`` or keyword overrides; the default, :func:`miem.default_params` ``("stream")``, is
    the default preset). The stream does not implement ``theta0="auto"`` (the median of the
    whole scan's angles, which a stream never sees: give degrees): a ValueError naming it.

    Parameters
    ----------
    width : int
        Points per profile.
    params : DetectParams or mapping, optional
        The parameters (not together with ``preset``). ``max_iterations`` is at most 254 here.
    preset : {"paper", "recommended"}, optional
        A named parameter set.
    dtype : {numpy.float64, numpy.float32}
        Storage type of the coordinates kept for the lag (computation is always float64).
        Profiles of another dtype are converted.
    num_threads : int, optional
        Threads of a push (default: all cores). Angle pass 1, an angle pass's judgments, the
        edge passes' tile columns and height pass 1's strips are split among them (one thread
        below 256 points per profile); the results never depend on the count.
    **overrides
        Fields of :class:`miem.DetectParams`.

    Attributes
    ----------
    params : DetectParams
        The parameters used.

    Raises
    ------
    ValueError
        A parameter out of range or not implemented by the stream (the message names it).

    Examples
    --------
    >>> import numpy as np, miem
    >>> stream = miem.ProfileStream(64)
    >>> for r in range(700):
    ...     profile = np.zeros((64, 3)); profile[:, 0] = np.arange(64) * 0.5; profile[:, 1] = r
    ...     if r == 10:
    ...         profile[30, 2] = 3.0                  # a burr tip
    ...     done = stream.push(profile)
    ...     if done is not None and (done.labels == miem.ABNORMAL).any():
    ...         hit = np.flatnonzero(done.labels == miem.ABNORMAL)
    ...         print(done.row, hit, done.heights[hit])
    10 [30] [3.]
    >>> stream.lag, len(stream.flush())              # the last `lag` rows
    (550, 550)
    """

    def __init__(
        self,
        width: int,
        params: Optional[DetectParams] = None,
        *,
        preset: Optional[str] = None,
        dtype: DTypeLike = np.float64,
        num_threads: Optional[int] = None,
        **overrides: Any,
    ) -> None:
        w = _int("width", width, 1)
        p, name = resolve_params(params, preset, overrides, "stream")
        core_params = p._core_grid(_threads(num_threads), "stream")
        try:
            dt = np.dtype(dtype)
        except TypeError:
            raise ValueError(f"dtype: expected float32 or float64, got {dtype!r}") from None
        if dt == np.float64:
            cls = _core.ProfileStream64
        elif dt == np.float32:
            cls = _core.ProfileStream32
        else:
            raise ValueError(f"dtype: expected float32 or float64, got {dt}")
        code, message = _core.check_stream_params(w, core_params)
        if code != _OK:
            raise ValueError(message)
        self._dtype = dt
        a, gp = p.angle, p.grid
        edge = None if gp.edge_tolerance is None else (a.max_iterations, gp.edge_window // 2)
        _check_storage(w, dt, int(_core.stream_lag(core_params)), max(a.scales) + gp.max_gap
                       + (0 if gp.min_step is None else gp.max_reach), gp.window // 2, edge,
                       304 if "auto" in (gp.min_step, gp.z_resolution, gp.z_noise) else 0,
                       # (kMsBacklog)
                       gp.min_step is not None,  # stream.hpp ray_
                       gp.z_resolution == "auto")  # stream.hpp zkeys_
        try:
            self._core = cls(w, core_params)
        except MemoryError:
            raise ValueError(f"width: cannot allocate a stream of {w:,} points per profile "
                             f"(max_iterations={a.max_iterations})") from None
        self.params = p
        self._record = _params_record(p, name, "stream")

    @property
    def width(self) -> int:
        """Points per profile."""
        return int(self._core.width)

    @property
    def lag(self) -> int:
        """Profiles between pushing a row and getting it back final (see the class)."""
        return int(self._core.lag)

    @property
    def min_step(self) -> Optional[float]:
        """The min_step the stream judges with (scan units), None when off; with
        ``min_step="auto"`` None until the 256 profiles from the first one with a finite point
        are in (or the flush), then the value :func:`miem.detect` resolves on those rows."""
        return self._core.min_step

    @property
    def z_resolution(self) -> Optional[float]:
        """The z step the height and edge tests allow for (scan units, docs/SPEC.md
        "z_resolution"), None when off; with ``z_resolution="auto"`` None until the same 256
        profiles are in (or the flush), then the value :func:`miem.detect` resolves on them."""
        return self._core.z_resolution

    @property
    def z_noise(self) -> Optional[float]:
        """The z noise sigma under which the edge test's tolerances do not go (half of them;
        scan units, docs/SPEC.md "z_noise"), None when off; with ``z_noise="auto"`` None until
        the same 256 profiles are in (or the flush), then the value :func:`miem.detect`
        resolves on them."""
        return self._core.z_noise

    @property
    def dtype(self) -> np.dtype:
        """Storage dtype of the coordinates."""
        return self._dtype

    @property
    def rows_pushed(self) -> int:
        """Profiles pushed since construction or :meth:`reset`."""
        return int(self._core.rows_pushed)

    @property
    def edge_candidates(self) -> int:
        """Cells the edge test's first pass has judged since construction or :meth:`reset`: the
        NORMAL and EDGE cells that are not quiet (docs/SPEC.md "Edge test" step 1), the edge
        test's work (its cost per profile grows with it); 0 without the edge test."""
        return int(self._core.edge_candidates)

    @property
    def finished(self) -> bool:
        """True after :meth:`flush` until :meth:`reset`."""
        return bool(self._core.finished)

    def push(self, profile: ArrayLike) -> Optional[StreamRow]:
        """Add one profile; return the row that became final, if any.

        Parameters
        ----------
        profile : array_like, shape (width, 3)
            The profile's points in scan order (any strides). Non-finite points are dropouts; a
            profile with no finite point is taken as a row of dropouts (all INVALID).

        Returns
        -------
        StreamRow or None
            ``(row, labels, heights, defects)`` of the row pushed ``lag`` profiles ago (with
            the defects it made final); None while fewer than ``lag + 1`` profiles have been
            pushed.

        Raises
        ------
        ValueError
            Wrong shape or dtype kind, or the stream was flushed (call :meth:`reset`). A rejected
            profile leaves the stream unchanged.
        """
        # native order, aligned; SPEC's coordinate range is checked by the core's push before
        # it takes the profile, here only before a conversion (which could make values inf)
        arr = _as_float_array(profile, "profile", check_range=False)
        if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] != self.width:
            raise ValueError(f"profile: expected shape ({self.width}, 3), got {arr.shape}")
        if arr.dtype != self._dtype:
            _check_range(arr, "profile", lower=False)
            arr = arr.astype(self._dtype)
        code, message, row, labels, heights, defects = self._core.push(arr)
        if code not in (_OK, _EMPTY_PROFILE):
            if "rescale" in message:  # the core's range check: say the magnitude it found
                _check_range(arr, "profile", lower=False)
            raise ValueError(message)
        if labels is None:
            return None
        return StreamRow(int(row), labels, heights, _grid_defects(defects, self.width))

    def flush(self) -> List[StreamRow]:
        """End the stream and return every row still pending, oldest first.

        The last rows are judged with the end of the stream as the border of the scan, as
        :func:`miem.detect` does. Call :meth:`reset` to start a new stream.

        Returns
        -------
        list of StreamRow
            At most ``lag`` rows (empty on a second call).
        """
        w = self.width
        return [StreamRow(int(r), labels, heights, _grid_defects(defects, w))
                for r, labels, heights, defects in self._core.flush()]

    def reset(self) -> None:
        """Start a new stream (a new part) with the same width and parameters."""
        self._core.reset()

    def __repr__(self) -> str:
        return (f"ProfileStream(width={self.width}, lag={self.lag}, dtype={self._dtype.name}, "
                f"rows_pushed={self.rows_pushed})")
