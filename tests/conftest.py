"""Shared fixtures: built-in object models (built once per session) and small random meshes.

Models are built with default settings (bins, bounds="exact") unless a fixture says
otherwise. Randomness comes from ``numpy.random.default_rng`` with fixed seeds.
"""

import os

import numpy as np
import pytest
import trimesh
from hypothesis import settings

from contactpose.model.object_model import ObjectModel
from contactpose.sim import objects

# Property and fuzz tests draw the same cases on every run (repeatable CI); set
# CONTACTPOSE_HYPOTHESIS=explore to draw new ones.
settings.register_profile("repeatable", derandomize=True, database=None)
settings.register_profile("explore")
settings.load_profile(os.environ.get("CONTACTPOSE_HYPOTHESIS", "repeatable"))

@pytest.fixture(scope="session", autouse=True)
def model_cache_dir(tmp_path_factory):
    """The model cache (contactpose.io.cache) in a folder of the test session, never the user's."""
    folder = tmp_path_factory.mktemp("model_cache")
    saved = os.environ.get("CONTACTPOSE_CACHE_DIR")
    os.environ["CONTACTPOSE_CACHE_DIR"] = str(folder)
    yield folder
    if saved is None:
        os.environ.pop("CONTACTPOSE_CACHE_DIR", None)
    else:
        os.environ["CONTACTPOSE_CACHE_DIR"] = saved


#: Sensor noise used throughout the online tests: 0.5 mm and 1 degree per axis.
POSITION_NOISE = 0.0005
NORMAL_NOISE_DEG = 1.0


@pytest.fixture(scope="session")
def banana_mesh():
    return objects.load("banana")


@pytest.fixture(scope="session")
def banana_model(banana_mesh):
    return ObjectModel.from_mesh(banana_mesh)


@pytest.fixture(scope="session")
def carton_model():
    return ObjectModel.from_mesh(objects.load("carton"))


@pytest.fixture(scope="session")
def rock_model():
    return ObjectModel.from_mesh(objects.load("rock"))


@pytest.fixture(scope="session")
def box_model():
    return ObjectModel.from_mesh(objects.load("box"))


@pytest.fixture(scope="session")
def models(banana_model, carton_model, rock_model):
    """The three reference meshes (banana, carton, rock) by name."""
    return {"banana": banana_model, "carton": carton_model, "rock": rock_model}


def random_icosahedron(seed, jitter=0.25, scale=0.05):
    """A closed 20-facet mesh: an icosahedron with radially jittered vertices (no symmetry left).

    Star-shaped about the origin, so every facet stays outward-facing.
    """
    rng = np.random.default_rng(seed)
    ico = trimesh.creation.icosahedron()
    v = ico.vertices * (1.0 + jitter * rng.uniform(-1.0, 1.0, (len(ico.vertices), 1)))
    return trimesh.Trimesh(v * scale, ico.faces, process=False)


@pytest.fixture(scope="session")
def small_mesh():
    """A 20-facet irregular closed mesh (see :func:`random_icosahedron`)."""
    return random_icosahedron(7)


@pytest.fixture(scope="session")
def small_model(small_mesh):
    return ObjectModel.from_mesh(small_mesh)
