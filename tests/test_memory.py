"""Memory guards: every large allocation is estimated first and refused in one line.

Refusals are tested under an allocation ceiling (RLIMIT_AS) in a subprocess, never by
filling the machine: the ceiling is set a few GiB above the process's address space after
its imports and a warm-up build, so the guard must see the ceiling, not the free RAM.
"""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from contactpose.errors import ResourceError
from contactpose.model import memory
from contactpose.uncertainty.sampling import run_ensemble

PRELUDE = """
import json, resource, sys, time
import psutil, trimesh
from contactpose.errors import ResourceError
from contactpose.model import ObjectModel
from contactpose.sim import objects
ObjectModel.from_mesh(objects.load("banana"))  # imports, numba kernels and threads before the ceiling
ceiling = psutil.Process().memory_info().vms + int(float(sys.argv[1]) * 2**30)
resource.setrlimit(resource.RLIMIT_AS, (ceiling, resource.RLIM_INFINITY))

def attempt(build):
    start = time.perf_counter()
    try:
        out = {"ok": repr(build())}
    except ResourceError as exc:
        out = {"refused": str(exc)}
    out["seconds"] = time.perf_counter() - start
    print(json.dumps(out))
"""


def under_ceiling(body, gib=2.5, timeout=300):
    """Run PRELUDE + body in a subprocess whose address space may grow by gib GiB; the JSON it prints."""
    proc = subprocess.run([sys.executable, "-c", PRELUDE + body, str(gib)], capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def assert_refusal(out, facets):
    message = out.get("refused", "")
    assert message.startswith(f"the pair table for {facets} facets"), out
    assert "needs about" in message and "GiB is available" in message and "decimate the mesh" in message, message
    assert "\n" not in message


def test_free_memory_respects_the_ceiling():
    out = under_ceiling("from contactpose.io.modelfile import free_memory\n"
                        "print(json.dumps({'free': free_memory(), 'ceiling': ceiling, "
                        "'vms': psutil.Process().memory_info().vms}))", gib=1.0)
    assert out["free"] <= out["ceiling"] - out["vms"] + 64 * 2**20
    assert out["free"] < 1.1 * 2**30


def test_build_over_the_ceiling_is_refused_before_allocating():
    """20,480 facets, facet table only: 210 M pairs, about 12.5 GiB; refused under a 2.5 GiB ceiling
    (the machine may have that much free: the ceiling is what must refuse it)."""
    out = under_ceiling("mesh = trimesh.creation.icosphere(subdivisions=5)\n"
                        "attempt(lambda: ObjectModel.from_mesh(mesh, facet_pairs=True, patch_tol_deg=None))")
    assert_refusal(out, "20,480")
    assert "--max-span" in out["refused"]
    assert out["seconds"] < 10, out


def test_small_build_works_under_the_same_ceiling(tmp_path):
    out = under_ceiling(f"path = {str(tmp_path / 'rock1k.npz')!r}\n"
                        "attempt(lambda: ObjectModel.load(ObjectModel.from_mesh(objects.load('rock1k')).save(path)))")
    assert out.get("ok", "").startswith("ObjectModel(980 facets"), out


@pytest.mark.parametrize("span", [None, 0.02])
def test_327680_facet_icosphere_is_refused_quickly(span):
    """Without a span it needs about 800 GiB of patch pairs; with 0.02 (radius 1) about 0.6 GiB,
    refused here under a 0.75 GiB ceiling (the mesh-level steps take about 0.3 GiB of it).
    Either way before any pair is listed."""
    out = under_ceiling("mesh = trimesh.creation.icosphere(subdivisions=7)\n"
                        f"attempt(lambda: ObjectModel.from_mesh(mesh, max_span={span!r}))", gib=0.75)
    assert_refusal(out, "327,680")
    assert out["seconds"] < 10, out  # measured 2-4 s on 2 shared cores


def test_cli_refuses_the_327680_facet_icosphere_in_one_line(tmp_path):
    import trimesh

    stl = tmp_path / "ico7.stl"
    trimesh.creation.icosphere(subdivisions=7).export(stl)
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "contactpose", "build-model", str(stl), "-o", str(tmp_path / "m.npz")],
                          capture_output=True, text=True, timeout=300)
    seconds = time.perf_counter() - start
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("contactpose: error: the pair table for 327,680 facets") and "--max-span" in lines[0]
    assert seconds < 20, seconds  # measured 3.7-4.4 s wall, interpreter start included


def test_mesh_steps_are_refused_under_a_tiny_ceiling():
    out = under_ceiling("mesh = trimesh.creation.icosphere(subdivisions=7)\n"
                        "attempt(lambda: ObjectModel.from_mesh(mesh))", gib=0.2)
    assert out.get("refused", "").startswith("preparing the 327,680 facets of the mesh needs about"), out
    assert out["refused"].endswith("decimate the mesh")


def test_sampling_refuses_a_chain_that_cannot_fit():
    with pytest.raises(ResourceError, match=r"sampling 32 walkers for up to 1,000,000,000 steps needs about .* GiB"):
        run_ensemble(lambda x: -0.5 * np.sum(x * x, axis=1), np.eye(6), 10, np.random.default_rng(0),
                     max_steps=10**9)


def test_scan_refuses_a_cloud_that_cannot_fit(monkeypatch):
    reconstruct = pytest.importorskip("contactpose.scan.reconstruct")
    rng = np.random.default_rng(0)
    points = rng.normal(size=(100_000, 3))
    points *= 0.05 / np.linalg.norm(points, axis=1, keepdims=True)
    # the cleaning steps (200 B/point: 20 MB) fit in 40 MB, the reconstruction of every point does not
    monkeypatch.setattr(memory, "free_memory", lambda: 50 * 2**20)
    with pytest.raises(ResourceError, match=r"poisson reconstruction of a cloud of [\d,]+ points needs about"):
        reconstruct.scan_to_mesh(points, reconstruct.ScanOptions(voxel=0.0))
    monkeypatch.setattr(memory, "free_memory", lambda: 10 * 2**20)
    with pytest.raises(ResourceError, match="cleaning a cloud of 100,000 points needs about .* crop the cloud"):
        reconstruct.scan_to_mesh(points)
