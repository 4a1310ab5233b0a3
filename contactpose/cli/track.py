"""``contactpose track``: follow an object held in a moving hand, touch after touch."""

from __future__ import annotations

import os
import textwrap

import numpy as np

from contactpose import view
from contactpose.cli.common import add_noise_options, add_parser, model_or_mesh, warn_in_vain
from contactpose.errors import ContactPoseError, check_count
from contactpose.geometry.metrics import rotation_error_deg, translation_error
from contactpose.io import jsonfiles, output
from contactpose.localize import localize
from contactpose.model.symmetry import symmetry
from contactpose.sim import objects
from contactpose.tracking.session import relocalizer
from contactpose.tracking.track import MAX_TRACKS, TrackSet


def register(subparsers):
    """Add ``track MODEL_OR_MESH --sequence SEQ.json [...]``; handler :func:`run`."""
    p = add_parser(subparsers, "track", help="follow an object held in a moving hand, touch after touch",
                   description="Localize the first grasp of SEQ.json, then follow every pose it leaves through "
                               "the later touches (iSAM2 per track, the hand motions and slip as given), "
                               "keeping the tracks whose touches fit best.")
    p.add_argument("model", metavar="MODEL_OR_MESH", help="model .npz, mesh file or built-in object name")
    p.add_argument("--sequence", required=True, metavar="SEQ.json",
                   help='{"steps": [{"contacts": [...], "hand_motion": {"delta": 4x4, "sigma_rot_deg": a, '
                        '"sigma_trans": b}, "true_pose": 4x4}, ...]}; step 0 is the first grasp')
    add_noise_options(p)
    p.add_argument("--max-tracks", type=int, default=MAX_TRACKS, metavar="N", help="tracks kept")
    p.add_argument("--no-reseed", action="store_true",
                   help="no new tracks, localized afresh, on a touch that no track explains")
    p.add_argument("--association-samples", type=int, default=0, metavar="N",
                   help="write each final track's association covariance from N drawn trajectories (the Laplace "
                        "covariance plus the spread that the choice of facets adds; 20 is the default of the API)")
    p.add_argument("--seed", type=int, metavar="S", help="seed for --association-samples (default: a fresh one)")
    p.add_argument("-o", "--output", metavar="OUT.json", help="write the trajectory and the tracks as JSON")
    p.add_argument("--plot", metavar="OUT.png", help="plot the pose error over the steps, modulo the object's "
                                                     "symmetry and raw (needs true_pose)")
    p.add_argument("--html", metavar="PAGE.html",
                   help="write a 3D page that opens offline in a browser, with a slider over the steps: the best "
                        "track's pose, every contact so far carried with the object (this step's touch with its "
                        "normals) and the true pose where the sequence gives it")
    p.add_argument("--finger-radius", type=float, metavar="R",
                   help="with --html: draw fingertips of this radius on each step's touch (default: none)")
    p.set_defaults(func=run)


def run(args):
    """Track, print a line per step; 0 on success."""
    check_count(args.association_samples, "--association-samples", minimum=0)
    if args.seed is not None and not args.association_samples:
        warn_in_vain("--seed", "without --association-samples")
    if args.association_samples and not args.output:
        warn_in_vain("--association-samples", "without -o (the covariances go into OUT.json)")
    if args.finger_radius is not None and not args.html:
        warn_in_vain("--finger-radius", "without --html (it draws the fingertips)")
    if args.html:
        view.check_page_path(args.html)  # before the model is built
    model = model_or_mesh(args.model)
    steps = jsonfiles.read_sequence(args.sequence)
    group = symmetry(model)
    first, _, truth = steps[0]
    result = localize(model, first, position_noise=args.position_noise, normal_noise_deg=args.normal_noise_deg,
                      keep="all")
    if result.best is None:
        raise ContactPoseError(f"the first grasp has no hypothesis (status {result.status}): nothing to track")
    tracks = TrackSet(model, first, [(h.facets, h.pose) for h in result.hypotheses], result.tolerance,
                      max_tracks=args.max_tracks, seeder=None if args.no_reseed else relocalizer(model, result.tolerance))
    rows = [_row(0, tracks, truth, group)]
    shown = [_shown(tracks, first.n, truth)] if args.html else None
    for k, (contacts, motion, truth) in enumerate(steps[1:], 1):
        tracks.add(contacts, hand_motion=motion)
        rows.append(_row(k, tracks, truth, group))
        if args.html:
            shown.append(_shown(tracks, contacts.n, truth))
    metres = _in_metres(args.model)
    for before, r in zip([0] + [r["reseeds"] for r in rows], rows):
        reseeded = " (reseeded: no track explained the touch)" if r["reseeds"] > before else ""
        print(f"step {r['step']}: {r['tracks']} track(s), t = [{', '.join(f'{x:.4g}' for x in r['pose'][0:3, 3])}]"
              + reseeded + _error_text(r, group, metres))
    if args.output:
        rng = np.random.default_rng(args.seed)
        spread = ([t.association_covariance(rng, args.association_samples) for t in tracks.tracks]
                  if args.association_samples else None)
        jsonfiles.write_json(args.output, output.track_dict(result.status, rows, tracks, spread,
                                                            symmetry="" if group.trivial else group.describe()))
    if args.plot:
        _plot(rows, args.plot, group, metres)
    if args.html:
        _page(model, shown, rows, group, metres, args)
    return 0


