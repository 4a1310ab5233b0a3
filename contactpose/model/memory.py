"""Memory guards: estimate an allocation first, then refuse it in one line if it will not fit.

"Free" is :func:`contactpose.io.modelfile.free_memory`: the system's available memory, or
less under an RLIMIT_AS ceiling. An estimate fits when it is at most FIT_FRACTION of that
(the rest is headroom for what the estimates leave out: interpreter, libraries, the mesh).
Used by the model build (:mod:`contactpose.model.plan`), the scan step and the sampler.
"""

from __future__ import annotations

from contactpose.errors import ResourceError
from contactpose.io.modelfile import free_memory

#: An estimate fits when it needs at most this fraction of the free memory.
FIT_FRACTION = 0.8
#: Bytes one localize may allocate beyond the loaded model: a stage whose estimate exceeds
#: it (or the free memory's FIT_FRACTION) does not run, and the answer says so.
ONLINE_BYTES = 2**30


def gib(nbytes):
    """nbytes in GiB, three significant digits: '884', '2.5', '0.00195'."""
    return f"{nbytes / 2**30:.3g}"


def budget():
    """Bytes an estimate may need: FIT_FRACTION of the free memory."""
    return FIT_FRACTION * free_memory()


def online_fits(need):
    """Whether an online stage may allocate ``need`` bytes: at most ONLINE_BYTES and budget()."""
    return need <= min(ONLINE_BYTES, budget())


def check_fits(need, what, advice):
    """ResourceError "<what> needs about X GiB, but only Y GiB is available; <advice>" when
    need (bytes) exceeds FIT_FRACTION of the free memory; else need."""
    free = free_memory()
    if need > FIT_FRACTION * free:
        raise ResourceError(f"{what} needs about {gib(need)} GiB, but only {gib(free)} GiB is available; {advice}")
    return need
