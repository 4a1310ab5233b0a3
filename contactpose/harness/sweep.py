"""Experiment sweeps: a grid of settings x seeds, run as Dask tasks, rows streamed to CSV.

A :class:`Sweep` names a task function and a grid. Every combination of the grid's
settings with every seed is one *cell*; :func:`run` runs each unfinished cell as one
task, on a Dask ``LocalCluster`` (default) or an existing cluster (``scheduler=
"tcp://HOST:PORT"``), and writes under ``out_dir``:

* ``results.csv``: every row of every finished cell, timing columns left out. Sorted
  by cell (grid order, then seed), so it is identical bit for bit whatever the number
  of workers, the completion order or how often the sweep was interrupted and resumed.
* ``timings.csv``: the same rows with every column, timing columns included (names
  starting with ``time_``). Timings differ from run to run, so this file is not
  reproducible; the bit-identity guarantee is about ``results.csv`` only.
* ``config.json``: the grid, seeds and fixed configuration (deterministic), and
  ``run.json``: machine, workers and wall time of the last run (not deterministic).

Both CSVs are rewritten atomically (sorted snapshot of the finished cells) while the
sweep runs, at most every ``flush_seconds``, so rows stream to disk and an interrupted
sweep loses at most that much work. A rerun resumes: cells whose rows are already in
``timings.csv`` are skipped, unless the fixed configuration or the base seed changed.

Randomness: each cell's generator is ``default_rng(SeedSequence(base_seed,
spawn_key=hash(settings restricted to seed_axes, seed)))``. The hash is of the cell's
stable key, not of its position in the grid, so growing the grid never changes the
random stream of existing cells (resume stays valid). ``seed_axes`` pairs cells: with
``seed_axes=("object",)``, two cells that differ only in, say, the method get the same
grasps.

Execution: ``workers=None`` starts a LocalCluster with one worker process per CPU,
``threads_per_worker=1`` (numba, BLAS and OpenMP held to one thread per task);
``workers=0`` runs the cells in the calling process without Dask (debugging, profiling);
``scheduler=...`` uses an existing cluster. A failed cell is logged and reported at the end
(SweepError) after the others have finished and been written; a rerun retries it.

Task contract: ``task(settings, rng) -> dict | list[dict]``; ``settings`` is the cell's
settings plus ``"seed"``. Rows are flat dicts of str, int, float, bool or None. Bind
fixed configuration with :func:`functools.partial`. Tasks defined in scripts are sent to
the workers by value (cloudpickle), so a script's task needs no installed module.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import functools
import hashlib
import io
import itertools
import json
import logging
import math
import os
import platform
import sys
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

#: Columns whose name starts with this are timings: kept out of results.csv.
TIMING_PREFIX = "time_"
RESULTS_CSV = "results.csv"
TIMINGS_CSV = "timings.csv"
CONFIG_JSON = "config.json"
RUN_JSON = "run.json"
#: Environment of LocalCluster workers: one thread each for BLAS and OpenMP (Open3D), so n
#: workers use n cores and results do not depend on thread counts. (Dask also sets these
#: before spawning.) numba gets one thread per task from numba.set_num_threads in the
#: worker, not from NUMBA_NUM_THREADS: a script's imports run in the spawned worker before
#: the Nanny's environment is applied, and numba refuses a changed NUMBA_NUM_THREADS once
#: its threads run.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: Reserved leading columns of every row.
CELL_COLUMN = "cell"
SEED_COLUMN = "seed"


class SweepError(RuntimeError):
    """A sweep could not run, or some of its cells failed."""


# --------------------------------------------------------------------------- cells

def canonical(value):
    """JSON text of a settings value with sorted keys and no spaces (numpy scalars as Python)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=_json_default)


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (tuple, set)):
        return list(value)
    raise TypeError(f"cannot put {type(value).__name__} into a sweep setting or config")


