"""The detector configuration, defined once per scope: fields, defaults, units, help, presets.

:class:`DetectParams` mirrors the C++ parameter types of ``cpp/include/miem/params.hpp`` in the
user's spelling (``theta0="auto"``, ``height_tolerance="4.5rms"``, ``None`` for "off"), one
part per scope: ``angle`` (:class:`AngleParams`, the angle test shared by every detector),
``grid`` (:class:`GridParams`, organized grids: batch and stream) and ``cloud``
(:class:`CloudParams`, unorganized clouds). Each field carries its default, unit and help text;
a detector reads ``angle`` and its own part, and a keyword override names a field of those parts
(``miem.detect(grid, window=15)``, ``miem.detect(points, radius=2.0)``); a field of another part
is refused with a ValueError naming it. ``ProfileStream`` refuses ``min_step="auto"`` (it
needs the whole scan; give the length a first scan resolves).
The command line's detection options, ``--config`` files and ``miem config`` are generated from
these fields.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Tuple, Union

from . import _core

__all__ = [
    "AngleParams",
    "GridParams",
    "CloudParams",
    "DetectParams",
    "PRESETS",
    "CLOUD_PRESETS",
    "DEFAULT_PRESET",
    "PATHS",
    "default_params",
    "resolve_params",
    "load_config",
    "dump_config",
]

#: The detectors: organized batch detection, the profile stream, unorganized clouds.
PATHS = ("grid", "stream", "cloud")
#: The parts of DetectParams each detector reads.
_PARTS = {"grid": ("angle", "grid"), "stream": ("angle", "grid"), "cloud": ("angle", "cloud")}
_WHAT = {"grid": "organized grids (H, W, 3)", "stream": "ProfileStream",
         "cloud": "unorganized clouds (N, 3)"}


# ---------------------------------------------------------------------------------------------
# value checks (the user's spelling; ranges are the core's check())


def _int(name: str, value: object, minimum: int, maximum: int = 2**30) -> int:
    import numpy as np

    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    v = int(value)
    if v < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {v}")
    if v > maximum:
        raise ValueError(f"{name}: expected an integer in {minimum}..{maximum}, got {v}")
    return v


def _real(name: str, value: object) -> float:
    import numpy as np

    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}: expected a real number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name}: must be finite, got {v}")
    return v


def _positive(name: str, value: object) -> float:
    v = _real(name, value)
    if not v > 0.0:
        raise ValueError(f"{name}: expected a length > 0, got {v}")
    return v


def _scales_tuple(value: object) -> Tuple[int, ...]:
    import numpy as np

    if isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)):
        value = (value,)
    if isinstance(value, (str, bytes)):
        raise ValueError(f"scales: expected integers >= 1, got {value!r}")
    try:
        out = tuple(_int("scales", s, 1) for s in value)  # type: ignore[union-attr]
    except TypeError:
        raise ValueError(f"scales: expected integers >= 1, got {value!r}") from None
    if not out:
        raise ValueError("scales: must contain at least one scale")
    return out


def _height_mode(value: object) -> Any:
    if value == "all":
        return _core.HeightMode.ALL
    if value == "abnormal":
        return _core.HeightMode.ABNORMAL
    raise ValueError(f"heights: expected 'all' or 'abnormal', got {value!r}")


_RMS = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*rms\s*$")


def _height_tolerance(value: object) -> Tuple[float, float]:
    """(absolute, k_rms) from None, a length or a '<k>rms' string; 0 means off."""
    if value is None:
        return 0.0, 0.0
    if isinstance(value, str):
        m = _RMS.match(value)
        if not m or not float(m.group(1)) > 0 or not math.isfinite(float(m.group(1))):
            raise ValueError(
                f"height_tolerance: expected a length > 0, '<k>rms' with k > 0 (e.g. '4rms') "
                f"or None, got {value!r}")
        return 0.0, float(m.group(1))
    v = _real("height_tolerance", value)
    if not v > 0:
        raise ValueError(f"height_tolerance: expected a length > 0, got {v}")
    return v, 0.0


def _raise_unless_ok(status: Tuple[int, str]) -> None:
    code, message = status
    if code != 0:
        raise ValueError(message)


def _f(default: Any, unit: str, help: str, metavar: str, stream: Any = dataclasses.MISSING,
       stream_refuses: Any = dataclasses.MISSING) -> Any:
    """A field with its unit, help text and command-line metavar; ``stream``: the only value
    ProfileStream accepts (a grid field it does not implement yet), or with ``stream_refuses``:
    the stream's default, and the one value the stream refuses."""
    meta: Dict[str, Any] = {"unit": unit, "help": help, "metavar": metavar}
    if stream is not dataclasses.MISSING:
        meta["stream"] = stream
    if stream_refuses is not dataclasses.MISSING:
        meta["stream_refuses"] = stream_refuses
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class AngleParams:
    """The angle test and its iteration, shared by grids, the stream and clouds."""

    theta0: Union[float, str] = _f(
        90.0, "deg", "angle threshold: a direction is flagged when the interior angle at the "
        "point is at most theta0 (0 < theta0 < 180); 'auto' derives it from the scan's angle "
        "statistics (grids only)", "DEG")
    scales: Tuple[int, ...] = _f(
        (1, 2), "cells", "neighbour distances: (1, 2) also finds defects two points wide (on "
        "clouds: the s-th point along a direction)", "N")
    min_directions: Optional[int] = _f(
        None, "directions", "flagged directions needed for ABNORMAL, 1-4 (clouds: 1-K); None: "
        "all available directions", "N")
    max_iterations: int = _f(
        10, "passes", "maximum detection passes; each pass removes the points found and judges "
        "the rest again (and at most as many height passes)", "N")

    def __post_init__(self) -> None:
        object.__setattr__(self, "scales", _scales_tuple(self.scales))


