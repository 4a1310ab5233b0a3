"""A localization answer as one self-contained HTML page (plotly, its JavaScript inside the
page, so that it opens without a network).

:func:`localization_figure` draws the object at the best placement, the contacts with their
finger normals, the fingertips, the other placements (translucent, toggled in the legend)
and the directions that a pose family leaves free; :func:`track_figure` steps through a
tracked touch sequence with a slider; :func:`write_html` writes either as a page.

The inputs are plain arrays: vertices (V, 3), faces (F, 3) int, poses (4, 4)
T_world_object (x_w = R x_o + t), contact points and finger normals (n, 3) in the world
frame. A finger normal points into the object (contactpose.contacts), so a fingertip of
radius r touching at p has its centre at p - r·ñ (contactpose.scoring.freespace). Plotly is
imported only when a figure is made.
"""

from __future__ import annotations

import html
import os
import textwrap
from dataclasses import dataclass

import numpy as np

from contactpose import tol
from contactpose.errors import ContactPoseError, check_length

#: Lengths drawn, as shares of the object's diameter (its bounding-box diagonal): the finger
#: normals' arrows; the free directions' arrows, each way from the object's centre (past its
#: surface: no surface point is more than half the diameter from the centre) and their heads.
NORMAL_FRAC = 0.08
FREE_FRAC = 0.6
HEAD_FRAC = 0.04
#: Other placements drawn (the best-ranked first) and, of those, shown when the page opens;
#: the rest are in the legend, hidden until clicked.
MAX_OTHERS = 12
VISIBLE_OTHERS = 3
#: Longest title line (characters), and the lines a hint may take below it; a longer hint is cut
#: with an ellipsis.
TITLE_CHARS = 130
TITLE_LINES = 2
BEST_COLOR = "#f2d13a"
OTHER_COLORS = ("#4c78a8", "#e45756", "#54a24b", "#b279a2", "#ff9da6", "#9d755d", "#72b7b2")
OTHER_OPACITY = 0.25
TRUTH_COLOR = "#7f7f7f"
CONTACT_COLOR = "#c0392b"
EARLIER_COLOR = "#e8a09a"
NORMAL_COLOR = "#1f5fa8"
TIP_COLOR = "#8fa9c8"
FREE_COLOR = "#2ca02c"
ROTATION_COLOR = "#9467bd"
#: Camera distance from the scene's centre, in plotly's scene units per unit of the longest
#: side's aspect ratio (plotly's default camera is 2.17 from a cube of ratio 1).
EYE_DISTANCE = 1.25
#: Meshes are lit from the camera's direction, by a light this far out (plotly's limit is 1e5).
LIGHT_DISTANCE = 5e4
#: The page's plotly config: no logo link, a PNG button that saves at twice the size.
CONFIG = {"displaylogo": False, "toImageButtonOptions": {"format": "png", "scale": 2}}


@dataclass(frozen=True)
class TrackStep:
    """One step of a tracked sequence.

    pose : (4, 4) the tracked T_world_object; points, finger_normals : (N, 3) every contact so
    far, carried with the object to this pose (world frame); latest : how many of the last
    rows are this step's touch; true_pose : (4, 4) or None; caption : the step's title line.
    """

    pose: np.ndarray
    points: np.ndarray
    finger_normals: np.ndarray
    latest: int
    true_pose: np.ndarray | None = None
    caption: str = ""


# ------------------------------------------------------------------ figures ---

