"""Figures with matplotlib: the object under a pose, the contacts and their normals."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402


def transform(T, points):
    """Apply a (4, 4) pose to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def plot_localization(model, contacts, pose, path, *, true_pose=None, title=""):
    """Save a PNG of the object at ``pose`` (and, faintly, ``true_pose``) with the contacts.

    pose, true_pose : (4, 4) T_world_object; contacts in the world frame.
    """
    fig = plt.figure(figsize=(6.4, 5.2), dpi=130)
    ax = fig.add_subplot(projection="3d")
    tri = model.triangles[model.planes.valid]
    if true_pose is not None:
        ax.add_collection3d(Poly3DCollection(
            [transform(true_pose, t) for t in tri], facecolor="none", edgecolor="0.6", linewidths=0.4))
    ax.add_collection3d(Poly3DCollection(
        [transform(pose, t) for t in tri], facecolor="#f2d13a", edgecolor="#8a7100", linewidths=0.5, alpha=0.55))
    p, nf = contacts.points, contacts.finger_normals
    L = 0.15 * model.diameter
    ax.scatter(*p.T, color="#c0392b", s=28, depthshade=False, label="contacts")
    ax.quiver(*p.T, *(nf * L).T, color="#2c3e50", linewidth=1.2, label="finger normals")
    _equal_axes(ax, transform(pose, model.vertices))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _equal_axes(ax, points):
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2 * 1.1
    for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        set_lim(c - half, c + half)