@dataclass(frozen=True)
class GridParams:
    """Organized grids only (batch detection and ProfileStream)."""

    max_gap: int = _f(
        1, "cells", "missing or removed cells that may be skipped to reach a neighbour", "CELLS")
    min_step: Union[None, float, str] = _f(
        "auto", "length", "minimum neighbour distance in the scan's units, so that every "
        "direction sees the same physical scale; 'auto': from the scan's spacing and profile "
        "noise (SPEC \"min_step='auto'\"; result.params holds the value used; ProfileStream "
        "needs a length); None: off", "LENGTH|auto", stream=None, stream_refuses="auto")
    max_reach: int = _f(
        32, "cells", "with min_step: how many cells beyond scale + max_gap the neighbour search "
        "may go", "CELLS")
    window: int = _f(
        21, "cells", "side of the square (odd) whose NORMAL points give the local plane for "
        "heights and the height test", "CELLS")
    heights: str = _f(
        "all", "", "which points get a height: 'all' finite points or only 'abnormal' ones "
        "(faster)", "{all,abnormal}")
    height_tolerance: Union[None, float, str] = _f(
        "4.5rms", "length or k x rms", "height test (beyond the paper): a NORMAL point "
        "farther than this from its local plane becomes ABNORMAL; a length or '<k>rms' (k times "
        "the plane's rms); None: off", "LENGTH|Krms")
    edge_extent: int = _f(
        12, "cells", "with the height test: EDGE groups whose bounding box is at most this long "
        "are compact (a defect's halo) and height-tested too; longer ones are feature lines",
        "CELLS")
    edge_tolerance: Optional[float] = _f(
        4.0, "k x rms", "edge test (SPEC 'Edge test', beyond the paper, after the height test): "
        "a point standing proud of a feature line or the scan's outline by more than k times "
        "the rms of its one-sided sub-window plane becomes ABNORMAL; None: off", "K")
    edge_window: int = _f(
        15, "cells", "with the edge test: side of its one-sided sub-windows (odd >= 3)", "CELLS")


