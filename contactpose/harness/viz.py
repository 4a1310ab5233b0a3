"""Figures with matplotlib: the object under a pose, the contacts and their normals."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection  # noqa: E402

ESTIMATE_COLOR = "#f2d13a"
TRUTH_COLOR = "#2b2b2b"
CONTACT_COLOR = "#c0392b"
NORMAL_COLOR = "#1f5fa8"


def transform(T, points):
    """Apply a (4, 4) pose to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def plot_localization(model, contacts, pose, path, *, true_pose=None, title="", costs=None, threshold=None):
    """Save a PNG: the estimate shaded, the truth as a wireframe over it, the contacts with
    their finger normals drawn from outside the object toward each contact, a legend, and
    (with ``costs``) a panel of the hypotheses' costs.

    pose, true_pose : (4, 4) T_world_object; contacts in the world frame; costs : dict
    label -> (H,) costs of the ranked hypotheses (χ²); threshold : the fit threshold line.
    """
    fig = plt.figure(figsize=(10.5 if costs else 6.4, 5.2), dpi=130)
    ax = fig.add_subplot(1, 2 if costs else 1, 1, projection="3d")
    ax.computed_zorder = False  # draw in the order added: surfaces first, contacts on top
    _draw_object(ax, model, pose, true_pose)
    _draw_contacts(ax, contacts, 0.25 * model.diameter)
    _equal_axes(ax, np.vstack([transform(pose, model.vertices), contacts.points]))
    ax.view_init(*_view_angles(contacts))
    for set_label, name in zip((ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), "xyz"):
        set_label(f"{name} [m]", fontsize=8)
    ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    ax.legend(handles=_legend(true_pose is not None), loc="upper left", fontsize=8, framealpha=0.9)
    if costs:
        _plot_costs(fig.add_subplot(1, 2, 2), costs, threshold)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _draw_object(ax, model, pose, true_pose):
    tri = model.triangles[model.planes.valid]
    ax.add_collection3d(Poly3DCollection([transform(pose, t) for t in tri], facecolor=ESTIMATE_COLOR,
                                         edgecolor="#b89a10", linewidths=0.3, alpha=0.45))
    if true_pose is not None:
        edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        ax.add_collection3d(Line3DCollection([transform(true_pose, e) for e in edges], colors=TRUTH_COLOR,
                                             linewidths=0.5, alpha=0.8))


def _draw_contacts(ax, contacts, length):
    """Each finger normal as an arrow from outside the object to its contact."""
    p, nf = contacts.points, contacts.finger_normals
    tail = p - length * nf
    ax.quiver(*tail.T, *(length * nf).T, color=NORMAL_COLOR, linewidth=1.6, arrow_length_ratio=0.25)
    ax.scatter(*p.T, color=CONTACT_COLOR, s=40, depthshade=False, edgecolors="white", linewidths=0.6)


def _legend(with_truth):
    handles = [Patch(facecolor=ESTIMATE_COLOR, alpha=0.6, label="estimated pose")]
    if with_truth:
        handles.append(Line2D([], [], color=TRUTH_COLOR, lw=0.8, label="true pose (wireframe)"))
    handles += [Line2D([], [], color=CONTACT_COLOR, marker="o", lw=0, label="contacts"),
                Line2D([], [], color=NORMAL_COLOR, lw=1.6, label="finger normals (into the object)")]
    return handles


def _plot_costs(ax, costs, threshold):
    """The ranked hypotheses' costs per method, with the fit threshold."""
    for (label, values), (marker, size) in zip(costs.items(), (("o", 9), ("s", 4), ("^", 4))):
        values = np.asarray(values, dtype=float)
        ax.plot(np.arange(1, len(values) + 1), values, marker, ms=size, mfc="none" if size > 5 else None,
                label=f"{label} ({len(values)} hypotheses)")
    if threshold is not None:
        ax.axhline(threshold, color="0.3", ls="--", lw=0.8, label=f"fits within noise: χ² ≤ {threshold:.3g}")
    ax.set_yscale("symlog", linthresh=1.0)  # a perfect fit (χ² = 0) stays on the plot
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("hypothesis rank", fontsize=8)
    ax.set_ylabel("χ² of the contacts (whitened)", fontsize=8)
    ax.set_title("hypotheses, best first", fontsize=9)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)


def _view_angles(contacts):
    """(elev, azim) in degrees looking at the contacts from outside, from the side of their
    mean outward normal, raised or lowered by at most 20° so the object keeps its depth."""
    v = -contacts.finger_normals.mean(axis=0)
    if np.linalg.norm(v[:2]) < 1e-6:
        return 25.0, -60.0
    elev = np.degrees(np.arctan2(v[2], np.linalg.norm(v[:2])))
    return float(np.clip(elev, -20.0, 20.0)), float(np.degrees(np.arctan2(v[1], v[0])))


def _equal_axes(ax, points):
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2 * 1.05
    for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        set_lim(c - half, c + half)