def localization_figure(vertices, faces, points, finger_normals, *, pose=None, best_name="best placement", others=(),
                        finger_radius=None, free_translation=None, free_rotation=None, title=""):
    """The page of one answer -> plotly Figure.

    vertices (V, 3), faces (F, 3) int: the object's mesh; points, finger_normals (n, 3): the
    contacts (world); pose : (4, 4) the best placement, or None (no answer: the contacts
    only); others : [(name, pose (4, 4))], the other placements, best first (MAX_OTHERS drawn);
    finger_radius : draw fingertips of this radius (None: none); free_translation (k, 3),
    free_rotation (3,) or None: world directions the best pose leaves free; title : its text
    (:func:`title_text`).
    """
    vertices, faces = compact(*check_mesh(vertices, faces))
    points, normals = check_contacts(points, finger_normals)
    radius = None if finger_radius is None else check_length(finger_radius, "finger_radius")
    size = diameter(vertices)
    traces, shown = [], [points]
    if pose is not None:
        pose = check_pose(pose, "pose")
        posed = moved(pose, vertices)
        traces.append(mesh_trace(posed, faces, best_name, BEST_COLOR))
        shown.append(posed)
    for rank, (name, other) in enumerate(list(others)[:MAX_OTHERS]):
        posed_other = moved(check_pose(other, f"pose of {name!r}"), vertices)
        traces.append(mesh_trace(posed_other, faces, name, OTHER_COLORS[rank % len(OTHER_COLORS)], OTHER_OPACITY,
                                 visible=True if rank < VISIBLE_OTHERS else "legendonly"))
        shown += [posed_other] if rank < VISIBLE_OTHERS else []
    traces += contact_traces(points, normals, NORMAL_FRAC * size, radius)
    if pose is not None:
        centre = moved(pose, (vertices.min(axis=0) + vertices.max(axis=0))[None] / 2)[0]  # the bounding box's
        traces += free_traces(centre, free_translation, free_rotation, FREE_FRAC * size, HEAD_FRAC * size)
    return figure(traces, title, scene(camera_eye(normals, EYE_DISTANCE * data_ratio(np.vstack(shown)))), size)


def track_figure(vertices, faces, steps, *, finger_radius=None, title=""):
    """A tracked sequence -> plotly Figure with a slider over its steps (the last shown first).

    vertices (V, 3), faces (F, 3) int: the object's mesh; steps : [TrackStep]; finger_radius :
    fingertips on each step's own touch (None: none); title : the page's first line, above
    each step's caption.
    """
    vertices, faces = compact(*check_mesh(vertices, faces))
    radius = None if finger_radius is None else check_length(finger_radius, "finger_radius")
    steps = list(steps)
    if not steps:
        raise ContactPoseError("track_figure needs at least one TrackStep, got none")
    size = diameter(vertices)
    groups, extent = [], []
    for k, step in enumerate(steps):
        traces, posed = step_traces(vertices, faces, step, k, NORMAL_FRAC * size, radius)
        groups.append(traces)
        extent += posed
    captions = [title_text(title, step.caption) if title else title_text(step.caption) for step in steps]
    for k, group in enumerate(groups):
        for trace in group:
            trace.visible = k == len(groups) - 1
    last = steps[-1]
    fig = figure([t for g in groups for t in g], captions[-1],
                 scene(camera_eye(last.finger_normals[len(last.points) - last.latest:]), np.vstack(extent)), size)
    fig.update_layout(sliders=[slider(groups, captions)])
    return fig


def step_traces(vertices, faces, step, k, length, radius):
    """The traces of TrackStep ``step`` (number k) and the points they span.
    -> ([traces], [(m, 3) arrays])"""
    pose = check_pose(step.pose, f"step {k} pose")
    points, normals = check_contacts(step.points, step.finger_normals, f"step {k} ")
    latest = int(step.latest)
    if not 0 < latest <= len(points):
        raise ContactPoseError(f"step {k}: latest must count 1 to {len(points)} of its contacts, got {step.latest!r}")
    posed = moved(pose, vertices)
    traces = [mesh_trace(posed, faces, "tracked pose", BEST_COLOR)]
    if step.true_pose is not None:
        traces.append(mesh_trace(moved(check_pose(step.true_pose, f"step {k} true pose"), vertices), faces,
                                 "true pose", TRUTH_COLOR, OTHER_OPACITY))
    cut = len(points) - latest
    if cut:
        traces.append(marker_trace(points[:cut], f"contacts of earlier touches ({cut}), carried with the object",
                                   EARLIER_COLOR, 4))
    traces += contact_traces(points[cut:], normals[cut:], length, radius, "contacts of this touch")
    return traces, [posed, points]


def slider(groups, captions):
    """A slider whose step k shows the traces of groups[k] only, and captions[k] as the title.
    groups : [[trace]] in figure order; captions : [str]."""
    owner = np.repeat(np.arange(len(groups)), [len(g) for g in groups])
    steps = [dict(label=str(k), method="update", args=[{"visible": (owner == k).tolist()}, {"title.text": caption}])
             for k, caption in enumerate(captions)]
    return dict(active=len(groups) - 1, steps=steps, currentvalue=dict(prefix="step "), pad=dict(t=10, b=10))