@dataclass(frozen=True)
class CloudParams:
    """Unorganized clouds only."""

    radius: Optional[float] = _f(
        None, "length", "neighbourhood radius; None: 5 x the median point spacing", "LENGTH")
    K: int = _f(4, "directions", "tangent-plane directions tested, 2-8", "N")
    min_step: Optional[float] = _f(
        None, "length", "shortest tangent-plane offset of a neighbour; None: 0.5 x the point "
        "spacing", "LENGTH")
    link: Optional[float] = _f(
        None, "length", "ABNORMAL points this close belong to one defect; None: radius", "LENGTH")
    heights: str = _f(
        "all", "", "which points get a height: 'all' finite points or only 'abnormal' ones "
        "(faster)", "{all,abnormal}")
    height_tolerance: Union[None, float, str] = _f(
        "7rms", "length or k x rms", "height test: a NORMAL point farther than this from the "
        "plane of its surroundings (beyond radius, within height_radius) becomes ABNORMAL; a "
        "length or '<k>rms'; None: off", "LENGTH|Krms")
    edge_extent: float = _f(
        12.0, "spacings", "with the height test: EDGE groups at most this many spacings across "
        "are compact and height-tested too", "SPACINGS")
    min_group: int = _f(
        40, "points", "0 (off) or >= 3: groups of usable points (linked within radius) smaller "
        "than this are ABNORMAL (floating clusters)", "N")
    height_radius: Optional[float] = _f(
        None, "length", "radius of the height planes; None: 2 x radius", "LENGTH")
    merge_distance: float = _f(
        0.0, "length", "duplicate points: rows this close (0: equal coordinates) are one point, "
        "detected once and labelled alike", "LENGTH")
    spacing: Optional[float] = _f(
        None, "length", "the cloud's point spacing, the unit of the defaults and of edge_extent; "
        "None: the median nearest-neighbour distance", "LENGTH")
    edge_tolerance: Optional[float] = _f(
        4.0, "k x rms", "edge test (SPEC 'Unorganized clouds: edge test', after the height "
        "test): a point standing proud of a feature line or the cloud's outline "
        "by more than k times the rms of a one-sided sector's plane becomes ABNORMAL (4: "
        "chosen on the held-out-style clouds' tune split); None: off", "K")
    edge_radius: Optional[float] = _f(
        None, "length", "with the edge test: radius of its sectors; None: height_radius",
        "LENGTH")
    isolated_tolerance: Optional[float] = _f(
        5.0, "k x rms", "with the height test (either tolerance): a point alone farther than "
        "k times the rms of "
        "its surroundings plane, whose neighbours within radius lie about that plane as loosely "
        "as the rms says (a low spike or pit one point wide), becomes ABNORMAL; None: off", "K")


_PART_TYPES = {"angle": AngleParams, "grid": GridParams, "cloud": CloudParams}


