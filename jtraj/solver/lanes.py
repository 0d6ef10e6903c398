"""The batch solve: vmapped programs and the host-driven lane driver that keeps
lanes busy by refilling finished ones (see ``solve_batch``'s ``slots``)."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _packing, _tracecache
from .._compile import SOLVER_XLA_OPTIONS, supported_options
from .._compile import solver_jit as _jit
from ..transcription import Transcription
from . import ipm, loop
from .al import ALMethod
from .core import finish, ip_method, prepare, solve_core
from .options import TracedOptions, options_jit, split_options
from .results import Solution


@options_jit()
def solve_batch_jit(problems, opts, transcription, init, warm):
    tr = Transcription(transcription)
    return eqx.filter_vmap(lambda p, i: solve_core(p, opts, tr, i, warm))(problems, init)


@options_jit()
def _prepare_batch_jit(problems, opts, transcription, init, warm):
    tr = Transcription(transcription)
    return eqx.filter_vmap(lambda p, i: prepare(p, opts, tr, i, warm))(problems, init)


def _segment(nlps, states, opts, steps: int, method=None):
    """``steps`` more iterations of each lane's run of ``method`` (default the AL method of
    ``opts``; :func:`jtraj.solver.loop.iterate`, vmapped: a finished lane idles)."""
    method = ALMethod(opts) if method is None else method
    return eqx.filter_vmap(lambda n, s: loop.iterate(method, n, s, s.it + steps))(nlps, states)


def _restart_lanes(nlps, states, need, method):
    """``states`` (a set of lanes) with the lanes ``need`` restarted (``method.restart``)."""
    new = eqx.filter_vmap(lambda n, s: method.restart(n, s))(nlps, states)
    return jax.tree.map(lambda a, b: jnp.where(need.reshape(need.shape + (1,) * (a.ndim - 1)), a, b), new, states)


#: :func:`_segment` on pytrees (``benchmarks/iteration_cost.py``; the batch driver runs it on
#: packed arrays, see :func:`_lane_programs`)
segment_jit = options_jit()(_segment)


@_jit
def _gather_jit(nlps, states, idx):
    return _take(nlps, idx), _take(states, idx)


@options_jit()
def _finish_batch_jit(nlps, states, opts, valid, light):
    """:func:`jtraj.solver.core.finish` over a batch, vmapped (see :func:`_finish_lanes` on a CPU)."""
    return eqx.filter_vmap(lambda n, s, v, l: finish(n, s, opts, v, l))(nlps, states, valid, light)


def _finish_lanes(nlps, states, opts, valid, slots: int, light):
    """:func:`_finish_batch_jit` over ``slots`` problems at a time (the last group padded
    with a repeat of its first problem), the results concatenated in order. On a CPU a
    wide vmap costs more per problem, as the loop's lanes do (serial3, N = 20, one core:
    2.1 ms per problem at 8 lanes, 3.9 at 256, 4.5 at 1024), and the kernel, compiled for
    ``slots`` lanes, does not depend on the batch size. With the restart's kernel also on
    gathered lanes, a first batch of a new size (72 benchmark pairs after 64, one core)
    took 6.9 s instead of 20.4 s (2.9 s warm): as a ``lax.map`` inside one kernel the
    finish took 7 s to compile for each size. The same 1024 pairs: the same results to
    the last bit, 35.8-37.2 against 35.5-36.3 s. The ``light`` problems (NumPy mask, see
    :func:`jtraj.solver.core.finish`) go first, in groups of their own, so that their groups skip the work
    they do not need."""
    B = int(valid.shape[0])
    order = np.argsort(~light, kind="stable")  # the light problems first, each kind in order
    parts = []
    for start in range(0, B, slots):
        idx = _padded(order[start:start + slots], slots)
        sub_nlps, (sub_states, sub_valid) = _gather_jit(nlps, (states, valid), idx)
        parts.append(_finish_batch_jit(sub_nlps, sub_states, opts, sub_valid, jax.device_put(light[idx])))
    # in order already where all or none are light: no permutation
    back = None if not light.any() or light.all() else np.argsort(order)
    return _join_jit(parts, back, B)


@functools.partial(jax.jit, static_argnums=2)
def _join_jit(parts, back, size: int):
    """The groups' results concatenated, cut to ``size`` and put in order by ``back``
    (None: in order already), as one program: leaf by leaf, eager ``concatenate`` and
    slicing dispatched about 50 small programs per batch (a profile of a dataset
    worker's chunk of 256 pairs: 0.10 of its 2.1 s under the profiler)."""
    def one(*xs):
        x = jnp.concatenate(xs)[:size]
        return x if back is None else x[back]

    return jax.tree.map(one, *parts)


def _padded(group, width: int):
    """Lane indices for ``group`` (a NumPy index array, at most ``width`` long) padded to
    ``width`` with repeats of its first entry (a fixed width, one compilation; a repeated
    lane computes and writes back the same result twice). A NumPy array: indexing on the
    host dispatches no program."""
    return np.concatenate([group, np.repeat(group[:1], width - group.size)])


def _take(tree, idx):
    return jax.tree.map(lambda x: x[idx] if eqx.is_array(x) else x, tree)


def lane_counts(slots: int) -> list[int]:
    """Lane counts a compacted batch steps down through once nothing is pending: on a CPU
    a vmapped iteration costs about its lane count, so the stragglers at the end of a
    batch run on 1/4 and 1/16 of the lanes, but on no fewer than 2 (each count is one
    more compilation, cached); on an accelerator lanes are nearly free and the count
    stays. Stopping at 2 lanes rather than 1 is as fast and compiles one segment program
    less."""
    if jax.default_backend() != "cpu":
        return [slots]
    return sorted({slots, max(slots // 4, min(slots, 2)), max(slots // 16, min(slots, 2))}, reverse=True)


def cpu_lanes(nz: int) -> int:
    """The default lane count on a CPU for problems of about ``nz`` unknowns: 16 at
    serial3's N = 20 (nz = 80), fewer for larger problems (8 at N = 40), at least 4.
    Beyond that each lane costs more (the working set outgrows the core's cache), and the
    threshold falls as N grows: on one core, 16 lanes solve 256 benchmark pairs at N = 20
    about 5 % faster than 8 and 12 % faster than 24 or 32; at N = 40, 4 lanes beat 8."""
    return int(min(16, max(4, 1280 // max(nz, 1))))


def _solve_compacted(problems, opts, transcription, init, warm, slots: int, steps: int, progress=None):
    """Solve B problems (more than the smallest lane count) with a fixed number of
    vmapped slots, refilled as problems finish. A vmapped ``while_loop`` runs every
    member until the slowest is done, so one batch costs max(iterations) per problem;
    running segments of ``steps`` iterations and
    handing finished slots to pending problems brings the cost to about the mean. Once
    nothing is pending, the unfinished problems move to fewer lanes (see
    :func:`lane_counts`). Each problem takes the iterations it takes in a one-shot batch
    (results equal up to rounding at another batch width), restarts included: a run that
    ends uncertified is restarted on its lane (see :func:`_run_lanes`). With lanes held
    throughout, about a third of the lane-iterations would be idle."""
    nlps, states, valid = _prepare_batch_jit(problems, opts, transcription, init, warm)
    B = int(valid.shape[0])
    report = None if progress is None else (lambda k: progress(k, B))
    states = _run_lanes(nlps, states, np.arange(B), opts, slots, steps, report)
    return _finish_all(nlps, states, opts, valid, slots)


def _finish_all(nlps, states, opts, valid, slots: int, light=None):
    """:func:`jtraj.solver.core.finish` over a batch; on a CPU ``slots`` problems at a time (see
    :func:`_finish_lanes`). ``light``: (B,) NumPy mask of the problems the interior-point
    method decided (see :func:`jtraj.solver.core.finish`), or None."""
    light = np.zeros(int(valid.shape[0]), bool) if light is None else np.asarray(light, bool)
    if jax.default_backend() == "cpu":
        return _finish_lanes(nlps, states, opts, valid, slots, light)
    return _finish_batch_jit(nlps, states, opts, valid, jnp.asarray(light))


@options_jit()
def _ip_init_batch_jit(nlps, states, opts):
    """The interior-point states of a batch (a state the AL loop would not run, a warm
    start already optimal, starts finished)."""
    def one(n, s):
        st = ipm.InteriorPoint().init(n, s.z, opts.ip_mu_init, opts.ip_bound_push, opts.ip_first_shift)
        return st._replace(done=s.done)

    return eqx.filter_vmap(one)(nlps, states)


@_jit
def _ip_merge_jit(nlps, states, ips):
    """The AL states with the interior-point method's results where it decided
    (:meth:`jtraj.solver.ipm.InteriorPoint.postprocess`), and where that is."""
    solved = ipm.decided(states, ips)
    merged = eqx.filter_vmap(lambda n, s, st: ipm.InteriorPoint().postprocess(n, st, s))(nlps, states, ips)
    return jax.tree.map(lambda a, b: jnp.where(solved.reshape(solved.shape + (1,) * (a.ndim - 1)), a, b),
                        merged, states), solved


def _solve_batch_ip(problems, opts, transcription, init, warm, slots: int, steps: int, progress=None):
    """``solve_batch`` with ``method="ip"``: the interior-point method on every problem
    through ``slots`` lanes (:func:`_run_pool`), then the AL loop on the problems it left
    unsolved (the same lanes, :func:`_run_lanes`), then the finish."""
    nlps, states, valid = _prepare_batch_jit(problems, opts, transcription, init, warm)
    ips = _ip_init_batch_jit(nlps, states, opts)
    todo = np.flatnonzero(~np.asarray(ips.done))
    B, before = int(valid.shape[0]), int(valid.shape[0]) - todo.size
    # (progress counts a problem once its interior-point run ends, also where the AL
    # loop goes on from it)
    report = None if progress is None else (lambda k: progress(before + k, B))
    ips = _run_pool(nlps, ips, todo, opts, slots, report)
    states, solved = _ip_merge_jit(nlps, states, ips)
    solved = np.asarray(solved)
    todo = np.flatnonzero(~solved & ~np.asarray(states.done) & np.asarray(valid))
    states = _run_lanes(nlps, states, todo, opts, slots, steps)
    sol = _finish_all(nlps, states, opts, valid, slots, light=solved)
    return dataclasses.replace(sol, iterations=_add_ip_iterations(sol.iterations, solved, ips.it))


@jax.jit
def _add_ip_iterations(iterations, solved, ip_iterations):
    """The interior-point iterations added where the AL loop went on after them."""
    return iterations + jnp.where(solved, 0, ip_iterations)


def _run_pool(nlps, states, todo, opts, slots: int, progress=None):
    """The interior-point method on the problems ``todo`` (indices into the batch) through
    ``slots`` vmapped lanes, refilled inside one compiled loop (``_LanePrograms.pool``);
    returns the states.

    A lane whose problem finishes takes the next pending one at once, in the same loop:
    the AL loop's segments (:func:`_run_lanes`) hand lanes over only between segments of
    ``segment`` iterations, and a problem finishing within one left its lane idle for the
    rest of it, about half a segment per problem (on serial3 at N = 20 about 20-30 % of
    the lane-iterations; refilled at once, 3 %). Once nothing is pending and at most the
    next smaller lane count (:func:`lane_counts`) of problems is left, the loop returns
    and the rest goes on through that many lanes.

    ``progress(finished)``: called on the host with the number of ``todo`` problems
    finished so far; the pool then returns every :func:`_round_size` problems handed out
    and goes on from where it stopped (the same program; each problem takes the same
    iterates, see :func:`_pool_rounds`)."""
    B = todo.size
    if B == 0:
        return states
    counts = lane_counts(slots)
    while len(counts) > 1 and counts[1] >= B:  # few problems: fewer lanes
        counts = counts[1:]
    # (steps 0: the pool runs no segments)
    progs = _lane_programs(_packing.packing(nlps), _packing.packing(states), 0, jax.default_backend())
    split = split_options(opts)
    total = int(jax.tree.leaves(states)[0].shape[0])
    # the batch padded to a power of two, at least 64 (the pool takes it whole: one
    # program per lane count and size, not per batch size)
    size = max(_POOL_MIN, counts[0], 1 << (total - 1).bit_length())
    all_nlps, all_states = progs.pack(_packing.arrays(nlps), _packing.arrays(states), size)
    queue = todo
    for i, lanes in enumerate(counts):
        first = np.zeros(lanes, np.int64)
        first[:min(lanes, queue.size)] = queue[:lanes]
        stop_at = counts[i + 1] if i + 1 < len(counts) else 0
        all_states, lane_ids, open_ = _pool_rounds(progs, all_nlps, all_states, queue, first,
                                                   np.arange(lanes) < queue.size, stop_at, split, size,
                                                   None if progress is None else (lambda left: progress(B - left)))
        queue = np.asarray(lane_ids)[np.asarray(open_)]
        if queue.size == 0:
            break
    return _packing.from_arrays(progs.unpack(all_states, total), progs.states)


def _round_size(lanes: int, queued: int) -> int:
    """Problems handed out per round of the pool when progress is reported: an eighth of
    the queue, at least the lane count (each round ends with one call back to the host
    and the lanes written back and gathered again)."""
    return max(lanes, -(-queued // 8))


def _pool_rounds(progs, all_nlps, all_states, queue, first, live, stop_at: int, split, size: int, left=None):
    """One lane count's pool over ``queue`` (the problems on the lanes ``first`` where
    ``live``, then the pending ones), as one call of the pool program, or with ``left``
    (called with the number of queued problems not finished yet) in rounds: a round
    stops once its share of the queue is handed out, leaving the lanes' problems running
    (``stop_at`` = the lane count), and the next goes on with the same lanes and the rest
    of the queue. A lane freed in a round's last iteration waits for the next round; no
    problem's iterates change (lanes are independent), only which iteration starts it."""
    lanes = first.size
    q = np.zeros(size, np.int64)  # the queue (problem indices), padded
    while True:
        on = int(np.sum(live))  # queue[:on] are on the lanes
        end = queue.size if left is None else min(queue.size, on + _round_size(lanes, queue.size))
        last = end == queue.size
        q[:] = 0
        q[:queue.size] = queue
        all_states, lane_ids, open_ = progs.pool(all_nlps, all_states, q, np.asarray(end), first, live,
                                                 np.asarray(stop_at if last else lanes), split)
        if left is None:
            return all_states, lane_ids, open_
        lane_ids, open_ = np.asarray(lane_ids), np.asarray(open_)
        left(queue.size - end + int(np.sum(open_)))
        if last:
            return all_states, lane_ids, open_
        # the lanes' unfinished problems first (on their lanes), then the pending ones
        queue = np.concatenate([lane_ids[open_], queue[end:]])
        first, live = lane_ids, open_


#: the smallest batch size the interior-point pool's programs are compiled for (see _run_pool)
_POOL_MIN = 64


def _run_lanes(nlps, states, todo, opts, slots: int, steps: int, progress=None):
    """Run the problems ``todo`` (indices into the batch) to the end of their loop through
    ``slots`` vmapped lanes (see :func:`_solve_compacted`); returns the states.

    The batch's problems and states travel packed (:mod:`jtraj._packing`): after each
    segment one call writes the lanes back and takes the next ones (:func:`_lane_programs`).
    A run that ended uncertified in a segment is restarted (:func:`jtraj.solver.al.restart_state`) on its lane
    and goes on there: 256 benchmark pairs of seed 1, one core, PBM (whose fallback is
    such a restart, 13 pairs) 7.7-8.1 s against 8.2-8.9 s with the restarts in a second
    round of lanes after the batch, PHR (3 restarts) unchanged.
    With a gather, a segment and a scatter per segment on the pytrees (``eqx.filter_jit``,
    about 50 leaves), the driver's own work was 14 % of a batch's time (serial3, N = 20,
    128 pairs, one core: 0.25 s gathering and 0.22 s scattering of 5.2 s).
    ``progress(finished)``: called after each segment with the number of ``todo``
    problems finished."""
    B = todo.size
    counts = lane_counts(slots)
    while len(counts) > 1 and counts[1] >= B:  # few problems: fewer lanes
        counts = counts[1:]
    # fewer problems than lanes: the other lanes repeat the first problem (the same
    # iterates, written back twice)
    idx = np.concatenate([np.arange(min(counts[0], B)), np.zeros(max(counts[0] - B, 0), int)])
    nxt = min(counts[0], B)
    done = np.zeros(B, bool)
    if todo.size == 0:
        return states
    progs = _lane_programs(_packing.packing(nlps), _packing.packing(states), steps, jax.default_backend())
    split = split_options(opts)
    all_nlps, all_states = progs.pack(_packing.arrays(nlps), _packing.arrays(states), None)
    lanes = todo[idx]  # NumPy index arrays: the compiled calls take them without jnp's dispatch
    sub_nlps, sub_states = progs.take(all_nlps, all_states, lanes)
    while True:
        sub_states, fin, need = progs.segment(sub_nlps, sub_states, split)
        need = np.asarray(need)
        if need.any():
            # a run that ended uncertified goes on, restarted, on its lane; compiled for a
            # lane count only when a restart first happens there
            sub_states, fin = progs.restart(sub_nlps, sub_states, need, split)
        fin = np.asarray(fin)
        done[idx[fin]] = True
        if progress is not None:
            progress(int(done.sum()))
        for j in np.flatnonzero(fin):
            if nxt < B:
                idx[j] = nxt
                nxt += 1
        if done.all():
            return _packing.from_arrays(progs.result(all_states, sub_states, lanes), progs.states)
        open_ = np.flatnonzero(~done)  # running or pending
        if nxt >= B and len(counts) > 1 and len(open_) <= counts[1]:
            counts = counts[1:]
            # the unfinished problems, padded with a finished one (a lane that idles)
            pad = np.flatnonzero(done)[:1]
            idx = np.concatenate([open_, np.repeat(pad, counts[0] - len(open_))])
        new_lanes = todo[idx]
        all_states, sub_nlps, sub_states = progs.exchange(all_nlps, all_states, sub_states, lanes, new_lanes)
        lanes = new_lanes


class _Pool(NamedTuple):
    """The carry of the interior-point lane pool's loop (``pool`` in :func:`_lane_programs`)."""

    #: the lanes' problems and states (packed array leaves)
    lane_nlps: Any
    lane_states: Any
    #: every problem's state (packed), the lanes' finished ones written back
    states: Any
    #: the problem each lane holds, and whether it holds an unfinished one
    lanes: Any
    live: Any
    #: queued problems handed to lanes so far
    queued: Any


class _LanePrograms(NamedTuple):
    """The compiled programs of :func:`_run_lanes` on packed batches (tuples of
    ``(B, width)`` arrays, see :mod:`jtraj._packing`)."""

    pack: Any  # (nlps' arrays, states' arrays, rows or None) -> packed nlps, packed states (padded to rows)
    take: Any  # (nlps, states, lanes) -> the lanes' nlps and states
    segment: Any  # (lane nlps, lane states, split options) -> (lane states, finished, to restart)
    restart: Any  # (lane nlps, lane states, which, split options) -> (lane states, finished)
    exchange: Any  # (nlps, states, lane states, lanes, next lanes) -> lanes written back, next taken
    result: Any  # (states, lane states, lanes) -> the states' arrays, lanes written back (_packing.from_arrays)
    pool: Any  # (nlps, states, queue, count, lanes, live, stop_at, split options) -> (states, lanes, unfinished)
    unpack: Any  # (states, rows) -> the first rows' states' arrays (_packing.from_arrays)
    states: _packing.Packing  # how the states are packed


def _pad_rows(packed: tuple, rows: int | None) -> tuple:
    """Packed arrays with rows of zeros added up to ``rows`` (None: as they are)."""
    return packed if rows is None else tuple(jnp.pad(a, ((0, rows - a.shape[0]), (0, 0))) for a in packed)


@functools.lru_cache(maxsize=32)
def _lane_programs(pn: _packing.Packing, ps: _packing.Packing, steps: int, backend: str) -> _LanePrograms:
    """The programs for problems packed as ``pn`` and states as ``ps`` (the AL loop's
    states for ``segment`` and ``restart``, the interior-point method's for ``pool``;
    plain ``jax.jit`` on packed arrays: no pytree partitioning per call), compiled with
    the solver's XLA options on a CPU (see :mod:`jtraj._compile`)."""
    options = supported_options(SOLVER_XLA_OPTIONS) if backend == "cpu" else None
    jit = functools.partial(jax.jit, compiler_options=options)

    def put(states, sub, lanes):  # (a lane index out of bounds: that lane not written)
        return tuple(a.at[lanes].set(b, mode="drop") for a, b in zip(states, sub))

    def take(nlps, states, lanes):
        return tuple(a[lanes] for a in nlps), tuple(a[lanes] for a in states)

    def segment(nlps, states, split):
        # (the AL method: a method's run in segments of `steps` iterations, restarted
        # where it ended uncertified; terminate and needs_restart on all lanes at once)
        method = ALMethod(TracedOptions(split))
        nlps, before = _packing.unpack(nlps, pn), _packing.unpack(states, ps)
        out = _segment(nlps, before, None, steps, method)
        fin = method.terminate(None, out)
        # the lanes whose run ended in this segment uncertified, to restart
        need = fin & ~method.terminate(None, before) & method.needs_restart(None, out)
        return _packing.pack(_packing.arrays(out), ps), fin, need

    def restart(nlps, states, need, split):
        method = ALMethod(TracedOptions(split))
        nlps = _packing.unpack(nlps, pn)
        out = _restart_lanes(nlps, _packing.unpack(states, ps), need, method)
        return _packing.pack(_packing.arrays(out), ps), method.terminate(None, out)

    def exchange(nlps, states, sub, lanes, new_lanes):
        states = put(states, sub, lanes)
        return (states, *take(nlps, states, new_lanes))

    def pool(nlps, states, queue, count, lanes, live, stop_at, split):
        # (the interior-point method, see _run_pool) the problems queue[:count] through
        # the lanes (their first problems `lanes`, those `live`), each lane taking the next
        # queued problem as its own finishes, until nothing is queued and at most
        # `stop_at` are unfinished; returns the states with every lane's written back, the
        # lanes' problems and which of them are unfinished. The loop carries the lanes'
        # array leaves (a loop's or a cond's carry turns a static leaf into an array)
        # (the interior-point method: its step on every lane, vmapped; terminate on all
        # lanes at once)
        method = ip_method(TracedOptions(split))
        B = states[0].shape[0]
        step = eqx.filter_vmap(lambda n, s: method.step(method.enter(n, s), s))

        def finished(ls):
            return method.terminate(None, _packing.from_arrays(ls, ps))

        def select(mask, a, b):
            return [jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y) for x, y in zip(a, b)]

        def write_back(states, ls, rows):  # rows B (out of bounds): not written
            return put(states, _packing.pack(ls, ps), rows)

        def gather(states, rows):
            n, s = take(nlps, states, rows)
            return _packing.arrays(_packing.unpack(n, pn)), _packing.arrays(_packing.unpack(s, ps))

        def refill(c: _Pool) -> _Pool:
            fin = finished(c.lane_states)
            states = write_back(c.states, c.lane_states, jnp.where(c.live & fin, c.lanes, B))
            free = ~c.live | fin
            pos = c.queued + jnp.cumsum(free) - 1
            take = free & (pos < count)
            lanes = jnp.where(take, queue[jnp.clip(pos, 0, queue.shape[0] - 1)], c.lanes)
            new_n, new_s = gather(states, lanes)
            return _Pool(lane_nlps=select(take, new_n, c.lane_nlps), lane_states=select(take, new_s, c.lane_states),
                         states=states, lanes=lanes, live=(c.live & ~fin) | take, queued=c.queued + jnp.sum(take))

        def handover(c: _Pool) -> _Pool:  # only where a lane is free: a real branch (the loop is not vmapped)
            free = jnp.any(c.live & finished(c.lane_states)) | (jnp.any(~c.live) & (c.queued < count))
            return jax.lax.cond(free, refill, lambda c: c, c)

        def body(c: _Pool) -> _Pool:
            # the lanes whose problem finished (in the last iteration, or before its
            # first) handed over, then one iteration
            c = handover(c)
            new = step(_packing.from_arrays(c.lane_nlps, pn), _packing.from_arrays(c.lane_states, ps))
            return c._replace(lane_states=select(finished(c.lane_states), c.lane_states, _packing.arrays(new)))

        def cond(c: _Pool):
            return (c.queued < count) | (jnp.sum(c.live & ~finished(c.lane_states)) > stop_at)

        ln, ls = gather(states, lanes)
        end = jax.lax.while_loop(cond, body, _Pool(lane_nlps=ln, lane_states=ls, states=states, lanes=lanes,
                                                   live=live, queued=jnp.sum(live)))
        states = write_back(end.states, end.lane_states, jnp.where(end.live, end.lanes, B))
        return states, end.lanes, end.live & ~finished(end.lane_states)

    return _LanePrograms(
        pack=jit(lambda nlps, states, rows: (_pad_rows(_packing.pack(nlps, pn), rows),
                                             _pad_rows(_packing.pack(states, ps), rows)), static_argnums=2),
        # the segment program kept across processes where the compilation cache is on
        # (jtraj._tracecache; plain jit where it is off: eqx.filter_jit's per-call work is
        # what the packing saves)
        segment=_tracecache.cached("segment", segment, repr((pn, ps, steps)), options, fallback=jit(segment)),
        restart=_tracecache.cached("restart", restart, repr((pn, ps)), options, fallback=jit(restart)),
        take=jit(take), exchange=jit(exchange, donate_argnums=1),
        # (no donation: the unpacked arrays cannot reuse the packed buffers; called once)
        result=jit(lambda states, sub, lanes: _packing.arrays(_packing.unpack(put(states, sub, lanes), ps))),
        pool=_tracecache.cached("pool", pool, repr((pn, ps)), options, fallback=jit(pool)),
        unpack=jit(lambda states, rows: _packing.arrays(_packing.unpack(tuple(a[:rows] for a in states), ps)),
                   static_argnums=1),
        states=ps)


def solve_problems(problems, opts, transcription, init, warm: bool, slots, segment: int,
                   progress=None) -> Solution:
    """:func:`jtraj.solve_batch`'s solve of built problems (a batch of :class:`Problem`) from
    ``init`` (arrays), by the host-driven lane driver (see ``slots`` there).
    ``progress(finished, B)``: called on the host as problems finish, last with (B, B)."""
    B = int(jax.tree.leaves(problems.q_start)[0].shape[0])
    warm = bool(warm)
    if opts.method == "ip":
        sol = _solve_batch_ip(problems, opts, transcription, init, jax.device_put(warm), slots or B, segment,
                              progress)
    elif slots is not None and B > min(lane_counts(slots)):
        sol = _solve_compacted(problems, opts, transcription, init, jax.device_put(warm), slots, segment, progress)
    else:
        sol = solve_batch_jit(problems, opts, transcription, init, jax.device_put(warm))
    if progress is not None:
        jax.block_until_ready(sol.status)
        progress(B, B)
    return sol
