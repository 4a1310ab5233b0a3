"""Simulation: built-in objects (:mod:`.objects`), the YCB meshes (:mod:`.ycb`), grasps and
sensor noise (:mod:`.grasps`), rounded fingertips (:mod:`.fingertip`), a probe's touch
(:mod:`.touch`), the espresso machine (:mod:`.espresso`) and a range scanner
(:mod:`.range_scanner`).

Paper equation: the §5 protocol (contacts at facet centroids, the banana rolled 5.7° and
shifted 10 mm) -> :func:`grasps.paper_pose` with ``grasps.grasp(..., where="centroid")``.
Its modules are imported by name: some load Open3D.
"""

__all__ = ["espresso", "fingertip", "grasps", "objects", "range_scanner", "touch", "ycb"]