@dataclass(frozen=True)
class Cell:
    """One task: settings (dict) and seed (int); index is its position in the grid order.

    key : canonical JSON of settings + seed (stable across grids); cell : a 12-hex digest of key.
    """

    index: int
    settings: dict
    seed: int

    @property
    def key(self):
        return canonical({**self.settings, SEED_COLUMN: self.seed})

    @property
    def cell(self):
        return hashlib.sha256(self.key.encode()).hexdigest()[:12]

    def seed_sequence(self, base_seed, seed_axes=None):
        """SeedSequence(base_seed, spawn_key=digest of the seed axes' settings and the seed)."""
        axes = sorted(self.settings) if seed_axes is None else list(seed_axes)
        missing = [a for a in axes if a not in self.settings]
        if missing:
            raise SweepError(f"seed_axes {missing} are not settings of the grid {sorted(self.settings)}")
        text = canonical({"settings": {a: self.settings[a] for a in axes}, "seed": self.seed})
        digest = hashlib.sha256(text.encode()).digest()
        words = tuple(int.from_bytes(digest[i:i + 4], "little") for i in range(0, 16, 4))
        return np.random.SeedSequence(int(base_seed), spawn_key=words)


def grid_settings(grid):
    """Settings dicts of a grid: a mapping axis -> values (their product, first axis slowest)
    or a sequence of settings dicts (taken as they are)."""
    if isinstance(grid, Mapping):
        axes = list(grid)
        for axis in axes:
            if isinstance(grid[axis], (str, bytes)) or not isinstance(grid[axis], Sequence):
                raise SweepError(f"grid axis {axis!r} must be a list of values, got {grid[axis]!r}")
        return [dict(zip(axes, combo)) for combo in itertools.product(*(grid[a] for a in axes))]
    settings = [dict(s) for s in grid]
    if not all(isinstance(s, dict) for s in settings):
        raise SweepError("a grid must be a mapping of axis -> values or a list of settings dicts")
    return settings


def make_cells(grid, seeds):
    """All cells of a grid, settings-major then seed: list of :class:`Cell`.

    seeds : int (seeds 0..seeds-1) or a sequence of ints.
    """
    seed_list = list(range(seeds)) if isinstance(seeds, (int, np.integer)) else [int(s) for s in seeds]
    settings = grid_settings(grid)
    for s in settings:
        reserved = {CELL_COLUMN, SEED_COLUMN} & set(s)
        if reserved:
            raise SweepError(f"grid axes may not be named {sorted(reserved)}: they are reserved columns")
        canonical(s)  # raises on values JSON cannot hold
    cells = [Cell(i, s, seed) for i, (s, seed) in enumerate(itertools.product(settings, seed_list))]
    keys = [c.key for c in cells]
    if len(set(keys)) != len(keys):
        raise SweepError("the grid repeats a cell (the same settings and seed twice)")
    return cells


# --------------------------------------------------------------------------- sweep

@dataclass
class Sweep:
    """A named grid of settings x seeds and the task that runs one cell.

    task : callable(settings: dict, rng: numpy.random.Generator) -> dict | list[dict];
    grid : mapping axis -> values, or list of settings dicts; seeds : int or list of ints;
    base_seed : int; seed_axes : settings that enter the random stream (None: all);
    config : fixed configuration the task depends on (saved; a change starts afresh).
    """

    name: str
    task: Callable
    grid: Mapping | Sequence
    seeds: int | Sequence[int] = 1
    base_seed: int = 0
    seed_axes: Sequence[str] | None = None
    config: dict = field(default_factory=dict)

    def cells(self):
        return make_cells(self.grid, self.seeds)

    def config_record(self):
        """The deterministic content of config.json."""
        seeds = self.seeds if isinstance(self.seeds, (int, np.integer)) else list(self.seeds)
        grid = dict(self.grid) if isinstance(self.grid, Mapping) else [dict(s) for s in self.grid]
        return json.loads(canonical({
            "experiment": self.name, "grid": grid, "seeds": seeds, "base_seed": self.base_seed,
            "seed_axes": None if self.seed_axes is None else list(self.seed_axes),
            "config": self.config,
        }))


@dataclass
class SweepReport:
    """What :func:`run` did: output paths, cells run / skipped / failed, wall seconds."""

    results: Path
    timings: Path
    config: Path
    ran: int
    skipped: int
    failed: list
    seconds: float
    workers: int | None