@dataclass(frozen=True)
class DetectParams:
    """Detection parameters: ``angle``, ``grid`` and ``cloud`` parts. The defaults are the
    recommended preset, the best measured configuration (``bench/accuracy``);
    ``PRESETS["paper"]`` is the paper's method exactly.

    Build one from a preset (``PRESETS["paper"].replace(window=15)``), from parts
    (``DetectParams(angle=AngleParams(theta0=80))``) or from a file (:func:`load_config`).
    Values are checked when a detector uses them (:meth:`check`), with a ValueError naming the
    field. ``DetectParams.fields(path)`` lists the fields a detector reads, with unit and help.
    """

    angle: AngleParams = field(default_factory=AngleParams)
    grid: GridParams = field(default_factory=GridParams)
    cloud: CloudParams = field(default_factory=CloudParams)

    # -- fields ---------------------------------------------------------------------------

    @staticmethod
    def fields(path: str = "grid") -> Dict[str, Dict[str, Any]]:
        """Field name -> ``{"default", "unit", "help", "metavar", "part", ...}`` for the fields
        detector ``path`` reads (``angle`` and its own part)."""
        out: Dict[str, Dict[str, Any]] = {}
        for part in _parts(path):
            for f in dataclasses.fields(_PART_TYPES[part]):
                out[f.name] = {"default": f.default, "part": part, **f.metadata}
        return out

    def flat(self, path: str = "grid") -> Dict[str, Any]:
        """The values detector ``path`` reads, by field name."""
        out: Dict[str, Any] = {}
        for part in _parts(path):
            out.update(dataclasses.asdict(getattr(self, part)))
        return out

    # -- construction ---------------------------------------------------------------------

    def replace(self, **overrides: Any) -> "DetectParams":
        """A copy with fields changed, by name, in every part that has the field
        (``height_tolerance`` sets the grids' and the clouds'); an unknown name is a
        ValueError."""
        return self._replace(overrides, ("angle", "grid", "cloud"))

    def for_path(self, path: str, **overrides: Any) -> "DetectParams":
        """A copy with fields of ``angle`` and ``path``'s part changed; a field of another part
        is a ValueError (the detector would not use it)."""
        return self._replace(overrides, _parts(path), path)

    def _replace(self, overrides: Mapping[str, Any], parts: Tuple[str, ...],
                 path: Optional[str] = None) -> "DetectParams":
        changes: Dict[str, Dict[str, Any]] = {part: {} for part in parts}
        for name, value in overrides.items():
            owners = [part for part in parts if name in _names(part)]
            if not owners:
                others = [part for part in _PART_TYPES if name in _names(part)]
                if others and path is not None:
                    raise ValueError(
                        f"{name}: does not apply to {_WHAT[path]} (a field of the "
                        f"{' and '.join(others)} part), so it is refused")
                raise ValueError(f"{name}: unknown detection parameter; expected one of "
                                 f"{', '.join(_all_names())}")
            for part in owners:
                changes[part][name] = value
        new = {part: dataclasses.replace(getattr(self, part), **kw)
               for part, kw in changes.items() if kw}
        return dataclasses.replace(self, **new) if new else self

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], base: Optional["DetectParams"] = None
                  ) -> "DetectParams":
        """``base`` (default: the defaults) changed by ``values``: parts as tables
        (``{"angle": {...}, "grid": {...}}``, as :meth:`to_dict` writes) and/or fields by name
        (set in every part that has them)."""
        p = cls() if base is None else base
        flat = {}
        for key, value in values.items():
            if key in _PART_TYPES and isinstance(value, Mapping):
                p = p._replace(dict(value), (key,))
            else:
                flat[key] = value
        return p.replace(**flat)

    def to_dict(self) -> Dict[str, Dict[str, Any]]:
        """``{"angle": {...}, "grid": {...}, "cloud": {...}}``, JSON-ready."""
        out = {part: dataclasses.asdict(getattr(self, part)) for part in _PART_TYPES}
        out["angle"]["scales"] = list(out["angle"]["scales"])
        return out

    # -- checks and conversion to the core ------------------------------------------------

    def check(self, path: str = "grid") -> None:
        """Raise ValueError (naming the field) unless detector ``path`` can run these values."""
        if path == "cloud":
            self._core_cloud(0)
        elif path == "stream":
            _raise_unless_ok(_core.check_stream_params(1, self._core_grid(0, path)))
        else:
            self._core_grid(0, path)

    def _reject_unhonoured(self, path: str) -> None:
        bad = []
        if path != "grid" and isinstance(self.angle.theta0, str):
            bad.append((f"theta0={self.angle.theta0!r}", "theta0=<degrees>"))
        if path == "stream":
            for name, meta in DetectParams.fields("grid").items():
                if "stream" not in meta:
                    continue
                value = getattr(self.grid, name)
                if "stream_refuses" in meta:
                    if value == meta["stream_refuses"]:
                        raise ValueError(
                            f"{name}={value!r}: ProfileStream cannot resolve it (it takes "
                            f"medians over the whole scan, which a stream never sees); give a "
                            f"length or None: the value miem.detect(first_scan).params"
                            f"[{name!r}] resolves on a first scan of the part (C++: "
                            f"miem::auto_min_step)")
                elif value != meta["stream"]:
                    bad.append((f"{name}={value!r}", f"{name}={meta['stream']!r}"))
        if bad:
            raise ValueError(
                f"{', '.join(b[0] for b in bad)}: not implemented for {_WHAT[path]} yet; the "
                f"field would be ignored, so it is refused (use {', '.join(b[1] for b in bad)})")

    def _core_angle(self, core: Any) -> None:
        a = self.angle
        if isinstance(a.theta0, str):
            if a.theta0 != "auto":
                raise ValueError(f"theta0: expected degrees or 'auto', got {a.theta0!r}")
            core.theta0_auto = True
            core.theta0_deg = 90.0
        else:
            core.theta0_deg = _real("theta0", a.theta0)
        core.scales = list(a.scales)
        md = a.min_directions
        core.min_directions = 0 if md is None else _int("min_directions", md, 1)
        core.max_iterations = _int("max_iterations", a.max_iterations, 1)

    def _core_grid(self, num_threads: int, path: str = "grid") -> Any:
        """The C++ ``miem::DetectParams`` for an organized grid (or a stream), checked."""
        self._reject_unhonoured(path)
        g = self.grid
        p = _core.DetectParams()
        self._core_angle(p)
        p.max_gap = _int("max_gap", g.max_gap, 0)
        p.min_step_auto = isinstance(g.min_step, str)
        if p.min_step_auto and g.min_step != "auto":
            raise ValueError(f"min_step: expected a length >= 0, 'auto' or None, got {g.min_step!r}")
        p.min_step = -1.0 if g.min_step is None or p.min_step_auto else _length0("min_step",
                                                                                  g.min_step)
        p.max_reach = _int("max_reach", g.max_reach, 1)
        p.window = _int("window", g.window, 3)
        p.height_mode = _height_mode(g.heights)
        p.height_abs, p.height_k = _height_tolerance(g.height_tolerance)
        p.edge_extent = _int("edge_extent", g.edge_extent, 0)
        if g.edge_tolerance is None:
            p.edge_k = 0.0
        else:
            p.edge_k = _real("edge_tolerance", g.edge_tolerance)
            if not p.edge_k > 0.0:
                raise ValueError(
                    f"edge_tolerance: expected None (off) or a number > 0, got {p.edge_k}")
        p.edge_window = _int("edge_window", g.edge_window, 3)
        if p.edge_window % 2 == 0:
            raise ValueError(f"edge_window: expected an odd integer >= 3, got {p.edge_window}")
        p.num_threads = num_threads
        _raise_unless_ok(p.check())
        return p

    def _core_cloud(self, num_threads: int) -> Any:
        """The C++ ``miem::PointsDetectParams`` for an unorganized cloud, checked."""
        self._reject_unhonoured("cloud")
        c = self.cloud
        p = _core.PointsDetectParams()
        self._core_angle(p)
        p.num_directions = _int("K", c.K, 2, 8)
        p.radius = None if c.radius is None else _positive("radius", c.radius)
        p.link = None if c.link is None else _positive("link", c.link)
        p.min_step = None if c.min_step is None else _length0("min_step", c.min_step)
        if p.min_directions > p.num_directions:
            raise ValueError(
                f"min_directions: expected 1..K={p.num_directions} or None, got {p.min_directions}")
        p.height_mode = _height_mode(c.heights)
        p.height_abs, p.height_k = _height_tolerance(c.height_tolerance)
        extent = _real("edge_extent", c.edge_extent)
        if extent < 0:
            raise ValueError(f"edge_extent: expected a number of spacings >= 0, got {extent}")
        p.edge_extent = extent
        group = _int("min_group", c.min_group, 0)
        if 0 < group < 3:
            raise ValueError(f"min_group: expected 0 (off) or an integer >= 3, got {group}")
        p.min_group = group
        p.height_radius = (None if c.height_radius is None
                           else _positive("height_radius", c.height_radius))
        p.merge_distance = _length0("merge_distance", c.merge_distance)
        p.spacing = None if c.spacing is None else _positive("spacing", c.spacing)
        p.edge_k = 0.0 if c.edge_tolerance is None else _positive("edge_tolerance",
                                                                  c.edge_tolerance)
        p.edge_radius = (None if c.edge_radius is None
                         else _positive("edge_radius", c.edge_radius))
        p.isolated_k = (0.0 if c.isolated_tolerance is None
                        else _positive("isolated_tolerance", c.isolated_tolerance))
        p.num_threads = num_threads
        _raise_unless_ok(p.check())
        return p


