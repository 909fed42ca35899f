"""The detector configuration, defined once per scope: fields, defaults, units, help, presets.

:class:`DetectParams` is the C++ parameter types of ``cpp/include/miem/params.hpp`` in the
user's spelling, one part per scope: ``angle`` (:class:`AngleParams`, the angle test shared by
every detector), ``grid`` (:class:`GridParams`, organized grids: batch and stream) and ``cloud``
(:class:`CloudParams`, unorganized clouds). The parts are **generated** from the C++ types'
field tables (``visit_fields``, bound as ``miem._core.GridParams.fields()`` etc.): every C++
field is a field here with the C++ default, unit and help, converted to the core generically and
checked by the C++ ``check()`` (whose message starts with the field's name). The presets are the
C++ presets (``paper_params()``, ``paper_points_params()``; the defaults are default-constructed
C++ parameters). Only the fields whose Python spelling differs from C++ are written out here
(``_SPELLED``): ``theta0`` (degrees or ``"auto"``: ``theta0_deg`` + ``theta0_auto``),
``min_directions`` (None for all: 0), grid ``min_step``, ``z_resolution`` and ``z_noise`` (a
length, ``"auto"`` or None: the length + its ``_auto`` flag), ``heights`` (``"all"`` /
``"abnormal"``: ``height_mode``),
``height_tolerance`` (a length or ``"<k>rms"``: ``height_abs`` + ``height_k``),
``edge_tolerance`` and ``isolated_tolerance`` (None for off: ``edge_k`` / ``isolated_k`` 0) and
cloud ``K`` (``num_directions``).

A detector reads ``angle`` and its own part, and a keyword override names a field of those parts
(``miem.detect(grid, window=15)``, ``miem.detect(points, radius=2.0)``); a field of another part
is refused with a ValueError naming it. ``ProfileStream`` refuses ``theta0="auto"`` (the
median of the whole scan's angles); ``min_step``, ``z_resolution`` and ``z_noise`` ``"auto"``
it measures on its first 256 profiles with data, as batch detection does.
The command line's detection options, ``--config`` files, ``miem config`` and ``miem.dask``'s
known fields are generated from these fields.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Mapping, Optional, Tuple, Union

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
#: The bound C++ type of each part (its ``fields()`` are the part's fields), and the combined
#: C++ type a detector converts the parts to (its default-constructed value gives the defaults).
_CORE_PART = {"angle": _core.AngleParams, "grid": _core.GridParams, "cloud": _core.CloudParams}
_CORE_WHOLE = {"angle": _core.DetectParams, "grid": _core.DetectParams,
               "cloud": _core.PointsDetectParams}


# ---------------------------------------------------------------------------------------------
# value checks of the user's spelling (types; the ranges are the core's check())


def _int(name: str, value: object, minimum: Optional[int] = None, maximum: int = 2**31 - 1
         ) -> int:
    """An integer (a C++ int: 32 bits), at least ``minimum`` when given."""
    import numpy as np

    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    v = int(value)
    if minimum is None:
        if not -2**31 < v <= maximum:
            raise ValueError(f"{name}: expected a 32-bit integer, got {v}")
    elif v < minimum:
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


def _ints(name: str, value: object) -> Tuple[int, ...]:
    """A non-empty tuple of integers (a C++ std::vector<int> field) from a sequence or one int."""
    import numpy as np

    if isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)):
        value = (value,)
    if isinstance(value, (str, bytes)):
        raise ValueError(f"{name}: expected integers, got {value!r}")
    try:
        out = tuple(_int(name, s) for s in value)  # type: ignore[union-attr]
    except TypeError:
        raise ValueError(f"{name}: expected integers, got {value!r}") from None
    if not out:
        raise ValueError(f"{name}: must not be empty")
    return out


def _bool(name: str, value: object) -> bool:
    import numpy as np

    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected True or False, got {value!r}")
    return bool(value)


def _optional_real(name: str, value: object) -> Optional[float]:
    return None if value is None else _real(name, value)


def _raise_unless_ok(status: Tuple[int, str]) -> None:
    code, message = status
    if code != 0:
        raise ValueError(message)


# ---------------------------------------------------------------------------------------------
# plain fields: the C++ field as it is (its C++ type, read from the default, picks the conversion)

#: C++ default's Python type -> (to the core, from the core). std::optional<double> is None by
#: default (all optional fields are lengths whose default the detector derives).
_PLAIN: Dict[type, Tuple[Callable[[str, Any], Any], Callable[[Any], Any]]] = {
    bool: (_bool, bool),
    int: (_int, int),
    float: (_real, float),
    list: (lambda n, v: list(_ints(n, v)), tuple),  # std::vector<int>
    type(None): (_optional_real, lambda v: v),      # std::optional<double>
}


def _metavar(unit: str, default: Any) -> str:
    if isinstance(default, tuple):
        return "N"
    return {"length": "LENGTH", "cells": "CELLS", "spacings": "SPACINGS"}.get(unit, "N")


# ---------------------------------------------------------------------------------------------
# spelled fields: the only fields whose Python form differs from the C++ field(s) they stand for


@dataclass(frozen=True)
class _Spelled:
    """A Python field standing for C++ fields ``core`` of its part: ``to_core(value)`` -> the
    C++ values by name (ValueError naming ``name`` when the value is not of its form),
    ``from_core(values by C++ name)`` -> the Python value (gives the default and the presets)."""

    name: str
    core: Tuple[str, ...]
    unit: str
    help: str
    metavar: str
    to_core: Callable[[Any], Dict[str, Any]]
    from_core: Callable[[Dict[str, Any]], Any]
    extra: Tuple[Tuple[str, Any], ...] = ()  # more metadata (ProfileStream's "stream" values)
    annotation: Any = Any  # the Python type, for signatures and help()


def _theta0_to(v: Any) -> Dict[str, Any]:
    if isinstance(v, str):
        if v != "auto":
            raise ValueError(f"theta0: expected degrees or 'auto', got {v!r}")
        return {"theta0_auto": True, "theta0_deg": 90.0}
    return {"theta0_auto": False, "theta0_deg": _real("theta0", v)}


def _min_directions_to(v: Any) -> Dict[str, Any]:
    return {"min_directions": 0 if v is None else _int("min_directions", v, 1)}


def _auto_length(name: str, help: str) -> _Spelled:
    """A grid length that may be measured (C++ ``name`` < 0: off, and ``name + "_auto"``),
    spelled as a length >= 0, ``"auto"`` or None."""
    flag = name + "_auto"

    def to(v: Any) -> Dict[str, Any]:
        if isinstance(v, str):
            if v != "auto":
                raise ValueError(f"{name}: expected a length >= 0, 'auto' or None, got {v!r}")
            return {flag: True, name: -1.0}
        if v is None:
            return {flag: False, name: -1.0}
        m = _real(name, v)
        if m < 0:
            raise ValueError(f"{name}: expected a length >= 0, 'auto' or None, got {m}")
        return {flag: False, name: m}

    def back(c: Dict[str, Any]) -> Any:
        return "auto" if c[flag] else (None if c[name] < 0 else c[name])

    return _Spelled(name, (name, flag), "length", help, "LENGTH|auto", to, back, (),
                    Union[None, float, str])


_HEIGHT_MODES = {"all": _core.HeightMode.ALL, "abnormal": _core.HeightMode.ABNORMAL}


def _heights_to(v: Any) -> Dict[str, Any]:
    if not isinstance(v, str) or v not in _HEIGHT_MODES:
        raise ValueError(f"heights: expected 'all' or 'abnormal', got {v!r}")
    return {"height_mode": _HEIGHT_MODES[v]}


def _heights_from(c: Dict[str, Any]) -> str:
    return next(k for k, m in _HEIGHT_MODES.items() if m == c["height_mode"])


_RMS = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*rms\s*$")


def _height_tolerance_to(value: Any) -> Dict[str, Any]:
    """(absolute, k_rms) from None, a length or a '<k>rms' string; 0 means off."""
    if value is None:
        return {"height_abs": 0.0, "height_k": 0.0}
    if isinstance(value, str):
        m = _RMS.match(value)
        if not m or not float(m.group(1)) > 0 or not math.isfinite(float(m.group(1))):
            raise ValueError(
                f"height_tolerance: expected a length > 0, '<k>rms' with k > 0 (e.g. '4rms') "
                f"or None, got {value!r}")
        return {"height_abs": 0.0, "height_k": float(m.group(1))}
    v = _real("height_tolerance", value)
    if not v > 0:
        raise ValueError(f"height_tolerance: expected a length > 0, got {v}")
    return {"height_abs": v, "height_k": 0.0}


def _height_tolerance_from(c: Dict[str, Any]) -> Any:
    if c["height_abs"] > 0 and c["height_k"] > 0:
        raise ValueError("height_tolerance: C++ sets both height_abs and height_k; Python "
                         "spells one of them")
    if c["height_abs"] > 0:
        return c["height_abs"]
    return f"{c['height_k']:g}rms" if c["height_k"] > 0 else None


def _off_is_zero(name: str, core: str, unit: str, help: str, metavar: str = "K") -> _Spelled:
    """A C++ multiple ``core`` that is off at 0, spelled ``name``: a number > 0, or None (off)."""

    def to_core(v: Any) -> Dict[str, Any]:
        if v is None:
            return {core: 0.0}
        k = _real(name, v)
        if not k > 0.0:
            raise ValueError(f"{name}: expected None (off) or a number > 0, got {k}")
        return {core: k}

    return _Spelled(name, (core,), unit, help, metavar, to_core,
                    lambda c: c[core] if c[core] > 0 else None, annotation=Optional[float])


def _theta0() -> _Spelled:
    return _Spelled(
        "theta0", ("theta0_deg", "theta0_auto"), "deg",
        "angle threshold: a direction is flagged when the interior angle at the point is at "
        "most theta0 (0 < theta0 < 180); 'auto' derives it from the scan's angle statistics "
        "(grids only)", "DEG", _theta0_to,
        lambda c: "auto" if c["theta0_auto"] else c["theta0_deg"], annotation=Union[float, str])


def _min_directions() -> _Spelled:
    return _Spelled(
        "min_directions", ("min_directions",), "directions",
        "flagged directions needed for ABNORMAL, 1-4 (clouds: 1-K); None: all available "
        "directions", "N", _min_directions_to,
        lambda c: None if c["min_directions"] == 0 else c["min_directions"],
        annotation=Optional[int])


def _heights() -> _Spelled:
    return _Spelled("heights", ("height_mode",), "",
                    "which points get a height: 'all' finite points or only 'abnormal' ones "
                    "(faster)", "{all,abnormal}", _heights_to, _heights_from, annotation=str)


def _height_tolerance(help: str) -> _Spelled:
    return _Spelled("height_tolerance", ("height_abs", "height_k"), "length or k x rms", help,
                    "LENGTH|Krms", _height_tolerance_to, _height_tolerance_from,
                    annotation=Union[None, float, str])


#: The fields whose Python spelling differs from C++, per part (all other fields are plain).
_SPELLED: Dict[str, Tuple[_Spelled, ...]] = {
    "angle": (_theta0(), _min_directions()),
    "grid": (
        _auto_length(
            "min_step",
            "minimum neighbour distance in the scan's units, so that every direction sees the "
            "same physical scale; 'auto': from the scan's spacing and profile noise over the "
            "first 256 rows with data (SPEC \"min_step='auto'\"; result.params holds the value "
            "used); None: off"),
        _heights(),
        _height_tolerance(
            "height test (beyond the paper): a NORMAL point farther than this from its local "
            "plane becomes ABNORMAL; a length or '<k>rms' (k times the plane's rms); None: off"),
        _off_is_zero(
            "edge_tolerance", "edge_k", "k x rms",
            "edge test (SPEC 'Edge test', beyond the paper, after the height test): a point "
            "standing proud of a feature line or the scan's outline by more than k times the "
            "rms of its one-sided sub-window plane (at least min_step / 2 with a min_step, "
            "2 z_noise) becomes ABNORMAL; None: off"),
        _auto_length(
            "z_resolution",
            "the scan's z step (quantisation): the height test's k x rms and the edge test's "
            "tolerances are at least 1.5 times it, so that a cell one step off a level surface "
            "is not a defect; 'auto': the smallest non-zero z difference of neighbours, or of "
            "any two points of the first rows, in the rows min_step 'auto' reads (SPEC "
            "\"z_resolution\"; "
            "result.params holds the value used); None: off"),
        _auto_length(
            "z_noise",
            "the scan's z noise sigma, profile jitter included: the edge test's tolerances are "
            "at least 2 times it, so that a profile offset by its scanner's jitter does not "
            "stand proud of a few profiles that happen to agree; 'auto': measured as min_step "
            "'auto' measures it (the larger robust sigma of the second differences along and "
            "across the profiles of its rows; SPEC \"z_noise\"; result.params holds the value "
            "used); None: off"),
    ),
    "cloud": (
        _Spelled("K", ("num_directions",), "directions", "tangent-plane directions tested, 2-8",
                 "N", lambda v: {"num_directions": _int("K", v)},
                 lambda c: c["num_directions"], annotation=int),
        _heights(),
        _height_tolerance(
            "height test: a NORMAL point farther than this from the plane of its surroundings "
            "(beyond radius, within height_radius) becomes ABNORMAL; a length or '<k>rms'; "
            "None: off"),
        _off_is_zero(
            "edge_tolerance", "edge_k", "k x rms",
            "edge test (SPEC 'Unorganized clouds: edge test', after the height test): a point "
            "standing proud of a feature line or the cloud's outline by more than k times the "
            "rms of a one-sided sector's plane becomes ABNORMAL (3 was measured on the "
            "held-out-style clouds; not in the default); None: off"),
        _off_is_zero(
            "isolated_tolerance", "isolated_k", "k x rms",
            "with the height test: a point alone farther than k times the rms of its "
            "surroundings plane, whose neighbours within radius lie about that plane as loosely "
            "as the rms says (a low spike or pit one point wide), becomes ABNORMAL; None: off"),
    ),
}


# ---------------------------------------------------------------------------------------------
# the parts, generated from the C++ field tables


@dataclass(frozen=True)
class _Field:
    """How one Python field converts: to the core (C++ values by name) and from it."""

    name: str
    core: Tuple[str, ...]
    to_core: Callable[[Any], Dict[str, Any]]
    from_core: Callable[[Dict[str, Any]], Any]
    annotation: Any = Any


#: C++ default's Python type -> the field's annotation.
_ANNOTATION = {bool: bool, int: int, float: float, list: Tuple[int, ...],
               type(None): Optional[float]}


def _plain(part: str, name: str) -> Tuple[Callable, Callable]:
    default = getattr(_CORE_WHOLE[part](), name)
    if type(default) not in _PLAIN:
        raise TypeError(f"C++ field {name}: type {type(default).__name__} has no plain Python "
                        "conversion; spell it in miem/params.py _SPELLED")
    to, back = _PLAIN[type(default)]
    return (lambda v: {name: to(name, v)}), (lambda c: back(c[name]))


def _part_table(part: str) -> Tuple[Tuple[Any, ...], ...]:
    """``(_Field, unit, help, metavar or None, extra metadata)`` of the part's fields in C++
    declaration order: a spelled field where its first C++ field stands, every other C++ field
    as it is."""
    spelled = {c: s for s in _SPELLED[part] for c in s.core}
    out, seen = [], set()
    for name, unit, help in _CORE_PART[part].fields():
        s = spelled.get(name)
        if s is None:
            to, back = _plain(part, name)
            kind = type(getattr(_CORE_WHOLE[part](), name))
            out.append((_Field(name, (name,), to, back, _ANNOTATION[kind]), unit, help, None,
                        ()))
        elif s.name not in seen:
            seen.add(s.name)
            out.append((_Field(s.name, s.core, s.to_core, s.from_core, s.annotation), s.unit,
                        s.help, s.metavar, s.extra))
    missing = [s.name for s in _SPELLED[part] if s.name not in seen]
    if missing:
        raise TypeError(f"miem/params.py _SPELLED[{part!r}]: {missing} name no C++ field")
    return tuple(out)


def _core_values(core: Any, names: Tuple[str, ...]) -> Dict[str, Any]:
    return {n: getattr(core, n) for n in names}


def _make_part(part: str, doc: str) -> type:
    table = _part_table(part)
    default_core = _CORE_WHOLE[part]()
    fields, conv = [], {}
    for f, unit, help, metavar, extra in table:
        default = f.from_core(_core_values(default_core, f.core))
        meta = {"unit": unit, "help": help, "metavar": metavar or _metavar(unit, default),
                "core": f.core, **dict(extra)}
        fields.append((f.name, f.annotation, field(default=default, metadata=meta)))
        conv[f.name] = f
    tuples = tuple(f.name for f, *_ in table if isinstance(
        f.from_core(_core_values(default_core, f.core)), tuple))

    def __post_init__(self: Any) -> None:  # sequences of integers as tuples, checked
        for name in tuples:
            object.__setattr__(self, name, _ints(name, getattr(self, name)))

    lines = [doc, "", "Fields (generated from the C++ field table, with units):", ""]
    for f, unit, help, *_ in table:
        lines.append(f"- ``{f.name}``{f' [{unit}]' if unit else ''}: {help}")
    cls = dataclasses.make_dataclass(
        _CORE_PART[part].__name__, fields, frozen=True,
        namespace={"__doc__": "\n".join(lines), "__post_init__": __post_init__,
                   "_convert": conv})
    cls.__module__ = __name__  # (make_dataclass's module= is Python 3.12+)
    return cls


AngleParams = _make_part("angle", "The angle test and its iteration, shared by grids, the "
                                  "stream and clouds.")
GridParams = _make_part("grid", "Organized grids only (batch detection and ProfileStream).")
CloudParams = _make_part("cloud", "Unorganized clouds only.")

_PART_TYPES = {"angle": AngleParams, "grid": GridParams, "cloud": CloudParams}


def _to_core(part_obj: Any, core: Any) -> None:
    """Sets the C++ fields of ``core`` that the part's fields stand for."""
    for name, f in part_obj._convert.items():
        for cname, value in f.to_core(getattr(part_obj, name)).items():
            setattr(core, cname, value)


