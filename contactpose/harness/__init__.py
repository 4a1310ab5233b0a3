"""The harness around the method: experiment sweeps on Dask (:mod:`.sweep`), the benchmark
(:mod:`.bench`), the demo (:mod:`.demo`), figures (:mod:`.viz`), pictures of the 3D pages in
headless Chromium (:mod:`.pages`) and the ceiling on strict top-1 that a grasp allows
(:mod:`.ceiling`).

Nothing of the core imports this package (an import-linter contract in pyproject.toml);
the CLI and the scripts in experiments/ do. Its modules are imported by name
(``from contactpose.harness import sweep``): they load Dask and matplotlib.
"""

__all__ = ["bench", "ceiling", "demo", "pages", "sweep", "viz"]