def _parts(path: str) -> Tuple[str, ...]:
    if path not in _PARTS:
        raise ValueError(f"path: expected one of {', '.join(PATHS)}, got {path!r}")
    return _PARTS[path]


def _names(part: str) -> Tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(_PART_TYPES[part]))


def _all_names() -> Tuple[str, ...]:
    return tuple(dict.fromkeys(n for part in _PART_TYPES for n in _names(part)))


def _length0(name: str, value: object) -> float:
    v = _real(name, value)
    if v < 0:
        raise ValueError(f"{name}: expected a length >= 0 or None, got {v}")
    return v


# ---------------------------------------------------------------------------------------------
# presets and defaults

#: Named parameter sets (parameter objects). ``"paper"`` is the paper's method exactly (on
#: clouds too: no height test, no floating groups). ``"recommended"`` is the default: its grid
#: values were chosen on the tuning split of the accuracy benchmark
#: (``bench/accuracy/recommended.json``; ``min_step``, ``edge_tolerance`` and ``edge_window``
#: by ``bench/accuracy/edges.py --tune``; test-split scores in ``bench/accuracy/RESULTS.md`` and
#: ``results_edges.md``), its cloud values on the tuning split of the held-out-style cloud
#: scenes (``bench/accuracy/clouds.py``).
PRESETS: Dict[str, DetectParams] = {
    "paper": DetectParams(
        angle=AngleParams(theta0=75.0, scales=(1,)),
        grid=GridParams(min_step=None, height_tolerance=None, edge_extent=0,
                        edge_tolerance=None),
        cloud=CloudParams(height_tolerance=None, edge_extent=0.0, min_group=0,
                          isolated_tolerance=None, edge_tolerance=None),
    ),
    "recommended": DetectParams(),
}