def _part_from_core(part: str, core: Any) -> Any:
    cls = _PART_TYPES[part]
    return cls(**{name: f.from_core(_core_values(core, f.core))
                  for name, f in cls._convert.items()})


def _check(core: Any, parts: Tuple[str, ...]) -> None:
    """The C++ check(); its message names the C++ field, which is renamed to the Python field
    that stands for it (``edge_k`` -> ``edge_tolerance``)."""
    code, message = core.check()
    if code == 0:
        return
    head, sep, rest = message.partition(":")
    for part in parts:
        for name, f in _PART_TYPES[part]._convert.items():
            if head in f.core and head != name:
                message = f"{name} (C++ {head}){sep}{rest}"
    raise ValueError(message)


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

    angle: AngleParams = field(default_factory=AngleParams)  # type: ignore[valid-type]
    grid: GridParams = field(default_factory=GridParams)  # type: ignore[valid-type]
    cloud: CloudParams = field(default_factory=CloudParams)  # type: ignore[valid-type]

    # -- fields ---------------------------------------------------------------------------

    @staticmethod
    def fields(path: str = "grid") -> Dict[str, Dict[str, Any]]:
        """Field name -> ``{"default", "unit", "help", "metavar", "part", "core", ...}`` for
        the fields detector ``path`` reads (``angle`` and its own part); ``core``: the C++
        fields it stands for."""
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
        for values in out.values():
            for k, v in values.items():
                if isinstance(v, tuple):
                    values[k] = list(v)
        return out

    @classmethod
    def _from_core(cls, grid: Any, cloud: Any) -> "DetectParams":
        """The parameters that C++ ``grid`` (a DetectParams: angle and grid) and ``cloud`` (a
        PointsDetectParams) spell."""
        return cls(angle=_part_from_core("angle", grid), grid=_part_from_core("grid", grid),
                   cloud=_part_from_core("cloud", cloud))

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
                if value != meta["stream"]:
                    bad.append((f"{name}={value!r}", f"{name}={meta['stream']!r}"))
        if bad:
            raise ValueError(
                f"{', '.join(b[0] for b in bad)}: not implemented for {_WHAT[path]} yet; the "
                f"field would be ignored, so it is refused (use {', '.join(b[1] for b in bad)})")

    def _core_grid(self, num_threads: int, path: str = "grid") -> Any:
        """The C++ ``miem::DetectParams`` for an organized grid (or a stream), checked."""
        self._reject_unhonoured(path)
        p = _core.DetectParams()
        _to_core(self.angle, p)
        _to_core(self.grid, p)
        p.num_threads = num_threads
        _check(p, ("angle", "grid"))
        return p

    def _core_cloud(self, num_threads: int) -> Any:
        """The C++ ``miem::PointsDetectParams`` for an unorganized cloud, checked."""
        self._reject_unhonoured("cloud")
        p = _core.PointsDetectParams()
        _to_core(self.angle, p)
        _to_core(self.cloud, p)
        p.num_threads = num_threads
        _check(p, ("angle", "cloud"))
        return p


