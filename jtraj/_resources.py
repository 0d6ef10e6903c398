"""What a solve will need, estimated from its sizes before anything is traced.

The interior-point method's Newton step is stage-wise (:mod:`jtraj.lq`), but a few of
the solver's arrays couple every pair of stages: the co-state terms and the Hessian
row bounds of the decoupled recursion (``(N + 1, N, n)``), and, in the AL fallback and
the final polish, the dense Jacobian of every constraint row (``~ N n x N (n + 1)``)
with its normal matrix. So the working set of one problem grows as ``N^2 (n + 1)^2``;
the rest (a process with JAX and the compiled programs, about half a GiB) does not
grow with N. The compiled programs' size does not depend on N or on the batch size
(the loops are not unrolled); it grows with the number of joints through the unrolled
dynamics.

:func:`check` refuses, with a ``ValueError`` naming N or the batch size and the
estimate, a solve whose estimate exceeds the limit: ``JTRAJ_MEMORY_LIMIT_GB`` (GiB;
``0`` switches the check off), by default 80 % of this machine's physical memory.
"""

from __future__ import annotations

import os
from typing import NamedTuple

#: bytes of a process that has imported JAX and jtraj and compiled the solver (one
#: interior-point solve of serial3 peaks at 0.48-0.52 GiB from N = 20 to N = 1,000,
#: ``benchmarks/bench_memory.py``)
_BASE = 0.6 * 2**30
#: per problem solved at once: bytes per N^2 (n + 1)^2, sized for the AL fallback and
#: the final polish (the dense Jacobian of ~4n N constraint rows by N (n + 1) variables,
#: in three copies, and two normal matrices of N (n + 1) squared, in float64: about 90
#: such bytes), with a margin for the forward-mode tangents that build them
_QUADRATIC = 128.0
#: per problem stored (a batch keeps every problem's state): bytes per N (n + 1)
_LINEAR = 4096.0
#: HLO instructions of a single solve's two programs (the interior-point one and the AL
#: fallback's), taken as proportional to the number of joints (the dynamics are unrolled
#: per joint; measured on serial3 only: about 30,000 at n = 3, for any N)
_OPS_PER_JOINT = 10000
_OPS_BASE = 0


class Estimate(NamedTuple):
    memory_bytes: float
    hlo_ops: int


def estimate(N: int, n: int, batch: int = 1, lanes: int | None = None) -> Estimate:
    """The peak memory (bytes) and the compiled programs' size (HLO instructions) of a
    solve of ``batch`` problems with ``N`` stages and ``n`` joints, ``lanes`` of them
    solved at once (default: all)."""
    lanes = batch if lanes is None else min(lanes, batch)
    per = _QUADRATIC * float(N) ** 2 * (n + 1) ** 2
    memory = _BASE + lanes * per + batch * _LINEAR * N * (n + 1)
    return Estimate(memory, int(_OPS_BASE + _OPS_PER_JOINT * n))


def limit_bytes() -> float | None:
    """The memory limit of :func:`check` in bytes (None: no limit)."""
    text = os.environ.get("JTRAJ_MEMORY_LIMIT_GB")
    if text is not None:
        try:
            gb = float(text)
        except ValueError:
            raise ValueError(f"JTRAJ_MEMORY_LIMIT_GB must be a number of GiB (0: no limit), got {text!r}") from None
        return None if gb <= 0 else gb * 2**30
    try:
        return 0.8 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # no sysconf: no limit
        return None


def check(N: int, n: int, batch: int = 1, lanes: int | None = None):
    """Raise ``ValueError`` where :func:`estimate` exceeds :func:`limit_bytes`."""
    limit = limit_bytes()
    if limit is None:
        return
    est = estimate(N, n, batch, lanes)
    if est.memory_bytes <= limit:
        return
    gib = est.memory_bytes / 2**30
    where = (f"N = {N}" if batch == 1 else
             f"N = {N} with a batch of {batch} problems ({lanes if lanes is not None else batch} solved at once)")
    raise ValueError(f"{where} and {n} joints: the solve is estimated to need {gib:.1f} GiB of memory, above the "
                     f"limit of {limit / 2**30:.1f} GiB (JTRAJ_MEMORY_LIMIT_GB; 0 switches the check off). "
                     f"Use a smaller N" + ("" if batch == 1 else " or smaller batches (or fewer slots)"))