def figure(traces, title, scene_layout, size):
    """traces in one 3D scene, lit from the camera's side, with the title and a legend at the
    top left -> plotly Figure. size : the object's diameter: facets smaller than
    tol.AREA_REL · size² have no normal to light them by."""
    import plotly.graph_objects as go

    fig = go.Figure(traces)
    eye = scene_layout["camera"]["eye"]
    eps = tol.AREA_REL * size ** 2  # plotly's own default (1e-6) darkens the facets of a mesh in metres
    light = np.array([eye[k] for k in "xyz"])
    light *= LIGHT_DISTANCE / np.linalg.norm(light)
    fig.update_traces(lightposition=dict(zip("xyz", light.tolist())),
                      lighting=dict(facenormalsepsilon=eps, vertexnormalsepsilon=eps), selector=dict(type="mesh3d"))
    fig.update_layout(template="plotly_white", scene=scene_layout, margin=dict(l=0, r=0, t=80, b=0),
                      title=dict(text=title, x=0.01, xanchor="left", y=0.98, yanchor="top", font=dict(size=14)),
                      legend=dict(x=0.01, y=0.92, xanchor="left", yanchor="top", bgcolor="rgba(255,255,255,0.85)",
                                  bordercolor="#cccccc", borderwidth=1, font=dict(size=12)),
                      font=dict(family="Helvetica, Arial, sans-serif"))
    return fig


def scene(eye, points=None):
    """The 3D scene, one length scale on every axis, camera at ``eye`` (3,). Without points its
    ranges follow the traces shown (toggled in the legend); around points (m, 3) they are fixed,
    each axis spanning its points' range plus a margin (at least 0.3 of the largest, so that a
    flat object keeps depth)."""
    axes = {f"{name}axis": dict(title=dict(text=name), backgroundcolor="#f4f6fa", gridcolor="#d9dde6",
                                showbackground=True) for name in "xyz"}
    camera = dict(eye=dict(zip("xyz", eye.tolist())))
    if points is None:
        return dict(**axes, aspectmode="data", camera=camera)
    lo, hi = points.min(axis=0), points.max(axis=0)
    largest = max(float((hi - lo).max()), 1e-12)
    half = np.maximum(hi - lo, 0.3 * largest) / 2 + 0.06 * largest
    centre = (lo + hi) / 2
    for name, c, h in zip("xyz", centre, half):
        axes[f"{name}axis"]["range"] = [float(c - h), float(c + h)]
    return dict(**axes, aspectmode="manual", aspectratio=dict(zip("xyz", (half / half.max()).tolist())), camera=camera)


def data_ratio(points):
    """The largest of plotly's scene aspect ratios for points (m, 3) under aspectmode "data":
    the longest span over the geometric mean of the three (a cube's: 1)."""
    spans = np.ptp(points, axis=0)
    spans = np.maximum(spans, 1e-3 * max(float(spans.max()), 1e-300))
    return float(spans.max() / np.exp(np.log(spans).mean()))


def camera_eye(finger_normals, distance=EYE_DISTANCE):
    """(3,) camera position (plotly's scene units) looking at the contacts from outside: from the
    side of their mean outward normal, raised or lowered 20° to 35°. finger_normals : (n, 3)."""
    v = -np.mean(finger_normals, axis=0)
    if np.linalg.norm(v[:2]) < 1e-6:
        elev, azim = np.radians(25.0), np.radians(-60.0)
    else:
        elev = np.arctan2(v[2], np.linalg.norm(v[:2]))
        elev = np.copysign(np.clip(abs(elev), np.radians(20.0), np.radians(35.0)), elev)
        azim = np.arctan2(v[1], v[0])
    return distance * np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])


def title_text(headline, *notes):
    """Plotly title text: the headline in bold, cut to TITLE_CHARS; each note (a hint, say) in
    smaller type below it, cut to TITLE_LINES lines of TITLE_CHARS; all escaped."""
    if not headline:
        return ""
    lines = [f"<b>{html.escape(shorten(headline), quote=False)}</b>"]
    for note in filter(None, notes):
        wrapped = textwrap.wrap(shorten(note, TITLE_LINES * TITLE_CHARS), TITLE_CHARS)
        lines += [f"<span style='font-size:12px'>{html.escape(line, quote=False)}</span>" for line in wrapped]
    return "<br>".join(lines)


