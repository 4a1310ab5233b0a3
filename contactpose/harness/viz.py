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


#: Share of the figure's height below the panels that holds the legend.
LEGEND_HEIGHT = 0.1


def plot_localization(model, contacts, pose, path, *, true_pose=None, title="", costs=None, threshold=None,
                      length_unit="m"):
    """Save a PNG: the estimate shaded, the truth as a wireframe over it, the contacts with
    their finger normals drawn from outside the object toward each contact, on axes of one
    scale, and (with ``costs``) a panel of the hypotheses' costs; one legend below the panels,
    covering none of them.

    pose, true_pose : (4, 4) T_world_object; contacts in the world frame; costs : dict
    label -> (H,) costs of the ranked hypotheses (χ²); threshold : the fit threshold line;
    length_unit : the axes' label unit.
    """
    fig = plt.figure(figsize=(11.0 if costs else 6.4, 5.6), dpi=130)
    grid = fig.add_gridspec(1, 2, width_ratios=(1.35, 1.0)) if costs else fig.add_gridspec(1, 1)
    ax = fig.add_subplot(grid[0], projection="3d")
    ax.computed_zorder = False  # draw in the order added: surfaces first, contacts on top
    _draw_object(ax, model, pose, true_pose)
    length = 0.25 * model.diameter
    _draw_contacts(ax, contacts, length)
    tails = contacts.points - length * contacts.finger_normals
    _equal_axes(ax, np.vstack([transform(pose, model.vertices), contacts.points, tails]))
    ax.view_init(*_view_angles(contacts))
    for set_label, name in zip((ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), "xyz"):
        set_label(f"{name} [{length_unit}]", fontsize=8)
    ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    handles = _legend(true_pose is not None)
    if costs:
        handles += _plot_costs(fig.add_subplot(grid[1]), costs, threshold)
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 4), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0.0, LEGEND_HEIGHT, 1.0, 0.96))
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
    """The ranked hypotheses' costs per method, with the fit threshold, every marker inside
    the frame. -> the legend handles"""
    handles, top, count = [], 1.0 if threshold is None else threshold, 1
    for (label, values), (marker, size) in zip(costs.items(), (("o", 9), ("s", 4), ("^", 4))):
        values = np.asarray(values, dtype=float)
        n = len(values)
        handles += ax.plot(np.arange(1, n + 1), values, marker, ms=size, mfc="none" if size > 5 else None,
                           label=f"{label} ({n} hypothes{'i' if n == 1 else 'e'}s)")
        top, count = max([top, *values[np.isfinite(values)]]), max(count, n)
    if threshold is not None:
        handles.append(ax.axhline(threshold, color="0.3", ls="--", lw=0.8,
                                  label=f"fits within noise: χ² ≤ {threshold:.3g}"))
    ax.set_yscale("symlog", linthresh=1.0)  # a perfect fit (χ² = 0) stays on the plot
    ax.set_ylim(-0.5, 10.0 ** (np.log10(max(top, 1.0)) + 0.5))  # half a decade above the highest marker
    ax.set_xlim(0.4, count + 0.6)
    ax.set_xticks(np.arange(1, count + 1) if count <= 12 else ax.get_xticks())
    ax.set_xlabel("hypothesis rank", fontsize=8)
    ax.set_ylabel("χ² of the contacts (whitened, unitless)", fontsize=8)
    ax.set_title("hypotheses, best first", fontsize=9)
    ax.tick_params(labelsize=7)
    return handles


def _view_angles(contacts):
    """(elev, azim) in degrees looking at the contacts from outside, from the side of their
    mean outward normal, raised or lowered by 20° to 35° so the object keeps its depth and
    its outline."""
    v = -contacts.finger_normals.mean(axis=0)
    if np.linalg.norm(v[:2]) < 1e-6:
        return 25.0, -60.0
    elev = np.degrees(np.arctan2(v[2], np.linalg.norm(v[:2])))
    return float(np.copysign(np.clip(abs(elev), 20.0, 35.0), elev)), float(np.degrees(np.arctan2(v[1], v[0])))


def _equal_axes(ax, points, least=0.3, pad=0.04):
    """Limits around the points with one length scale on every axis: each axis spans its
    points' range plus ``pad`` of the largest (at least ``least`` of the largest, so a flat
    object keeps a visible depth), and the box's sides are in proportion to those spans."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    largest = (hi - lo).max()
    half = np.maximum(hi - lo, least * largest) / 2 + pad * largest
    centre = (lo + hi) / 2
    for set_lim, c, h in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, half):
        set_lim(c - h, c + h)
    ax.set_box_aspect(half / half.max(), zoom=1.2)