#: The cloud-only values of each preset that differ between presets (a view of PRESETS).
CLOUD_PRESETS: Dict[str, Dict[str, Any]] = {
    name: {k: getattr(p.cloud, k)
           for k in ("height_tolerance", "edge_extent", "min_group", "edge_tolerance",
                     "isolated_tolerance")}
    for name, p in PRESETS.items()
}

#: The preset used when neither ``params`` nor ``preset`` is given.
DEFAULT_PRESET = "recommended"


def default_params(path: str = "grid") -> DetectParams:
    """The default parameters of a detector: the default preset, except that ``"stream"``
    has ``min_step=None`` instead of ``"auto"``, which needs the whole scan (give the length
    that ``miem.detect(first_scan).params["min_step"]`` resolves on a first scan of the part).
    The stream runs the rest of the default detector: the angle test, the height test with
    compact EDGE groups, the edge test, heights and defects."""
    _parts(path)
    base = PRESETS[DEFAULT_PRESET]
    if path != "stream":
        return base
    off = {n: m["stream"] for n, m in DetectParams.fields("grid").items() if "stream" in m}
    return base._replace(off, ("grid",))


def resolve_params(params: Any, preset: Optional[str], overrides: Mapping[str, Any],
                   path: str = "grid") -> Tuple[DetectParams, str]:
    """The parameters a call runs with, and the name to record: ``params`` or ``preset`` (not
    both; neither: :func:`default_params` of ``path``), then ``overrides`` (fields of ``angle``
    and ``path``'s part)."""
    if params is not None and preset is not None:
        raise ValueError("params, preset: give one of them, not both")
    if params is not None:
        if isinstance(params, Mapping):
            params = DetectParams.from_dict(params)
        elif not isinstance(params, DetectParams):
            raise ValueError(f"params: expected a miem.DetectParams or a mapping, got "
                             f"{type(params).__name__}")
        name = "custom"
    elif preset is not None:
        if not isinstance(preset, str) or preset not in PRESETS:
            raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
        params, name = PRESETS[preset], preset
    else:
        params = default_params(path)
        name = DEFAULT_PRESET if path != "stream" else "default"
    return params.for_path(path, **overrides), name


