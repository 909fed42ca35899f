"""The detector configuration, defined once: fields, defaults, units, help, presets, files.

:class:`DetectParams` mirrors the C++ parameter types (``cpp/include/miem/params.hpp``:
``AngleParams`` shared by every detector, ``GridParams`` for organized grids, ``CloudParams``
for unorganized clouds) in the user's spelling (``theta0="auto"``, ``height_tolerance="4.5rms"``,
``None`` for "off"). Each field's metadata says its unit, its help text and the detectors
("paths") that honour it: ``grid`` (:func:`miem.detect` on an ``(H, W, 3)`` scan), ``stream``
(:class:`miem.ProfileStream`) and ``cloud`` (:func:`miem.detect` on ``(N, 3)`` points). A path
that does not honour a field rejects any value but the field's neutral one with a ValueError.
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
    "DetectParams",
    "PRESETS",
    "DEFAULT_PRESET",
    "PATHS",
    "default_params",
    "resolve_params",
    "load_config",
]

#: The detectors a field can apply to.
PATHS = ("grid", "stream", "cloud")
_ALL = PATHS
_GRID = ("grid",)
_ORGANIZED = ("grid", "stream")
_CLOUD = ("cloud",)


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


def _f(default: Any, unit: str, help: str, paths: Tuple[str, ...], metavar: str,
       neutral: Any = dataclasses.MISSING) -> Any:
    """A field with its unit, help text, paths, command-line metavar and neutral value (the
    value a path that does not honour the field accepts; default: the field's default)."""
    meta = {"unit": unit, "help": help, "paths": paths, "metavar": metavar,
            "neutral": default if neutral is dataclasses.MISSING else neutral}
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class DetectParams:
    """Detection parameters. The defaults are the recommended preset, the best measured
    configuration (``bench/accuracy``); ``PRESETS["paper"]`` is the paper's method exactly.

    Build one with keywords (``DetectParams(theta0=80)``), from a preset
    (``PRESETS["paper"].replace(window=15)``) or from a file (:func:`load_config`). Values are
    checked when a detector uses them (:meth:`check`), with a ValueError naming the field.
    ``DetectParams.fields()`` lists each field's unit, help and paths.
    """

    theta0: Union[float, str] = _f(
        90.0, "deg", "angle threshold: a direction is flagged when the interior angle at the "
        "point is at most theta0 (0 < theta0 < 180); 'auto' derives it from the scan's angle "
        "statistics (grids only)", _ALL, "DEG")
    scales: Tuple[int, ...] = _f(
        (1, 2), "cells", "neighbour distances: (1, 2) also finds defects two points wide (on "
        "clouds: multiples of min_step)", _ALL, "N")
    max_gap: int = _f(
        1, "cells", "missing or removed cells that may be skipped to reach a neighbour",
        _ORGANIZED, "CELLS")
    min_step: Optional[float] = _f(
        None, "length", "grids: minimum neighbour distance in the scan's units, so that every "
        "direction sees the same physical scale (None: off); clouds: shortest tangent-plane "
        "offset (None: 0.5 x the point spacing)", _ALL, "LENGTH")
    min_directions: Optional[int] = _f(
        None, "directions", "flagged directions needed for ABNORMAL, 1-4 (clouds: 1-K); None: "
        "all available directions", _ALL, "N")
    max_iterations: int = _f(
        10, "passes", "maximum detection passes; each pass removes the points found and judges "
        "the rest again (and at most as many height passes)", _ALL, "N")
    window: int = _f(
        21, "cells", "side of the square (odd) whose NORMAL points give the local plane for "
        "heights and the height test", _GRID, "CELLS")
    heights: str = _f(
        "all", "", "which points get a height: 'all' finite points or only 'abnormal' ones "
        "(faster)", ("grid", "cloud"), "{all,abnormal}")
    height_tolerance: Union[None, float, str] = _f(
        "4.5rms", "length or k x rms", "height test (beyond the paper): a NORMAL point "
        "farther than this from its local plane becomes ABNORMAL; a length or '<k>rms' (k times "
        "the plane's rms); None: off",
        _GRID, "LENGTH|Krms", neutral=None)
    edge_extent: int = _f(
        12, "cells", "with the height test: EDGE groups whose bounding box is at most this long "
        "are compact (a defect's halo) and height-tested too; longer ones are feature lines",
        _GRID, "CELLS", neutral=0)
    max_reach: int = _f(
        32, "cells", "with min_step: how many cells beyond scale + max_gap the neighbour search "
        "may go", _ORGANIZED, "CELLS")
    radius: Optional[float] = _f(
        None, "length", "neighbourhood radius (None: 5 x the median point spacing)", _CLOUD,
        "LENGTH")
    K: int = _f(4, "directions", "tangent-plane directions tested, 2-8", _CLOUD, "N")
    link: Optional[float] = _f(
        None, "length", "ABNORMAL points this close belong to one defect (None: radius)",
        _CLOUD, "LENGTH")

    def __post_init__(self) -> None:
        object.__setattr__(self, "scales", _scales_tuple(self.scales))

    # -- construction ---------------------------------------------------------------------

    def replace(self, **overrides: Any) -> "DetectParams":
        """A copy with some fields changed; an unknown name is a ValueError."""
        unknown = sorted(set(overrides) - set(field_names()))
        if unknown:
            raise ValueError(f"{', '.join(unknown)}: unknown detection parameter(s); expected "
                             f"one of {', '.join(field_names())}")
        return dataclasses.replace(self, **overrides)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], base: Optional["DetectParams"] = None
                  ) -> "DetectParams":
        """``base`` (default: the defaults) with the fields in ``values`` (e.g. a JSON config)."""
        return (cls() if base is None else base).replace(**dict(values))

    def to_dict(self) -> Dict[str, Any]:
        """Every field, JSON-ready (``scales`` as a list)."""
        out = dataclasses.asdict(self)
        out["scales"] = list(out["scales"])
        return out

    @staticmethod
    def fields() -> Dict[str, Dict[str, Any]]:
        """Field name -> ``{"default", "unit", "help", "paths", "metavar", "neutral"}``."""
        return {f.name: {"default": f.default, **f.metadata}
                for f in dataclasses.fields(DetectParams)}

    # -- checks and conversion to the core ------------------------------------------------

    def check(self, path: str = "grid") -> None:
        """Raise ValueError (naming the field) unless the detector ``path`` can run these
        values: each honoured field in range, each other field at its neutral value."""
        if path == "cloud":
            self._core_cloud(0)
        elif path == "stream":
            _raise_unless_ok(_core.check_stream_params(1, self._core_grid(0, path)))
        else:
            self._core_grid(0, path)

    def _reject_unhonoured(self, path: str) -> None:
        bad = []
        for name, meta in DetectParams.fields().items():
            value = getattr(self, name)
            if path not in meta["paths"] and value != meta["neutral"]:
                bad.append(f"{name}={value!r}")
        if path != "grid" and isinstance(self.theta0, str):
            bad.append(f"theta0={self.theta0!r}")
        if bad:
            what = {"grid": "organized grids (H, W, 3)", "cloud": "unorganized clouds (N, 3)",
                    "stream": "ProfileStream"}[path]
            raise ValueError(
                f"{', '.join(bad)}: not implemented for {what}; the field would be ignored, so it "
                f"is rejected (set it to its neutral value, e.g. "
                f"{', '.join(_neutral_hint(b.split('=')[0]) for b in bad)})")

    def _core_angle(self, core: Any) -> None:
        if isinstance(self.theta0, str):
            if self.theta0 != "auto":
                raise ValueError(f"theta0: expected degrees or 'auto', got {self.theta0!r}")
            core.theta0_auto = True
            core.theta0_deg = 90.0
        else:
            core.theta0_deg = _real("theta0", self.theta0)
        core.scales = list(_scales_tuple(self.scales))
        md = self.min_directions
        core.min_directions = 0 if md is None else _int("min_directions", md, 1)
        core.max_iterations = _int("max_iterations", self.max_iterations, 1)

    def _core_grid(self, num_threads: int, path: str = "grid") -> Any:
        """The C++ ``miem::DetectParams`` for an organized grid (or a stream), checked."""
        self._reject_unhonoured(path)
        p = _core.DetectParams()
        self._core_angle(p)
        p.max_gap = _int("max_gap", self.max_gap, 0)
        if self.min_step is None:
            p.min_step = -1.0
        else:
            p.min_step = _real("min_step", self.min_step)
            if p.min_step < 0:
                raise ValueError(f"min_step: expected a length >= 0 or None, got {self.min_step}")
        p.max_reach = _int("max_reach", self.max_reach, 1)
        p.window = _int("window", self.window, 3)
        p.height_mode = _height_mode(self.heights)
        p.height_abs, p.height_k = _height_tolerance(self.height_tolerance)
        p.edge_extent = _int("edge_extent", self.edge_extent, 0)
        p.num_threads = num_threads
        _raise_unless_ok(p.check())
        return p

    def _core_cloud(self, num_threads: int) -> Any:
        """The C++ ``miem::PointsDetectParams`` for an unorganized cloud, checked."""
        self._reject_unhonoured("cloud")
        p = _core.PointsDetectParams()
        self._core_angle(p)
        p.num_directions = _int("K", self.K, 2, 8)
        p.radius = None if self.radius is None else _positive("radius", self.radius)
        p.link = None if self.link is None else _positive("link", self.link)
        if self.min_step is not None:
            step = _real("min_step", self.min_step)
            if step < 0:
                raise ValueError(f"min_step: expected a length >= 0 or None, got {step}")
            p.min_step = step
        if p.min_directions > p.num_directions:
            raise ValueError(
                f"min_directions: expected 1..K={p.num_directions} or None, got {p.min_directions}")
        p.height_mode = _height_mode(self.heights)
        p.num_threads = num_threads
        _raise_unless_ok(p.check())
        return p