def shorten(text, width=TITLE_CHARS):
    """``text`` on one line, cut at a word to at most ``width`` characters with an ellipsis."""
    text = " ".join(str(text).split())
    if len(text) <= width:
        return text
    return text[:width - 1].rsplit(" ", 1)[0].rstrip(",;:") + "…"


# ------------------------------------------------------------------- traces ---

def mesh_trace(posed, faces, name, color, opacity=1.0, visible=True):
    """A Mesh3d of the posed vertices (V, 3) and faces (F, 3), with its legend entry; in single
    precision, which WebGL draws in (half the page)."""
    import plotly.graph_objects as go

    x, y, z = posed.astype(np.float32).T
    return go.Mesh3d(x=x, y=y, z=z, i=faces[:, 0], j=faces[:, 1], k=faces[:, 2],
                     name=name, color=color, opacity=opacity, flatshading=True, showlegend=True, visible=visible,
                     hoverinfo="name", lighting=dict(ambient=0.5, diffuse=0.8, specular=0.1, roughness=0.7))


def marker_trace(points, name, color, size=6, text=None):
    """The points (n, 3) as markers with a legend entry."""
    import plotly.graph_objects as go

    return go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers", name=name, text=text,
                        hoverinfo="text+name" if text else "name",
                        marker=dict(size=size, color=color, line=dict(color="white", width=1)))


def contact_traces(points, finger_normals, length, radius=None, name="contacts"):
    """The contacts (n, 3) as markers, their finger normals (n, 3) as arrows of ``length`` from
    outside to the contact, and fingertip spheres of ``radius`` (None: none) -> [traces]."""
    n = len(points)
    traces = [marker_trace(points, f"{name} ({n})", CONTACT_COLOR, text=[f"finger {i}" for i in range(n)])]
    traces += arrow_traces(points - length * finger_normals, points, "finger normals (into the object)",
                           NORMAL_COLOR, 0.3 * length)
    if radius is not None:
        traces.append(sphere_trace(points - radius * finger_normals, radius, f"fingertips (radius {radius:.3g})"))
    return traces


def free_traces(centre, free_translation, free_rotation, length, head):
    """The directions a pose family leaves free, drawn through the object's centre (3,) and
    ``length`` each way from it: each free translation (k, 3) as a two-headed arrow, the free
    rotation's axis (3,) as a line with a ring about it near either end; arrowheads ``head`` long.
    -> [traces]"""
    traces = []
    directions = np.zeros((0, 3)) if free_translation is None else check_vectors(free_translation, "free_translation")
    if len(directions):
        d = unit_rows(directions, "free_translation")
        ends = np.concatenate([centre + length * d, centre - length * d])
        traces += arrow_traces(np.broadcast_to(centre, ends.shape), ends,
                               f"free translation{'s' if len(d) > 1 else ''} ({len(d)})", FREE_COLOR, head)
    if free_rotation is not None:
        axis = unit_rows(check_vectors(np.reshape(free_rotation, (1, 3)), "free_rotation"), "free_rotation")[0]
        traces += rotation_traces(centre, axis, length, head)
    return traces


def rotation_traces(centre, axis, length, head):
    """A free rotation about ``axis`` (3,) through ``centre`` (3,): the axis as a line ``length``
    each way, and near either end a ring about it with an arrowhead ``head`` long. -> [traces]"""
    import plotly.graph_objects as go

    name = "free rotation (about this axis)"
    e1, e2 = perpendiculars(axis[None])
    phi = np.linspace(0.0, 1.75 * np.pi, 64)[:, None]
    circle = 2 * head * (np.cos(phi) * e1 + np.sin(phi) * e2)
    rings = [centre + side * 0.85 * length * axis + circle for side in (1.0, -1.0)]
    gap = [[np.nan] * 3]
    xyz = np.concatenate([[centre - length * axis, centre + length * axis], gap, rings[0], gap, rings[1]])
    step = circle[-1] - circle[-2]
    tips = np.array([ring[-1] + head * step / np.linalg.norm(step) for ring in rings])
    return [go.Scatter3d(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="lines", name=name, legendgroup=name,
                         line=dict(color=ROTATION_COLOR, width=5), hoverinfo="name"),
            _solid(cone_mesh(tips, np.array([step, step]), head), name, ROTATION_COLOR, legendgroup=name)]