def load_config(path: Union[str, Path], base: Optional[DetectParams] = None) -> DetectParams:
    """Detection parameters from a JSON or TOML file: tables ``angle``, ``grid``, ``cloud``
    (as :func:`dump_config` writes, TOML optionally under ``[detect]``) and/or fields by name
    at the top (set in every part that has them). A ``preset = "NAME"`` key starts from that
    preset (else from ``base``, else the defaults). ``null`` (JSON) or ``"off"`` / ``"none"``
    mean None.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ValueError(f"config: cannot read {p}: {exc.strerror or exc}") from None
    if p.suffix.lower() == ".toml":
        try:
            import tomllib  # Python 3.11+
        except ImportError:  # pragma: no cover - Python < 3.11
            try:
                import tomli as tomllib  # type: ignore[no-redef]
            except ImportError:
                raise ValueError("config: TOML needs Python 3.11 or the 'tomli' package") from None
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"config: {p} is not valid TOML: {exc}") from None
        if isinstance(doc.get("detect"), dict):
            doc = doc["detect"]
    else:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"config: {p} is not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"config: {p} must hold a table of detection parameters")
    doc = _nones(doc)
    preset = doc.pop("preset", None)
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"config: preset: expected one of {sorted(PRESETS)}, got {preset!r}")
        base = PRESETS[preset]
    try:
        return DetectParams.from_dict(doc, base)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"config: {p}: {exc}") from None


def _nones(doc: Dict[str, Any]) -> Dict[str, Any]:
    def one(v: Any) -> Any:
        if isinstance(v, dict):
            return _nones(v)
        return None if isinstance(v, str) and v.strip().lower() in ("off", "none") else v

    return {k: one(v) for k, v in doc.items()}


def dump_config(params: DetectParams, fmt: str = "toml") -> str:
    """A complete config (every part and field) as TOML (with each field's unit and help as a
    comment) or JSON, loadable by :func:`load_config`."""
    d = params.to_dict()
    if fmt == "json":
        return json.dumps(d, indent=2) + "\n"
    if fmt != "toml":
        raise ValueError(f"format: expected 'json' or 'toml', got {fmt!r}")
    lines = ["# miem detection parameters (miem.DetectParams); 'off' means None.",
             "# angle: every detector; grid: organized scans; cloud: unorganized (N, 3) clouds."]
    for part, values in d.items():
        lines += ["", f"[{part}]"]
        for f in dataclasses.fields(_PART_TYPES[part]):
            unit = f" [{f.metadata['unit']}]" if f.metadata["unit"] else ""
            lines.append(f"# {f.name}{unit}: {f.metadata['help']}")
            lines.append(f"{f.name} = {_toml_value(values[f.name])}")
    return "\n".join(lines) + "\n"


def _toml_value(v: Any) -> str:
    if v is None:
        return '"off"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)
