"""CHSEL as an outside peer: its own package registers the contacts and the fingers' free space
against the object's signed distance field ("CHSEL: Producing Diverse Plausible Pose Estimates
from Contact and Free Space Data", RSS 2023).

Optional: ``pip install contactpose[peers]`` brings the package and torch (CPU). Its settings
here are those of its README's example (research/baselines.md, "CHSEL"): 30 transforms, 15
iterations of its gradient descent and quality-diversity search, an SDF cached on a grid of
1 cm with 10 cm of padding, the cost's defaults. The contacts enter as surface points (SDF 0),
the free space as FREE points. The package's ``surface_pts=``/``free_pts=`` path fails in
0.2.1 (it reads ``positions.dtype`` before it sets ``positions``), so the registration is made
once per object with one surface point and its points are set per grasp (``reset_points``):
the model's interior and surface points it builds at construction (40 s on a YCB object)
depend on the SDF alone.
"""

from __future__ import annotations

import os
import tempfile
import time

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.errors import ContactPoseError
from contactpose.peers.surface import BaselineResult

#: The README's example: a batch of 30 transforms refined over 15 iterations.
BATCH = 30
ITERATIONS = 15
#: The README's cached SDF: 1 cm voxels over the object's box padded by 10 cm.
SDF_RESOLUTION = 0.01
SDF_PADDING = 0.1


def available():
    """The CHSEL package's version, or None when it is not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("chsel")
    except PackageNotFoundError:
        return None


class ChselPeer:
    """CHSEL on one object: its SDF built once (vertices (V, 3), faces (F, 3), object frame),
    then :meth:`localize` per grasp."""

    def __init__(self, vertices, faces, *, resolution=SDF_RESOLUTION, padding=SDF_PADDING):
        if available() is None:
            raise ContactPoseError("CHSEL is not installed; install the peers' extra: pip install contactpose[peers]")
        import pytorch_volumetric as pv
        import torch
        import trimesh

        self.torch = torch
        self.dir = tempfile.mkdtemp(prefix="contactpose-chsel-")
        path = os.path.join(self.dir, "object.obj")
        trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces), process=False).export(path)
        start = time.perf_counter()
        obj = pv.MeshObjectFactory(path)
        exact = pv.MeshSDF(obj)
        self.sdf = pv.CachedSDF("object", resolution=resolution, range_per_dim=obj.bounding_box(padding=padding),
                                gt_sdf=exact, cache_path=os.path.join(self.dir, "sdf_cache.pkl"))
        # its model points depend on the SDF alone: built once here, the grasps' points set per grasp
        import chsel

        anchor = torch.tensor(np.asarray(vertices[:1], dtype=np.float32))
        self.registration = chsel.CHSEL(self.sdf, positions=anchor, semantics=[0.0])
        self.build_seconds = time.perf_counter() - start

    def localize(self, contacts, free_points, rng, *, scale, batch=BATCH, iterations=ITERATIONS):
        """Poses of the object from contact points (n, 3) and free points (M, 3), world frame.

        Starts: ``batch`` uniformly random rotations with the object's origin at the contacts'
        centroid plus N(0, scale²) per axis (the README's example draws N(0, 1 m²) about the
        world origin; our objects sit near the contacts). rng : numpy.random.Generator (it
        also seeds torch). -> (BaselineResult of the lowest-RMSE pose, poses (batch, 4, 4)
        T_world_object sorted by RMSE, RMSEs (batch,))
        """
        import chsel

        torch = self.torch
        torch.manual_seed(int(rng.integers(2**31)))
        registration = self.registration
        registration.reset_points(surface_pts=torch.tensor(np.asarray(contacts, dtype=np.float32)),
                                  free_pts=torch.tensor(np.asarray(free_points, dtype=np.float32)))
        start = np.repeat(np.eye(4)[None], batch, axis=0)
        start[:, :3, :3] = Rotation.random(batch, random_state=rng).as_matrix()
        start[:, :3, 3] = contacts.mean(axis=0) + rng.normal(0.0, scale, (batch, 3))
        world_to_link = torch.tensor(np.linalg.inv(start), dtype=torch.float32)
        res, _ = registration.register(iterations=iterations, batch=batch, initial_tsf=world_to_link)
        poses = np.linalg.inv(chsel.solution_to_world_to_link_matrix(res).cpu().numpy().astype(np.float64))
        rmse = res.rmse.detach().cpu().numpy().astype(np.float64)
        order = np.argsort(rmse)
        best = BaselineResult(poses[order[0]], float(rmse[order[0]]), batch * iterations, iterations)
        return best, poses[order], rmse[order]