def arrow_traces(tails, tips, name, color, head):
    """Arrows from tails (k, 3) to tips (k, 3), heads ``head`` long: the shafts as one line
    trace, the heads as one mesh, one legend entry -> [traces]."""
    import plotly.graph_objects as go

    shafts = np.stack([tails, tips, np.full_like(tips, np.nan)], axis=1).reshape(-1, 3)
    return [go.Scatter3d(x=shafts[:, 0], y=shafts[:, 1], z=shafts[:, 2], mode="lines", name=name, legendgroup=name,
                         line=dict(color=color, width=5), hoverinfo="name"),
            _solid(cone_mesh(tips, tips - tails, head), name, color, legendgroup=name)]


def sphere_trace(centres, radius, name):
    """Spheres of ``radius`` at centres (n, 3) as one translucent mesh."""
    unit, faces = unit_sphere()
    vertices = (centres[:, None, :] + radius * unit[None]).reshape(-1, 3)
    faces = (faces[None] + len(unit) * np.arange(len(centres))[:, None, None]).reshape(-1, 3)
    return mesh_trace(vertices, faces, name, TIP_COLOR, 0.35)


def _solid(mesh, name, color, legendgroup):
    """A mesh (vertices (V, 3), faces (F, 3)) in one colour, in ``legendgroup`` without an entry."""
    trace = mesh_trace(*mesh, name, color)
    trace.update(showlegend=False, legendgroup=legendgroup, flatshading=False)
    return trace


# ----------------------------------------------------------------- geometry ---

def compact(vertices, faces):
    """The mesh without coincident or unused vertices (a triangle soup, as an STL file loads,
    shares none): a page draws each vertex once. -> (vertices (V', 3), faces (F, 3))"""
    kept, inverse = np.unique(vertices[faces].reshape(-1, 3), axis=0, return_inverse=True)
    return kept, inverse.reshape(-1, 3)


def moved(T, points):
    """(m, 3) points moved by the pose T (4, 4): R x + t."""
    return points @ T[:3, :3].T + T[:3, 3]


def diameter(vertices):
    """The bounding-box diagonal of vertices (V, 3)."""
    return float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))


def perpendiculars(directions):
    """Two unit vectors (k, 3) each, perpendicular to directions (k, 3) and to each other."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(d, e1)


def cone_mesh(tips, directions, height, segments=12):
    """Arrowheads: a cone of ``height`` (base radius a third of it) ending at each tip (k, 3),
    pointing along directions (k, 3). -> (vertices (k (segments + 2), 3), faces (2 k segments, 3))"""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    e1, e2 = perpendiculars(d)
    phi = 2 * np.pi * np.arange(segments) / segments
    base = tips - height * d
    ring = base[:, None] + (height / 3) * (np.cos(phi)[None, :, None] * e1[:, None] + np.sin(phi)[None, :, None] * e2[:, None])
    vertices = np.concatenate([tips[:, None], base[:, None], ring], axis=1).reshape(-1, 3)
    j = np.arange(segments)
    one = np.concatenate([np.stack([np.zeros(segments), 2 + j, 2 + (j + 1) % segments], axis=1),
                          np.stack([np.ones(segments), 2 + (j + 1) % segments, 2 + j], axis=1)]).astype(np.int64)
    faces = one[None] + (segments + 2) * np.arange(len(tips))[:, None, None]
    return vertices, faces.reshape(-1, 3)


def unit_sphere(rings=10, segments=20):
    """A UV sphere of radius 1 about the origin -> (vertices (V, 3), faces (F, 3) int)."""
    theta = np.pi * np.arange(1, rings) / rings
    phi = 2 * np.pi * np.arange(segments) / segments
    grid = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.sin(theta), np.sin(phi)),
                     np.outer(np.cos(theta), np.ones(segments))], axis=-1).reshape(-1, 3)
    vertices = np.concatenate([[[0.0, 0.0, 1.0]], grid, [[0.0, 0.0, -1.0]]])
    j, nxt = np.arange(segments), (np.arange(segments) + 1) % segments
    r = np.arange(rings - 2)[:, None]
    a, b = 1 + r * segments + j, 1 + r * segments + nxt
    bottom, last = len(vertices) - 1, 1 + (rings - 2) * segments
    faces = np.concatenate([np.stack([np.zeros(segments, np.int64), 1 + j, 1 + nxt], axis=1),
                            np.stack([a, a + segments, b + segments], axis=-1).reshape(-1, 3),
                            np.stack([a, b + segments, b], axis=-1).reshape(-1, 3),
                            np.stack([np.full(segments, bottom), last + nxt, last + j], axis=1)])
    return vertices, faces.astype(np.int64)


# ------------------------------------------------------------------- checks ---

def check_vectors(values, name, n=None):
    """values -> (n, 3) float64 of finite numbers, else ContactPoseError naming ``name``."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ContactPoseError(f"{name} must be numbers of shape (n, 3), got {values!r:.80}") from None
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and len(arr) != n):
        raise ContactPoseError(f"{name} must have shape ({'n' if n is None else n}, 3), got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ContactPoseError(f"{name} has a NaN or inf entry in row {np.flatnonzero(~np.isfinite(arr).all(axis=1))[0]}; "
                               "every entry must be a finite number")
    return arr


