"""``contactpose track``: follow an object held in a moving hand, touch after touch."""

from __future__ import annotations

import numpy as np

from contactpose.cli.common import add_noise_options, add_parser, model_or_mesh, warn_in_vain
from contactpose.errors import ContactPoseError, check_count
from contactpose.geometry.metrics import rotation_error_deg, translation_error
from contactpose.io import jsonfiles, output
from contactpose.localize import localize
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
    p.add_argument("--plot", metavar="OUT.png", help="plot the pose error over the steps (needs true_pose)")
    p.set_defaults(func=run)


def run(args):
    """Track, print a line per step; 0 on success."""
    check_count(args.association_samples, "--association-samples", minimum=0)
    if args.seed is not None and not args.association_samples:
        warn_in_vain("--seed", "without --association-samples")
    if args.association_samples and not args.output:
        warn_in_vain("--association-samples", "without -o (the covariances go into OUT.json)")
    model = model_or_mesh(args.model)
    steps = jsonfiles.read_sequence(args.sequence)
    first, _, truth = steps[0]
    result = localize(model, first, position_noise=args.position_noise, normal_noise_deg=args.normal_noise_deg,
                      keep="all")
    if result.best is None:
        raise ContactPoseError(f"the first grasp has no hypothesis (status {result.status}): nothing to track")
    tracks = TrackSet(model, first, [(h.facets, h.pose) for h in result.hypotheses], result.tolerance,
                      max_tracks=args.max_tracks, seeder=None if args.no_reseed else relocalizer(model, result.tolerance))
    rows = [_row(0, tracks, truth)]
    for k, (contacts, motion, truth) in enumerate(steps[1:], 1):
        tracks.add(contacts, hand_motion=motion)
        rows.append(_row(k, tracks, truth))
    for before, r in zip([0] + [r["reseeds"] for r in rows], rows):
        err = "" if r["rot_err_deg"] is None else f"  error {r['rot_err_deg']:.2f} deg, {r['trans_err']:.4g}"
        reseeded = " (reseeded: no track explained the touch)" if r["reseeds"] > before else ""
        print(f"step {r['step']}: {r['tracks']} track(s), t = [{', '.join(f'{x:.4g}' for x in r['pose'][0:3, 3])}]"
              + reseeded + err)
    if args.output:
        rng = np.random.default_rng(args.seed)
        spread = ([t.association_covariance(rng, args.association_samples) for t in tracks.tracks]
                  if args.association_samples else None)
        jsonfiles.write_json(args.output, output.track_dict(result.status, rows, tracks, spread))
    if args.plot:
        _plot(rows, args.plot)
    return 0


def _row(step, tracks, truth):
    pose = tracks.best.pose
    return dict(step=step, pose=pose, tracks=len(tracks.tracks), reseeds=tracks.reseeds, score=tracks.best.score,
                rot_err_deg=None if truth is None else rotation_error_deg(pose, truth),
                trans_err=None if truth is None else translation_error(pose, truth))


def _plot(rows, path):
    """Rotation and translation error of the best track over the steps."""
    shown = [r for r in rows if r["rot_err_deg"] is not None]
    if not shown:
        raise ContactPoseError("--plot needs true_pose in the sequence's steps")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, sharex=True, figsize=(6, 4))
    steps = [r["step"] for r in shown]
    a.plot(steps, [r["rot_err_deg"] for r in shown], marker=".")
    b.plot(steps, [r["trans_err"] for r in shown], marker=".")
    a.set_ylabel("rotation error (deg)")
    b.set_ylabel("translation error (mesh units)")
    b.set_xlabel("step")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