def run(sweep, out_dir, *, workers=None, scheduler=None, resume=True, progress=None,
        flush_seconds=5.0):
    """Run the unfinished cells of a sweep and write its CSVs and config under out_dir.

    workers : LocalCluster worker processes (default: the number of CPUs); 0 runs the
    cells in this process without Dask (for debugging and profiling). scheduler :
    address of an existing Dask scheduler ("tcp://HOST:PORT"); then workers is ignored.
    resume : skip cells already in out_dir/timings.csv (False: start afresh).
    progress : tqdm bar (default: only when stderr is a terminal).
    Returns a :class:`SweepReport`; raises SweepError after writing if any cell failed.
    """
    start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cells = sweep.cells()
    record = sweep.config_record()
    done = _load_finished(out, record, cells) if resume else {}
    pending = [c for c in cells if c.cell not in done]
    _write_json(out / CONFIG_JSON, record)
    log.info("%s: %d cells, %d finished before, %d to run", sweep.name, len(cells), len(done), len(pending))
    writer = _Snapshot(out, cells, done, flush_seconds)
    failed = []
    used_workers = None
    if pending:
        runner = functools.partial(run_cell, sweep.task, base_seed=sweep.base_seed, seed_axes=sweep.seed_axes)
        bar = _progress_bar(progress, len(pending), sweep.name)
        try:
            if workers == 0 and scheduler is None:
                completed = ((c, *_call(runner, c)) for c in pending)
            else:
                completed, used_workers = _dask_completed(runner, pending, workers, scheduler)
            with contextlib.closing(completed):
                for cell, rows, error in completed:
                    if error is not None:
                        failed.append((cell.key, error))
                        log.error("%s: cell %s failed: %s", sweep.name, cell.key, error)
                    else:
                        writer.add(cell, rows)
                    if bar is not None:
                        bar.update(1)
        finally:
            if bar is not None:
                bar.close()
            writer.flush()
    else:
        writer.flush()
    seconds = time.perf_counter() - start
    _write_json(out / RUN_JSON, {"experiment": sweep.name, "cells": len(cells), "ran": len(pending) - len(failed),
                                 "skipped": len(done), "failed": len(failed), "seconds": round(seconds, 3),
                                 "workers": used_workers, "scheduler": scheduler, "machine": _machine()})
    report = SweepReport(out / RESULTS_CSV, out / TIMINGS_CSV, out / CONFIG_JSON, len(pending) - len(failed),
                         len(done), failed, seconds, used_workers)
    if failed:
        raise SweepError(f"{sweep.name}: {len(failed)} of {len(cells)} cells failed (rerun to retry them); "
                         f"first: {failed[0][0]}: {failed[0][1]}")
    return report


def run_cell(task, cell, *, base_seed, seed_axes=None):
    """Run one cell: its rows as a list of dicts of formatted strings, in the task's order."""
    rng = np.random.default_rng(cell.seed_sequence(base_seed, seed_axes))
    out = task({**cell.settings, SEED_COLUMN: cell.seed}, rng)
    rows = [out] if isinstance(out, Mapping) else list(out)
    if not rows:
        raise SweepError(f"the task returned no row for cell {cell.key}; every cell needs at least one")
    lead = {CELL_COLUMN: cell.cell, **cell.settings, SEED_COLUMN: cell.seed}
    formatted = []
    for row in rows:
        if not isinstance(row, Mapping):
            raise SweepError(f"a task row must be a dict, got {type(row).__name__}")
        clash = [k for k in row if k in lead and format_value(row[k]) != format_value(lead[k])]
        if clash:
            raise SweepError(f"row columns {clash} clash with the cell's settings of the same name")
        formatted.append({k: format_value(v) for k, v in {**lead, **row}.items()})
    return formatted


def _call(runner, cell):
    try:
        return runner(cell), None
    except Exception as exc:  # a failed cell is reported, the others go on
        where = traceback.extract_tb(exc.__traceback__)[-1]
        return None, f"{type(exc).__name__}: {exc} (at {Path(where.filename).name}:{where.lineno})"


def _call_pickled(payload, cell):
    """Worker side: one numba thread per task (threads_per_worker=1), then the cell."""
    try:
        import numba

        numba.set_num_threads(1)
    except ImportError:
        pass
    return _call(lambda c: _unpickled(payload)(c), cell)


@functools.lru_cache(maxsize=8)
def _unpickled(payload):
    """The runner of a payload, unpickled once per worker process."""
    import cloudpickle

    return cloudpickle.loads(payload)


