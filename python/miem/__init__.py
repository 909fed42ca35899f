"""miem: abnormal-point detection in laser scans of workpieces.

Implements the Multidimensional Improved Eigenvalue Method (MIEM): each scan point is tested in
several directions by the angle its neighbours make; points flagged in every direction are
abnormal (burr tips, spatter, dust, pits), points flagged in some only are designed edges.

>>> import miem
>>> res = miem.detect(grid)            # grid: (H, W, 3) organized scan, NaN = dropout
>>> res.labels, res.height, res.defects
"""

from ._api import (
    ABNORMAL,
    DEFAULT_PRESET,
    EDGE,
    INVALID,
    NORMAL,
    PRESETS,
    CLOUD_PRESETS,
    Defect,
    DetectResult,
    Label,
    Plane,
    detect,
    fit_plane,
    scan_line_angles,
    scan_line_heights,
)
from ._core import __version__
from .params import (
    AngleParams,
    CloudParams,
    DetectParams,
    GridParams,
    default_params,
    load_config,
)
from .stream import ProfileStream, StreamRow
from .targets import Target, TargetPlan, Tool, plan_targets, read_transform
from .comparison import (
    Agreement,
    CompareResult,
    DeviationLabel,
    Reference,
    compare,
    load_reference,
)
from .registration import Registration, register
from ._unorganized import (
    NeighborGrid,
    Normals,
    PointsDetectResult,
    detect_points,
    estimate_normals,
    point_spacing,
)

__all__ = [
    "Agreement",
    "CompareResult",
    "DeviationLabel",
    "Reference",
    "Registration",
    "compare",
    "load_reference",
    "register",
    "ABNORMAL",
    "DEFAULT_PRESET",
    "EDGE",
    "INVALID",
    "NORMAL",
    "PRESETS",
    "CLOUD_PRESETS",
    "AngleParams",
    "CloudParams",
    "Defect",
    "DetectParams",
    "GridParams",
    "DetectResult",
    "Label",
    "NeighborGrid",
    "Normals",
    "PointsDetectResult",
    "Plane",
    "ProfileStream",
    "StreamRow",
    "Target",
    "TargetPlan",
    "Tool",
    "__version__",
    "detect",
    "default_params",
    "detect_points",
    "estimate_normals",
    "fit_plane",
    "plan_targets",
    "load_config",
    "point_spacing",
    "read_transform",
    "scan_line_angles",
    "scan_line_heights",
]
