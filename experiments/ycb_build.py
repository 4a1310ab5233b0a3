"""What a YCB object's model costs: the first ``contactpose localize ycb:NAME`` (the model built
and stored in the model cache) and the second, in a new process (the model read from the
cache; SECOND_CALLS of them, their median and slowest), each timed as a whole (wall clock,
interpreter start included) with its peak memory;
the build's own seconds (the cache's note), the model file's size and its regions. Between
the two calls the new file is written back to disk (sync), as it is by the time a user calls
again.

Each call runs in its own process with an empty model cache of its own (CONTACTPOSE_CACHE_DIR
in a temporary folder); the grasp is 4 contacts at random facet points with noise 0.5 mm and
1°, from a light model of the same mesh. Writes results/ycb_build/build.csv and build.md::

    .venv/bin/python experiments/ycb_build.py ycb:011_banana ycb:025_mug ycb:035_power_drill
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from contactpose import ObjectModel
from contactpose.harness import sweep
from contactpose.io import cache
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "results" / "ycb_build"
OBJECTS = ("ycb:011_banana", "ycb:025_mug", "ycb:035_power_drill")
CLI = [sys.executable, "-m", "contactpose"]
#: Second calls timed per object (the machine's other work makes single calls vary by 0.3 s).
SECOND_CALLS = 3


def grasp_file(name, path, seed=0):
    """4 noisy contacts on ``name`` at a random pose, as CONTACTS.json at ``path`` (from a model
    without pair tables worth the name: max_span 1e-5, no regions; the facets are the same)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        light = ObjectModel.from_mesh(objects.load(name), max_span=1e-5, patch_tol_deg=None, facet_pairs=True)
    g = simulate.grasp(light, np.random.default_rng(seed), n=4, position_noise=0.0005, normal_noise_deg=1.0)
    path.write_text(json.dumps({"contacts": [{"point": p.tolist(), "finger_normal": n.tolist()}
                                             for p, n in zip(g.contacts.points, g.contacts.finger_normals)]}))


def timed(args, env):
    """Run a command; -> (wall seconds, peak resident memory in bytes, stdout)."""
    start = time.perf_counter()
    proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} exited with {proc.returncode}")
    return time.perf_counter() - start, usage.ru_maxrss * 1024, out


def measure(name, folder):
    """One object's row."""
    contacts = folder / "contacts.json"
    grasp_file(name, contacts)
    env = dict(os.environ, **{cache.CACHE_DIR_ENV: str(folder / "cache")})
    call = CLI + ["localize", name, "--contacts", str(contacts), "--position-noise", "0.0005"]
    first_s, first_rss, _ = timed(call, env)
    os.sync()  # the new model file written back to disk: the second call reads a settled file
    seconds, peaks, outs = zip(*(timed(call, env) for _ in range(SECOND_CALLS)))
    saved = os.environ.get(cache.CACHE_DIR_ENV)
    os.environ[cache.CACHE_DIR_ENV] = env[cache.CACHE_DIR_ENV]
    try:
        [entry] = cache.entries()
    finally:
        os.environ.pop(cache.CACHE_DIR_ENV) if saved is None else os.environ.update({cache.CACHE_DIR_ENV: saved})
    model = ObjectModel.load(entry.path)
    return dict(object=name, facets=model.num_facets, regions=None if model.patches is None else model.patches.count,
                build_s=entry.build_seconds["total"], first_call_s=first_s, first_peak_gib=first_rss / 2**30,
                file_gb=entry.path.stat().st_size / 1e9, second_call_s=float(np.median(seconds)),
                second_call_max_s=max(seconds), second_peak_gib=max(peaks) / 2**30,
                status=outs[-1].splitlines()[0].removeprefix("status: "))


def table(rows):
    lines = ["| object | facets | regions | build (s) | first call (s) | peak memory (GiB) | model file (GB) | "
             f"second call (s), median of {SECOND_CALLS} | slowest (s) | its peak (GiB) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['object']} | {r['facets']:,} | {r['regions']:,} | {float(r['build_s']):.1f} | "
                     f"{float(r['first_call_s']):.1f} | {float(r['first_peak_gib']):.2f} | {float(r['file_gb']):.3g} | "
                     f"{float(r['second_call_s']):.2f} | {float(r['second_call_max_s']):.2f} | "
                     f"{float(r['second_peak_gib']):.2f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("objects", nargs="*", default=list(OBJECTS))
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.objects:
        with tempfile.TemporaryDirectory() as folder:
            rows.append(measure(name, Path(folder)))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    sweep.write_rows(out / "build.csv", rows)
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"
    (out / "build.md").write_text(f"Machine: {machine}; {time.strftime('%Y-%m-%d')}.\n\n{table(rows)}\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