def _dask_completed(runner, pending, workers, scheduler):
    """Yield (cell, rows, error) as Dask tasks finish; returns (generator, worker count)."""
    import cloudpickle
    from distributed import Client, LocalCluster, as_completed

    # Dask pickles nested arguments by reference when it can; a task from a script imported
    # under a module name the workers cannot import must travel by value: pickle it here.
    _pickle_task_by_value(runner.args[0])
    payload = cloudpickle.dumps(runner)
    if scheduler is not None:
        cluster = None
        client = Client(scheduler)
    else:
        n = workers if workers is not None else (os.cpu_count() or 1)
        if n < 1:
            raise SweepError(f"workers must be >= 1 for a LocalCluster (0 runs in-process), got {workers}")
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=logging.CRITICAL, env=WORKER_ENV)
        client = Client(cluster)
    n_workers = len(client.scheduler_info()["workers"]) if scheduler else n

    def generate():
        try:
            futures = {client.submit(_call_pickled, payload, c, pure=False): c for c in pending}
            for future in as_completed(futures):
                rows, error = future.result()
                yield futures[future], rows, error
        finally:
            client.close()
            if cluster is not None:
                cluster.close()

    return generate(), n_workers


def _pickle_task_by_value(task):
    """Send a task defined outside an installed package (a script, a test) by value."""
    import cloudpickle

    func = task.func if isinstance(task, functools.partial) else task
    module = sys.modules.get(getattr(func, "__module__", None) or "")
    if module is None or module.__name__ == "__main__":
        return  # __main__ is pickled by value anyway
    if module.__name__.split(".")[0] != "contactpose":
        cloudpickle.register_pickle_by_value(module)


def _progress_bar(progress, total, name):
    if progress is None:
        progress = sys.stderr.isatty()
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=name, unit="cell", file=sys.stderr)


# --------------------------------------------------------------------------- rows on disk

def format_value(value):
    """A row value as CSV text: floats by repr (round-trip exact), bools as 1/0, None as ''."""
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return "1" if value else "0"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, str):
        if "\n" in value or "\r" in value:
            raise SweepError(f"row values may not contain line breaks: {value!r:.60}")
        return value
    raise SweepError(f"row values must be str, int, float, bool or None, got {type(value).__name__}")


class _Snapshot:
    """Finished cells' rows, written as sorted CSVs (atomically) at most every flush_seconds.

    Columns: ``cell``, the grid's axes in grid order, ``seed``, then the task's columns in
    alphabetical order, so the header never depends on which rows finished first.
    """

    def __init__(self, out, cells, done, flush_seconds):
        self.out = out
        self.order = {c.cell: c.index for c in cells}
        self.lead = [CELL_COLUMN, *dict.fromkeys(k for c in cells for k in c.settings), SEED_COLUMN]
        self.rows = dict(done)
        self.flush_seconds = flush_seconds
        self.last = time.monotonic()

    def add(self, cell, rows):
        self.rows[cell.cell] = rows
        if time.monotonic() - self.last >= self.flush_seconds:
            self.flush()

    def flush(self):
        ordered = [r for c in sorted(self.rows, key=self.order.__getitem__) for r in self.rows[c]]
        lead = set(self.lead)
        columns = self.lead + sorted({k for r in ordered for k in r} - lead)
        _write_csv(self.out / TIMINGS_CSV, columns, ordered)
        _write_csv(self.out / RESULTS_CSV, [c for c in columns if not c.startswith(TIMING_PREFIX)], ordered)
        self.last = time.monotonic()


def _write_csv(path, columns, rows):
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, restval="", extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    _atomic_write(path, buf.getvalue())


def _atomic_write(path, text):
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _write_json(path, data):
    _atomic_write(path, json.dumps(data, indent=1, sort_keys=False, default=_json_default) + "\n")


def _load_finished(out, record, cells):
    """Rows of finished cells from a previous run: {cell digest: [row, ...]}, in file order.

    Returns {} when there is none, or when the fixed config, base seed or seed axes changed.
    Rows of cells no longer in the grid are dropped.
    """
    path, cfg = out / TIMINGS_CSV, out / CONFIG_JSON
    if not path.exists() or not cfg.exists():
        return {}
    try:
        old = json.loads(cfg.read_text())
    except json.JSONDecodeError:
        old = {}
    same = all(old.get(k) == record[k] for k in ("experiment", "config", "base_seed", "seed_axes"))
    if not same:
        log.warning("%s: configuration changed since the last run; starting afresh", record["experiment"])
        return {}
    wanted = {c.cell for c in cells}
    done = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            digest = row.get(CELL_COLUMN)
            if digest in wanted:
                done.setdefault(digest, []).append(row)
    return done