def _shown(tracks, latest, truth):
    """What the page shows of a step: the best track's pose, every touch so far carried with
    it to that pose (PoseTrack.seen_now), the last ``latest`` contacts this step's, the true
    pose (or None). -> view.TrackStep without its caption"""
    seen, _ = tracks.best.seen_now()
    return view.TrackStep(tracks.best.pose, seen.points, seen.finger_normals, latest, truth)


def _page(model, shown, rows, group, metres, args):
    """Write the page of --html: a slider over the steps, each captioned as its printed line."""
    steps = [view.TrackStep(s.pose, s.points, s.finger_normals, s.latest, s.true_pose,
                            _caption(r, len(s.points), group, metres)) for s, r in zip(shown, rows)]
    fig = view.track_figure(model.vertices, model.faces, steps, finger_radius=args.finger_radius,
                            title=f"{args.model}: tracked over {len(steps)} steps")
    view.write_html(fig, args.html)


def _caption(row, seen, group, metres):
    """A step's line on the page: its printed line's counts and errors, and ``seen``, the
    contacts so far."""
    error = _error_text(row, group, metres).strip()
    return f"step {row['step']}: {row['tracks']} track(s), {seen} contacts so far" + (f"; {error}" if error else "")


def _row(step, tracks, truth, group):
    """One step's JSON row: the best track's pose, the tracks kept and the error against the
    truth (None without one), raw and modulo the object's symmetry ``group``."""
    pose = tracks.best.pose
    rot, trans = (None, None) if truth is None else (float(x) for x in group.errors(pose, truth))
    return dict(step=step, pose=pose, tracks=len(tracks.tracks), reseeds=tracks.reseeds, score=tracks.best.score,
                rot_err_deg=None if truth is None else float(rotation_error_deg(pose, truth)),
                trans_err=None if truth is None else float(translation_error(pose, truth)),
                rot_err_sym_deg=rot, trans_err_sym=trans)


def _in_metres(name):
    """Whether lengths are known to be metres: a built-in object (the procedural ones and the
    YCB meshes are in metres); a mesh or model file's unit is its own, which the library never
    learns."""
    return objects.is_builtin(name) and not os.path.exists(name)


def _length(x, metres):
    """'1.29 mm' for metres, else '0.001294 mesh units'."""
    return f"{1e3 * x:.2f} mm" if metres else f"{x:.4g} mesh units"


def _error_text(row, group, metres):
    """'  error 0.43° (raw 179.70°), 1.29 mm (raw 1.30 mm)': modulo the symmetry, then raw; the
    raw values alone, unlabelled, for an object without symmetry; '' without a true pose."""
    if row["rot_err_deg"] is None:
        return ""
    raw = f"{row['rot_err_deg']:.2f}°", _length(row["trans_err"], metres)
    if group.trivial:
        return f"  error {raw[0]}, {raw[1]}"
    return (f"  error {row['rot_err_sym_deg']:.2f}° (raw {raw[0]}), {_length(row['trans_err_sym'], metres)} "
            f"(raw {raw[1]})")


def _plot(rows, path, group, metres):
    """Rotation and translation error of the best track over the steps (integer ticks): modulo
    the object's symmetry on the left axis, the raw error (dashed) on its own scale on the
    right, since a symmetric twin's raw error can be 180° where the error modulo symmetry is
    a degree; the error alone for an object without symmetry."""
    shown = [r for r in rows if r["rot_err_deg"] is not None]
    if not shown:
        raise ContactPoseError("--plot needs true_pose in the sequence's steps")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    scale, unit = (1e3, "mm") if metres else (1.0, "mesh units")
    fig, panels = plt.subplots(2, 1, sharex=True, figsize=(6.4, 4.8))
    steps = [r["step"] for r in shown]
    series = (("rotation error (°)", "rot_err_sym_deg", "rot_err_deg", 1.0),
              (f"translation error ({unit})", "trans_err_sym", "trans_err", scale))
    for ax, (name, modulo, raw, factor) in zip(panels, series):
        if group.trivial:
            ax.plot(steps, [factor * r[raw] for r in shown], marker="o", ms=4)
            ax.set_ylabel(name)
        else:
            ax.plot(steps, [factor * r[modulo] for r in shown], marker="o", ms=4, color="C0", label="modulo symmetry")
            other = ax.twinx()
            other.plot(steps, [factor * r[raw] for r in shown], marker=".", ls="--", color="C1", label="raw (right axis)")
            other.set_ylim(0, 1.15 * max(factor * r[raw] for r in shown) or 1.0)
            other.set_ylabel("raw", color="C1")
            ax.set_ylabel(name.replace(" error", " error\nmodulo symmetry"), color="C0")
            ax.legend(handles=ax.get_lines() + other.get_lines(), fontsize=8, loc="upper left")
        ax.set_ylim(0, 1.15 * max(factor * r[raw if group.trivial else modulo] for r in shown) or 1.0)
        ax.grid(alpha=0.3)
    panels[-1].set_xlabel("step")
    panels[-1].xaxis.set_major_locator(MaxNLocator(integer=True))
    title = "best track against the true pose"
    title += " (the object has no symmetry)" if group.trivial else "\n" + textwrap.fill(f"symmetry: {group.describe()}", 90)
    panels[0].set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