def field_names() -> Tuple[str, ...]:
    """The fields of :class:`DetectParams`, in order."""
    return tuple(f.name for f in dataclasses.fields(DetectParams))


def _neutral_hint(name: str) -> str:
    if name == "theta0":
        return "theta0=<degrees>"
    return f"{name}={DetectParams.fields()[name]['neutral']!r}"


# ---------------------------------------------------------------------------------------------
# presets and defaults

#: Named parameter sets (parameter objects). ``"paper"`` is the paper's method exactly;
#: ``"recommended"`` was chosen on the tuning split of the accuracy benchmark
#: (``bench/accuracy/recommended.json``; overall F1 0.96 on the test split against 0.20 for
#: ``"paper"``, ``bench/accuracy/RESULTS.md``) and is the default.
PRESETS: Dict[str, DetectParams] = {
    "paper": DetectParams(theta0=75.0, scales=(1,), height_tolerance=None, edge_extent=0),
    "recommended": DetectParams(),
}

#: The preset used when neither ``params`` nor ``preset`` is given.
DEFAULT_PRESET = "recommended"


def default_params(path: str = "grid") -> DetectParams:
    """The default parameters of a detector: the default preset, minus the fields that path
    does not implement yet (documented in README and SPEC "Parameters").

    ``grid``: the recommended preset. ``stream`` and ``cloud``: the recommended angle test
    (theta0 90, scales (1, 2)) without the height test (``height_tolerance=None``,
    ``edge_extent=0``), which only organized batch detection implements so far; asking either
    for the height test explicitly is a ValueError.
    """
    if path not in PATHS:
        raise ValueError(f"path: expected one of {', '.join(PATHS)}, got {path!r}")
    base = PRESETS[DEFAULT_PRESET]
    if path == "grid":
        return base
    values = {}
    for name, meta in DetectParams.fields().items():
        if path not in meta["paths"]:
            values[name] = meta["neutral"]
    if isinstance(base.theta0, str):
        values["theta0"] = 90.0
    return base.replace(**values)