def machine_description():
    """CPU model, core count and memory, for the results."""
    import psutil

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gib": round(psutil.virtual_memory().total / 2**30, 1),
            "python": platform.python_version(), "numpy": np.__version__}


def _machine():
    try:
        return machine_description()
    except Exception:  # machine info is a courtesy; never fail a sweep over it
        return {}


# --------------------------------------------------------------------------- reading back

def read_rows(path):
    """The rows of a sweep CSV as a list of dicts of strings."""
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def write_rows(path, rows):
    """Rows (dicts) as a CSV with a header: the union of their keys in first-seen order, missing
    values empty, values as str() gives them. Plain, not atomic: for scripts' own tables."""
    columns = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)


def read_columns(path):
    """A sweep CSV as {column: numpy array}: float where every non-empty value parses as a
    number (empty -> nan), else str."""
    rows = read_rows(path)
    if not rows:
        return {}
    out = {}
    for col in rows[0]:
        values = [r[col] for r in rows]
        try:
            out[col] = np.array([float(v) if v != "" else math.nan for v in values])
        except ValueError:
            out[col] = np.array(values, dtype=object)
    return out


# --------------------------------------------------------------------------- experiment scripts

def add_arguments(parser, *, default_workers=None):
    """The options every experiment script shares: --quick, --workers, --scheduler, --out,
    --fresh, --plot-only, --set."""
    parser.add_argument("--quick", action="store_true", help="the small version (seconds, used by the tests)")
    parser.add_argument("--workers", type=int, default=default_workers,
                        help="LocalCluster worker processes (default: "
                             + ("the number of CPUs" if default_workers is None else str(default_workers))
                             + "); 0 runs in this process without Dask")
    parser.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler, tcp://HOST:PORT")
    parser.add_argument("--out", default=None, help="results root (default: results/, or results/_scratch/quick/ with --quick)")
    parser.add_argument("--fresh", action="store_true", help="ignore rows of a previous run instead of resuming")
    parser.add_argument("--plot-only", action="store_true", help="redraw the figures from the CSV without running")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                        help="override one setting of the experiment's config file, its value in JSON "
                             "(repeatable; e.g. --set seeds=20 --set 'objects=[\"ycb:025_mug\"]')")
    return parser


#: Repository root (the parent of the package directory): experiments/ and results/ live here.
ROOT = Path(__file__).resolve().parents[2]


def setup_logging(*names):
    """INFO messages of the sweep runner and the named loggers on stderr; others at WARNING."""
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    # cluster start/stop chatter (failed cells are reported by the runner itself); distributed
    # sets its loggers' levels when imported, so import it first
    import distributed  # noqa: F401

    for name in ["distributed", *[n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]]:
        logging.getLogger(name).setLevel(logging.CRITICAL)
    for name in (__name__, *names):
        logging.getLogger(name).setLevel(logging.INFO)


def workers_for(args, config):
    """--workers if given, else the config's "workers" (None: the number of CPUs)."""
    return args.workers if args.workers is not None else config.get("workers")


def read_run(out_dir):
    """run.json of the last run under out_dir ({} if none): machine, workers, seconds."""
    path = Path(out_dir) / RUN_JSON
    return json.loads(path.read_text()) if path.exists() else {}


def results_dir(args, name):
    """results/<name>/ (full) or results/_scratch/quick/<name>/ (--quick), or --out/<name>/."""
    if args.out is not None:
        return Path(args.out) / name
    return ROOT / "results" / ("_scratch/quick" if args.quick else "") / name


def load_config(name, quick, directory=None):
    """Settings of an experiment from experiments/configs/<name>.json: its "common" section
    updated by its "quick" or "full" section."""
    path = Path(directory or ROOT / "experiments" / "configs") / f"{name}.json"
    if not path.exists():
        raise SweepError(f"no config file {path}")
    data = json.loads(path.read_text())
    return {**data.get("common", {}), **data.get("quick" if quick else "full", {})}


def start(name, doc, argv=None):
    """Parse an experiment script's options (:func:`add_arguments`), set up logging and load
    its config. doc : the script's docstring (first line: --help). -> (args, config, out_dir)"""
    parser = add_arguments(argparse.ArgumentParser(description=doc.split("\n")[0]))
    args = parser.parse_args(argv)
    config = load_config(name, args.quick)
    try:
        config = overridden(config, args.set)
    except SweepError as err:
        parser.error(str(err))
    setup_logging(name)
    return args, config, results_dir(args, name)