def unit_rows(vectors, name):
    """vectors (k, 3) scaled to unit length; a zero row is a ContactPoseError naming ``name``."""
    norms = np.linalg.norm(vectors, axis=1)
    if (norms < 1e-12).any():
        raise ContactPoseError(f"{name} row {np.flatnonzero(norms < 1e-12)[0]} is a zero vector; need a direction")
    return vectors / norms[:, None]


def check_mesh(vertices, faces):
    """-> (vertices (V, 3) float64, faces (F, 3) int64 indexing them), else ContactPoseError."""
    vertices = check_vectors(vertices, "vertices")
    try:
        arr = np.asarray(faces)
    except (TypeError, ValueError):
        arr = np.empty(0)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0 or not np.issubdtype(arr.dtype, np.integer):
        raise ContactPoseError(f"faces must be integers of shape (F, 3), F >= 1, got {_described(arr)}")
    if arr.min() < 0 or arr.max() >= len(vertices):
        raise ContactPoseError(f"faces must index the {len(vertices)} vertices (0 to {len(vertices) - 1}), got "
                               f"indices {arr.min()} to {arr.max()}")
    return vertices, arr.astype(np.int64)


def check_contacts(points, finger_normals, prefix=""):
    """-> (points (n, 3), unit finger normals (n, 3)), n >= 1, else ContactPoseError."""
    points = check_vectors(points, f"{prefix}contact points")
    if not len(points):
        raise ContactPoseError(f"{prefix}contact points: need at least 1 contact, got 0")
    normals = check_vectors(finger_normals, f"{prefix}finger normals", len(points))
    norms = np.linalg.norm(normals, axis=1)
    if np.abs(norms - 1.0).max() > tol.UNIT_NORM:
        i = int(np.argmax(np.abs(norms - 1.0)))
        raise ContactPoseError(f"{prefix}finger normals must be unit vectors, row {i} has length {norms[i]:.6g}")
    return points, normals


def check_pose(T, name):
    """T -> (4, 4) float64 if it is a rigid transform, else ContactPoseError naming ``name``."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise ContactPoseError(f"{name} must be a 4x4 matrix of numbers, got {T!r:.80}") from None
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ContactPoseError(f"{name} must be a finite 4x4 matrix, got {_described(T)}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ContactPoseError(f"{name} must be a rigid transform (a rotation, a translation, last row [0, 0, 0, 1])")
    return T


def _described(arr):
    """'shape (a, b) of dtype' of an array, for error messages."""
    return f"shape {arr.shape} of {arr.dtype}"


# -------------------------------------------------------------------- pages ---

def check_page_path(path):
    """``path`` as a str if a page can be written there (its folder exists, it is no folder),
    else ContactPoseError naming it: checked before a long computation."""
    try:
        target = os.fspath(path)
    except TypeError:
        raise ContactPoseError(f"the page's path must be a file path, got {path!r:.80}") from None
    folder = os.path.dirname(os.path.abspath(target))
    if os.path.isdir(target):
        raise ContactPoseError(f"cannot write the page {target!r}: it is a folder; give a file name such as view.html")
    if not os.path.isdir(folder):
        raise ContactPoseError(f"cannot write the page {target!r}: folder {folder!r} does not exist")
    return target


def write_html(fig, path):
    """Write the Figure ``fig`` to ``path`` as one HTML page that opens offline (plotly.js inside,
    no MathJax). -> the path written"""
    target = check_page_path(path)
    try:
        fig.write_html(target, include_plotlyjs=True, include_mathjax=False, full_html=True, config=CONFIG)
    except OSError as exc:
        raise ContactPoseError(f"cannot write the page {target!r}: {exc.strerror or exc}") from None
    return target