def resolve_params(params: Optional[DetectParams], preset: Optional[str],
                   overrides: Mapping[str, Any], path: str = "grid") -> Tuple[DetectParams, str]:
    """The parameters a call runs with, and the name to record: ``params`` or ``preset`` (not
    both; neither: :func:`default_params` of ``path``), then ``overrides``."""
    if params is not None and preset is not None:
        raise ValueError("params, preset: give one of them, not both")
    if params is not None:
        if not isinstance(params, DetectParams):
            if isinstance(params, Mapping):
                params = DetectParams.from_dict(params)
            else:
                raise ValueError(f"params: expected a miem.DetectParams or a mapping, got "
                                 f"{type(params).__name__}")
        name = "custom"
    elif preset is not None:
        if not isinstance(preset, str) or preset not in PRESETS:
            raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
        params, name = PRESETS[preset], preset
    else:
        params, name = default_params(path), (DEFAULT_PRESET if path == "grid" else "default")
    if overrides:
        params = params.replace(**overrides)
    return params, name


def load_config(path: Union[str, Path], base: Optional[DetectParams] = None) -> DetectParams:
    """Detection parameters from a JSON or TOML file (a table of field names; TOML may nest them
    under ``[detect]``). A ``preset = "NAME"`` key starts from that preset; the other keys
    override it. ``null`` (JSON) or ``"off"`` / ``"none"`` mean None.
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
    doc = {k: (None if isinstance(v, str) and v.strip().lower() in ("off", "none") else v)
           for k, v in doc.items()}
    preset = doc.pop("preset", None)
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"config: preset: expected one of {sorted(PRESETS)}, got {preset!r}")
        base = PRESETS[preset]
    try:
        return DetectParams.from_dict(doc, base)
    except ValueError as exc:
        raise ValueError(f"config: {p}: {exc}") from None


def dump_config(params: DetectParams, fmt: str = "json") -> str:
    """A complete config (every field) as JSON or TOML text, loadable by :func:`load_config`."""
    d = params.to_dict()
    if fmt == "json":
        return json.dumps(d, indent=2) + "\n"
    if fmt != "toml":
        raise ValueError(f"format: expected 'json' or 'toml', got {fmt!r}")
    lines = ["[detect]"]
    for name, meta in DetectParams.fields().items():
        unit = f" [{meta['unit']}]" if meta["unit"] else ""
        lines.append(f"# {name}{unit}: {meta['help']}")
        v = d[name]
        lines.append(f"{name} = {_toml_value(v)}")
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