def overridden(config, settings):
    """config with each "KEY=JSON" of settings applied; a key the config lacks or a value that
    is not JSON raises SweepError naming it (the run records the result in config.json)."""
    out = dict(config)
    for item in settings:
        key, sep, text = item.partition("=")
        if not sep or key not in config:
            raise SweepError(f"--set {item!r}: expected KEY=JSON with KEY one of the config's settings "
                             f"({', '.join(sorted(config))})")
        try:
            out[key] = json.loads(text)
        except ValueError:
            raise SweepError(f"--set {item!r}: the value {text!r} is not JSON (strings need quotes: "
                             f"'{key}=\"...\"')") from None
    return out


def run_logged(sweep, out_dir, args, config):
    """:func:`run` with the script's --workers, --scheduler and --fresh; logs what it did."""
    report = run(sweep, out_dir, workers=workers_for(args, config), scheduler=args.scheduler, resume=not args.fresh)
    log.info("%s: ran %d cells, skipped %d, %.1f s", sweep.name, report.ran, report.skipped, report.seconds)
    return report


def finish(out_dir, plot, summary):
    """Draw the figures from the CSVs, print summary(out_dir) and where it all went; returns 0."""
    plot(out_dir)
    print(summary(out_dir))
    print(f"written: {out_dir}")
    return 0


def main(name, doc, make_sweep, plot, summary, argv=None):
    """The whole of a one-sweep experiment script: options, config, the sweep (skipped with
    --plot-only) into :func:`results_dir`, figures, summary.

    make_sweep : config -> Sweep; plot, summary : out_dir -> paths, text. Returns 0.
    """
    args, config, out = start(name, doc, argv)
    if not args.plot_only:
        run_logged(make_sweep(config), out, args, config)
    return finish(out, plot, summary)


def cached(key, factory):
    """A per-process memo: factory() once per key in each worker (models, surface samples)."""
    if key not in _CACHE:
        _CACHE[key] = factory()
    return _CACHE[key]


_CACHE: dict = {}


# --------------------------------------------------------------------------- figures

#: Matplotlib settings for figures read at paper size (one column is 3.5 in wide).
PAPER_RC = {
    "font.size": 8, "axes.labelsize": 8, "axes.titlesize": 8, "legend.fontsize": 7,
    "xtick.labelsize": 7, "ytick.labelsize": 7, "lines.linewidth": 1.2, "lines.markersize": 4,
    "axes.grid": True, "grid.alpha": 0.3, "grid.linewidth": 0.5, "figure.dpi": 100,
    "savefig.dpi": 300, "savefig.bbox": "tight", "savefig.pad_inches": 0.02, "pdf.fonttype": 42,
    "svg.hashsalt": "contactpose",
}
#: Figure widths in inches: one column and two columns of a two-column paper.
COLUMN_WIDTH = 3.5
PAGE_WIDTH = 7.16


def plain_log_axis(ax, axis="y", subs=None):
    """Log axis with plain numbers (0.5, 2, 100) instead of powers of ten; ticks at 1-2-5
    over short ranges, else at powers of ten (or at ``subs`` of each decade)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    target = ax.yaxis if axis == "y" else ax.xaxis
    lo, hi = sorted(ax.get_ylim() if axis == "y" else ax.get_xlim())
    decades = np.log10(hi / lo) if lo > 0 else 9
    # 1-2-5 ticks over a short range, powers of ten over a long one
    if subs is None:
        subs = (1.0, 2.0, 5.0) if decades < 3 else (1.0,)
    target.set_major_locator(LogLocator(base=10, subs=subs))
    target.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    target.set_minor_formatter(NullFormatter())


def save_figure(fig, out_dir, stem):
    """Lay fig out tightly, save it as <stem>.png and <stem>.pdf under out_dir (no timestamps
    in the files) and close it. Returns the two paths."""
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{stem}.png", out / f"{stem}.pdf"]
    fig.tight_layout()
    fig.savefig(paths[0], metadata={"Software": None})
    fig.savefig(paths[1], metadata={"CreationDate": None, "Producer": None, "Creator": None})
    plt.close(fig)
    return paths
