"""``contactpose cache list | clear``: the models built from named objects, kept between calls."""

from __future__ import annotations

import time

from contactpose.cli.common import add_parser
from contactpose.io import cache as model_cache


def register(subparsers):
    """Add ``cache {list,clear}``; handler :func:`run`."""
    p = add_parser(subparsers, "cache", help="list or clear the models built from named objects",
                   description="A model built from a built-in or YCB object name is kept in the model cache "
                               f"(${model_cache.CACHE_DIR_ENV}, else $XDG_CACHE_HOME/contactpose/models, else "
                               "~/.cache/contactpose/models), keyed by the mesh's hash, the model file's version "
                               "and the build options, so that later calls load it instead of building it. The "
                               f"least recently used models go first when it would exceed its limit (8 GiB; "
                               f"${model_cache.CACHE_LIMIT_ENV} sets it in GiB).")
    p.add_argument("action", choices=("list", "clear"), help="list: the cached models, most recently used first; "
                                                             "clear: remove them all")
    p.set_defaults(func=run)


def run(args):
    """List or clear the model cache; 0."""
    folder, limit = model_cache.cache_dir(), model_cache.cache_limit()
    if args.action == "clear":
        count, nbytes = model_cache.clear()
        print(f"removed {count} model{'' if count == 1 else 's'} ({_size(nbytes)}) from {folder}")
        return 0
    held = model_cache.entries()
    print(f"model cache: {folder} (limit {_size(limit)})")
    for e in held:
        built = e.build_seconds.get("total")
        note = f", built in {built:.1f} s" if built is not None else ""
        print(f"  {e.name:<32} {_size(e.size):>10}  last used {time.strftime('%Y-%m-%d %H:%M', time.localtime(e.last_used))}"
              f"{note}")
    print(f"{len(held)} model{'' if len(held) == 1 else 's'}, {_size(sum(e.size for e in held))}")
    return 0


def _size(nbytes):
    """'812.4 KiB', '54.7 MiB' or '1.91 GiB'."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{nbytes / 1024:.1f} KiB"