def _parts(path: str) -> Tuple[str, ...]:
    if path not in _PARTS:
        raise ValueError(f"path: expected one of {', '.join(PATHS)}, got {path!r}")
    return _PARTS[path]


def _names(part: str) -> Tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(_PART_TYPES[part]))


def _all_names() -> Tuple[str, ...]:
    return tuple(dict.fromkeys(n for part in _PART_TYPES for n in _names(part)))


# ---------------------------------------------------------------------------------------------
# presets and defaults

#: Named parameter sets (parameter objects), the C++ presets: ``"paper"`` is the paper's method
#: exactly (``paper_params()``, on clouds ``paper_points_params()``: no height test, no floating
#: groups). ``"recommended"`` is the default (default-constructed C++ parameters): its grid
#: values were chosen on the tuning split of the accuracy benchmark
#: (``bench/accuracy/recommended.json``; ``min_step``, ``edge_tolerance`` and ``edge_window``
#: by ``bench/accuracy/edges.py --tune``; test-split scores in ``bench/accuracy/RESULTS.md`` and
#: ``results_edges.md``), its cloud values on the tuning split of the held-out-style cloud
#: scenes (``bench/accuracy/clouds.py``).
PRESETS: Dict[str, DetectParams] = {
    "paper": DetectParams._from_core(_core.paper_params(), _core.paper_points_params()),
    "recommended": DetectParams(),
}

#: The cloud-only values of each preset that differ between presets (a view of PRESETS).
CLOUD_PRESETS: Dict[str, Dict[str, Any]] = {
    name: {k: v for k, v in dataclasses.asdict(p.cloud).items()
           if len({dataclasses.asdict(q.cloud)[k] for q in PRESETS.values()}) > 1}
    for name, p in PRESETS.items()
}

#: The preset used when neither ``params`` nor ``preset`` is given.
DEFAULT_PRESET = "recommended"


def default_params(path: str = "grid") -> DetectParams:
    """The default parameters of a detector: the default preset (for ``"stream"`` too: the
    stream runs the whole default detector, ``min_step="auto"`` included, SPEC "Streaming"),
    with the fields a path does not implement set to the one value it accepts."""
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
