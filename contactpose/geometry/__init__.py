"""Geometry below the method: exact distance kernels (numba), SE(3) in the library's one
convention, pose metrics, surface sampling and the raycaster.

No paper equation lives here; erratum 4 (the exact Δmin of §3.1) rests on
:func:`kernels.triangle_pair_bounds`.
"""

from contactpose.geometry.kernels import (
    closest_point_triangle,
    closest_points_on_triangles,
    point_triangle_dist2,
    point_triangle_distance,
    segment_segment_dist2,
    segment_triangle_intersect,
    triangle_pair_bounds,
    triangle_pair_vertex_bounds,
    triangle_triangle_dist2,
)
from contactpose.geometry.metrics import (
    MSSD_THRESHOLDS_FRAC,
    SAME_CLASS_ADDS_FRAC,
    adds,
    adds_many,
    ar_mssd,
    mssd,
    pose_success,
    rms_displacement,
    rotation_error_deg,
    symmetric_errors,
    translation_error,
)
from contactpose.geometry.raycast import Raycaster, raycaster

__all__ = ["MSSD_THRESHOLDS_FRAC", "SAME_CLASS_ADDS_FRAC", "Raycaster", "adds", "adds_many", "ar_mssd",
           "closest_point_triangle",
           "closest_points_on_triangles", "mssd", "point_triangle_dist2", "point_triangle_distance", "pose_success",
           "raycaster", "rms_displacement", "rotation_error_deg", "segment_segment_dist2",
           "segment_triangle_intersect", "symmetric_errors", "translation_error", "triangle_pair_bounds", "triangle_pair_vertex_bounds",
           "triangle_triangle_dist2"]
