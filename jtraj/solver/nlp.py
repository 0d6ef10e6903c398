"""The transcribed problem in augmented-Lagrangian form (:class:`NLP`) and its
multipliers, shared by the AL and the interior-point methods."""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .. import lq
from .._math import log1p
from ..problem import Problem
from ..transcription import Layout, StageData, Transcription, decoupled_hessian, decoupled_hessian_bounds
from . import curvature
from .options import SolverOptions


# ----------------------------------------------------------------------------------------
# the NLP in AL form


class Multipliers(NamedTuple):
    eq: dict
    ineq: dict
    glob: Array


class NLP(eqx.Module):
    """The transcribed problem with everything the solver needs, pure functions of z."""

    problem: Problem
    tr: Transcription = eqx.field(static=True)
    layout: Layout
    sd: StageData
    #: the reference path of the tests: stage Hessians by one forward-over-reverse pass
    #: and the decoupled Hessian in z assembled with jacfwd, like the other transcriptions
    generic_hessian: bool = eqx.field(static=True, default=False)
    #: Newton directions by the stage-wise Riccati recursion (decoupled only, see
    #: :mod:`jtraj.lq`) instead of dense Cholesky factorisations of the Hessian in z
    stagewise: bool = eqx.field(static=True, default=False)
    #: the inequalities' AL term: "phr" or "pbm" (see ``SolverOptions.inequality_penalty``)
    ineq_penalty: str = eqx.field(static=True, default=SolverOptions.inequality_penalty)
    pbm_init: float = eqx.field(static=True, default=SolverOptions.pbm_init)
    pbm_ratio: float = eqx.field(static=True, default=SolverOptions.pbm_ratio)
    #: the interior-point method's curvature of the dynamics, "exact" or "gauss_newton"
    #: (see :mod:`jtraj.solver.curvature`; the AL loop's Hessians are always exact)
    ip_curvature: str = eqx.field(static=True, default="exact")

    #: with ``ineq_penalty == "pbm"``: whether the PBM term is on (the first run) or PHR
    #: (a restart, see :func:`jtraj.solver.al.with_phase`); a traced flag, so one compiled loop serves both
    pbm_on: Array | bool = True

    @property
    def pbm_active(self):
        """Whether the PBM term is in use now (a traced bool; False for a PHR problem)."""
        return jnp.asarray(self.pbm_on) & (self.ineq_penalty == "pbm")

    def ineq_term(self, g, rho, mu):
        if self.ineq_penalty == "lagrangian":  # the interior-point method's (jtraj.solver.ipm)
            return jnp.sum(rho * g)
        if self.ineq_penalty == "pbm":
            return jnp.where(self.pbm_on, _pbm(g, rho, mu), _phr(g, rho, mu))
        return _phr(g, rho, mu)

    def ineq_update(self, g, rho, mu):
        """The first-order multiplier update of an inequality term (the multiplier the
        term implies at g)."""
        phr = jnp.clip(rho + mu * g, 0.0, 1e10)
        if self.ineq_penalty == "pbm":
            slope = jnp.clip(_pbm_slope(mu * g), 1.0 / self.pbm_ratio, self.pbm_ratio)
            return jnp.where(self.pbm_on, jnp.clip(rho * slope, PBM_FLOOR, 1e10), phr)
        return phr

    def W(self, z):
        return self.tr.stage_vectors(self.problem, self.layout, z)

    def stage_al(self, w, sdk, mult_k, mu, kink=None):
        return self._stage_al_parts(w, sdk, mult_k, mu, kink)[0]

    def _stage_al_parts(self, w, sdk, mult_k, mu, kink=None, tau=None):
        """(AL value, equalities, inequalities, cost terms) of one sample. ``tau``: the
        sample's efforts as an input of their own (transcriptions whose control slot is
        the acceleration, see :meth:`_stage_derivatives_split`) instead of the dynamics."""
        # the dynamics once per sample, shared by the cost and the constraints
        if tau is None:
            a_tau = self.tr.accel_and_tau(self.problem, *self.tr.split_stage(self.problem, w)[:3])
        else:
            a_tau = (self.tr.split_stage(self.problem, w)[2], tau)
        eq, ineq = self.tr.stage_constraints(self.problem, w, sdk, a_tau)
        terms = self.tr.stage_cost_terms(self.problem, w, sdk, a_tau)
        val = sum(terms.values())
        for key, c in eq.items():
            val = val + jnp.sum(mult_k.eq[key] * c) + 0.5 * mu * jnp.sum(c**2)
        for key, g in ineq.items():
            val = val + self.ineq_term(g, mult_k.ineq[key], mu)
            if kink is not None:
                val = val + kink_curvature(g, mult_k.ineq[key], mu, kink)
        return val, eq, ineq, terms

    def al_and_parts(self, z, mult, mu):
        """(AL value, ((equalities, inequalities, global inequalities), cost)) at z, from
        one pass through the dynamics (the parts are what :meth:`constraints` and
        :meth:`cost_terms` compute apart)."""
        val, eq, ineq, terms = jax.vmap(self._stage_al_parts, in_axes=(0, 0, _stage_axes(mult), None))(
            self.W(z), self.sd, _stage_mult(mult), mu)
        cost = sum(jnp.sum(v) for v in terms.values())
        glob = self.tr.global_inequalities(self.problem, self.layout, z)
        return jnp.sum(val) + self.global_al(z, mult, mu), ((eq, ineq, glob), cost)

    def al_grad_and_parts(self, z, mult, mu):
        """(gradient of the AL in z, parts of :meth:`al_and_parts`): the loop's test after
        each Newton step."""
        return jax.grad(self.al_and_parts, has_aux=True)(z, mult, mu)

    def global_al(self, z, mult, mu):
        # (the jerk rows, Problem(jerk=True), are global rows of z; the Riccati paths,
        # which take the global rows as functions of T alone, are not used for them)
        return self.ineq_term(self.tr.global_inequalities(self.problem, self.layout, z), mult.glob, mu)

    def al_value(self, z, mult, mu):
        return self.al_and_parts(z, mult, mu)[0]

    @property
    def split_derivatives(self) -> bool:
        """Whether :meth:`stage_derivatives` goes through the efforts
        (:meth:`_stage_derivatives_split`)."""
        return self.tr.controls_are_accelerations and not self.generic_hessian

    def stage_derivatives(self, W, mult, mu, kink=None, efforts=False):
        """Per-stage values, gradients and Hessians of the AL terms in w_k: (val (N+1,),
        c (N+1, nw), Hk (N+1, nw, nw)). ``kink`` (None, or a traced margin): Hk includes
        :func:`kink_curvature` with that margin. Where the control slot is the
        acceleration (decoupled, spline) by :meth:`_stage_derivatives_split`, elsewhere
        (and with ``generic_hessian``) by one forward-over-reverse pass per stage.
        ``efforts`` (split only): also the efforts tau (N+1, m) and their Jacobians in
        w_k (N+1, m, nw), which the chain rule computed on the way."""
        if efforts and not self.split_derivatives:
            raise ValueError("stage_derivatives(efforts=True) needs the split derivatives")
        per_stage = (functools.partial(self._stage_derivatives_split, efforts=efforts) if self.split_derivatives
                     else self._stage_derivatives_plain)
        return jax.vmap(per_stage, in_axes=(0, 0, _stage_axes(mult), None, None))(
            W, self.sd, _stage_mult(mult), mu, kink)

    def _stage_derivatives_plain(self, w, sdk, mk, mu, kink):
        def value_grad(w_):
            v, gw = jax.value_and_grad(self.stage_al)(w_, sdk, mk, mu, kink)
            return gw, (v, gw)

        H, (val, g) = jax.jacfwd(value_grad, has_aux=True)(w)
        return val, g, H

    def _stage_derivatives_split(self, w, sdk, mk, mu, kink, efforts=False):
        """(value, gradient, Hessian) of one sample's AL by the chain rule through its
        efforts tau = ID(q, qd, a), exact: with phi(w, tau) the AL with tau as an input,
        lam = d phi / d tau and J = d tau / dw,

            H = phi_ww + phi_wt J + J^T phi_tw + J^T phi_tt J + sum_i lam_i d2 tau_i / dw2.

        phi (boxes, penalties, cost) is cheap to differentiate twice; the dear part, the
        last term, is forward-over-reverse on lam . tau along q and qd only: tau is affine
        in the acceleration for every rigid-body model (M(q) a + b(q, qd), see
        :class:`jtraj.robots.Robot`), so its acceleration block is zero and its cross
        block is the transpose of rows already computed (serial3, 8 lanes: the stage
        derivatives 83 -> 66 us per problem and iteration against one pass over all of w)."""
        if self.ineq_penalty == "lagrangian" and self.ip_curvature == "gauss_newton":  # the interior-point model
            return curvature.stage_derivatives_gauss_newton(self, w, sdk, mk, mu, kink, efforts)
        n, nw = self.problem.robot.n, w.shape[0]
        nx, na = 2 * n, nw - 2 * n - 1  # state (q, qd), acceleration slot
        x, a = w[:nx], w[nx:nx + na]

        def tau_of(s, acc):
            return self.tr.accel_and_tau(self.problem, s[:n], s[n:], acc)[1]

        tau = tau_of(x, a)
        Hy, val, gy = self.phi_hessian(w, tau, sdk, mk, mu, kink)
        lam = gy[nw:]

        def weighted(s):  # (gradient of lam . tau in (q, qd, a), tau) at state s
            t, vjp = jax.vjp(tau_of, s, a)
            gs, ga = vjp(lam)
            return jnp.concatenate([gs, ga]), t

        R, Js = jax.jacfwd(weighted)(x)  # (nx + na, nx), (m, nx)
        Ja = jax.jacfwd(lambda acc: tau_of(x, acc))(a)  # (m, na)
        J = jnp.zeros((tau.shape[0], nw), w.dtype).at[:, :nx].set(Js).at[:, nx:nx + na].set(Ja)
        Hs = jnp.zeros((nw, nw), w.dtype).at[:nx + na, :nx].set(R).at[:nx, nx:nx + na].set(R[nx:].T)
        A = Hy[:nw, nw:] @ J
        H = Hy[:nw, :nw] + A + A.T + J.T @ Hy[nw:, nw:] @ J + Hs
        if efforts:
            return val, gy[:nw] + J.T @ lam, H, tau, J
        return val, gy[:nw] + J.T @ lam, H

    def phi_hessian(self, w, tau, sdk, mk, mu, kink):
        """(Hessian (nw + m, nw + m), value, gradient) of phi(w, tau), one sample's AL with
        its efforts as an input (see :meth:`_stage_derivatives_split`), by forward mode over
        the gradient one block of (q, qd, acceleration slot, h, tau) at a time. Each block's
        tangents flow only through the operations that depend on that block (JAX's
        symbolic zeros): the torque box and the energy see tau's, the velocity box qd's,
        nothing in the decoupled AL sees the acceleration's. The same values as one jacfwd
        over the whole of (w, tau) (on 2 x 256 benchmark pairs the same iterations and
        costs to the last bit) for under half its instructions: serial3, N = 20, 8 lanes,
        per problem and Newton iteration (``benchmarks/iteration_cost.py --instructions``),
        the stage derivatives 766 k -> 626 k instructions, the whole iteration 2.297 M ->
        2.096 M (-8.7 %). Splitting the inverse dynamics' forward-over-reverse pass into
        q's and qd's columns the same way cost more (2.135 M: each pass repeats the primal
        and its vjp)."""
        n, nw = self.problem.robot.n, w.shape[0]
        blocks = (w[:n], w[n:2 * n], w[2 * n:nw - 1], w[nw - 1], tau)
        argnums = tuple(range(len(blocks)))

        def phi(q, qd, a, h, t):
            return self._stage_al_parts(jnp.concatenate([q, qd, a, h[None]]), sdk, mk, mu, kink, t)[0]

        def flat(g):  # the blocks' gradients as one vector in (w, tau)'s layout
            return jnp.concatenate([g[0], g[1], g[2], g[3][None], g[4]])

        def flat_grad(*b):
            return flat(jax.grad(phi, argnums=argnums)(*b))

        val, g = jax.value_and_grad(phi, argnums=argnums)(*blocks)
        gy = flat(g)
        cols = [jax.jacfwd(flat_grad, argnums=i)(*blocks) for i in argnums]
        cols[3] = cols[3][:, None]  # the period is a scalar
        return jnp.concatenate(cols, axis=1), val, gy

    def time_al(self, T, mult, mu):
        """The global AL term as a function of the total time T (see global_al)."""
        return self.ineq_term(self.tr.time_inequalities(self.problem, T), mult.glob, mu)

    def al_derivatives(self, z, mult, mu, kink=None):
        """Value, gradient and Hessian of the AL in z, from per-stage pieces (exact; with a
        ``kink`` margin plus the curvature of the inequalities just short of their PHR
        kink, see :func:`kink_curvature`)."""
        W, W_vjp = jax.vjp(self.W, z)
        val_k, c, Hk = self.stage_derivatives(W, mult, mu, kink)
        # the gradient is reverse-mode autodiff through the recursion (the co-states)
        g = W_vjp(c)[0]
        if self.tr.name == "decoupled" and not self.generic_hessian:
            H = decoupled_hessian(self.layout, W, c, Hk)
        else:
            J = jax.jacfwd(self.W)(z)  # (N+1, nw, nz)
            H = jnp.einsum("kai,kaj->ij", J, jnp.einsum("kab,kbj->kaj", Hk, J))
            # co-state (second-order) term of the recursion: d2/dz2 <c, W(z)>, c fixed
            # (zero where W is linear in z: the collocation's states are unknowns)
            if not self.tr.linear_stage_map:
                c_fixed = jax.lax.stop_gradient(c)
                grad_cw = jax.grad(lambda zz: jnp.sum(c_fixed * self.W(zz)))
                if self.tr.linear_in_controls:
                    # W is linear in the controls: the control-control block vanishes and
                    # only the columns of the N periods are differentiated (N, not nz, passes)
                    nu = self.layout.N * self.layout.m_u
                    cols = jax.jacfwd(lambda zh: grad_cw(jnp.concatenate([z[:nu], zh])))(z[nu:])  # (nz, N)
                    H = H.at[:, nu:].add(cols).at[nu:, :nu].add(cols[:nu].T)
                else:
                    H = H + jax.jacfwd(grad_cw)(z)
        gval, ggrad, ghess = (self.global_al(z, mult, mu), jax.grad(self.global_al)(z, mult, mu),
                              jax.hessian(self.global_al)(z, mult, mu))
        return jnp.sum(val_k) + gval, g + ggrad, H + ghess

    def stage_newton_model(self, z, mult, mu, kink=None):
        """(value, stage model, pieces for :meth:`hessian_bounds`) of the AL for the
        stage-wise Newton solve (decoupled transcription; the Hessian in z is never formed)."""
        W = self.W(z)
        val_k, c, Hk = self.stage_derivatives(W, mult, mu, kink)
        T = jnp.sum(W[:-1, -1])
        d1 = jax.grad(self.time_al)
        dphi, d2phi = d1(T, mult, mu), jax.grad(d1)(T, mult, mu)
        model = lq.stage_model(W, c, Hk, self.layout.u_scale, self.layout.h_scale, (dphi, d2phi))
        return jnp.sum(val_k) + self.time_al(T, mult, mu), model, (W, c, Hk, d2phi)

    def hessian_bounds(self, pieces):
        """diag(H) and a function ``free -> bounds on the free row sums of |H|`` in z (see
        :func:`jtraj.transcription.decoupled_hessian_bounds`), the term of T included."""
        W, c, Hk, d2phi = pieces
        hdiag, stage_rows = decoupled_hessian_bounds(self.layout, W, c, Hk)
        # the term of T: d2phi hs^2 on every pair of periods
        hs2 = self.layout.h_scale**2
        is_h = jnp.arange(hdiag.shape[0]) >= self.layout.N * self.layout.m_u

        def rows(free):
            return stage_rows(free) + jnp.where(is_h, jnp.abs(d2phi) * hs2 * jnp.sum(free & is_h), 0.0)

        return hdiag + jnp.where(is_h, d2phi * hs2, 0.0), rows

    def constraints(self, z):
        W = self.W(z)
        eq, ineq = jax.vmap(lambda w, s: self.tr.stage_constraints(self.problem, w, s))(W, self.sd)
        return eq, ineq, self.tr.global_inequalities(self.problem, self.layout, z)

    def cost_terms(self, z):
        W = self.W(z)
        terms = jax.vmap(lambda w, s: self.tr.stage_cost_terms(self.problem, w, s))(W, self.sd)
        return {k: jnp.sum(v) for k, v in terms.items()}


def _phr(g, rho, mu):
    """Rockafellar/PHR term for g <= 0 with multiplier rho >= 0 and penalty mu."""
    return jnp.sum(jnp.maximum(0.0, rho + mu * g) ** 2 - rho**2) / (2 * mu)


#: the smallest PBM multiplier: a multiplier that decays to 0 would leave its constraint
#: unpenalised (the term is rho / mu phi(mu g))
PBM_FLOOR = 1e-8


def _pbm_phi(t):
    """Ben-Tal and Zibulevsky's log-quadratic penalty-barrier function: -log(1 - t) for
    t <= 1/2, continued by the quadratic that matches its value and first two
    derivatives there; phi(0) = 0, phi'(0) = 1, convex, twice differentiable everywhere."""
    tl = jnp.minimum(t, 0.5)
    return jnp.where(t <= 0.5, -log1p(-tl), 2.0 * (t - 0.5) ** 2 + 2.0 * (t - 0.5) + np.log(2.0))


def _pbm_slope(t):
    tl = jnp.minimum(t, 0.5)
    return jnp.where(t <= 0.5, 1.0 / (1.0 - tl), 4.0 * (t - 0.5) + 2.0)


def _pbm(g, rho, mu):
    """Penalty-barrier multiplier term for g <= 0 (multiplier rho > 0, penalty mu):
    ``sum rho / mu phi(mu g)``, twice differentiable (PHR's is once)."""
    return jnp.sum(rho * _pbm_phi(mu * g)) / mu


def kink_curvature(g, rho, mu, margin):
    """A term of value and gradient zero whose Hessian is the penalty's curvature
    ``mu grad g grad g^T`` on the inequalities just short of their PHR kink
    (``-mu margin < rho + mu g <= 0``): added to the Newton model only (see
    ``SolverOptions.kink_margin``)."""
    s = jax.lax.stop_gradient(rho + mu * g)
    near = (s > -mu * margin) & (s <= 0.0)
    dg = g - jax.lax.stop_gradient(g)
    return 0.5 * mu * jnp.sum(jnp.where(near, dg**2, 0.0))


def _stage_mult(mult: Multipliers):
    return Multipliers(eq=mult.eq, ineq=mult.ineq, glob=jnp.zeros(()))


def _stage_axes(mult: Multipliers):
    return Multipliers(eq=jax.tree.map(lambda _: 0, mult.eq), ineq=jax.tree.map(lambda _: 0, mult.ineq), glob=None)


def violation(eq, ineq, glob, mult=None, mu=None):
    """Max normalised violation; with multipliers, the complementarity-aware measure
    max(|c|, |min(-g, rho/mu)|) used to steer the penalty."""
    parts = [jnp.max(jnp.abs(c)) for c in jax.tree.leaves(eq)]
    if mult is None:
        parts += [jnp.max(jnp.maximum(g, 0.0)) for g in jax.tree.leaves(ineq)]
        parts.append(jnp.max(jnp.maximum(glob, 0.0)))
    else:
        parts += [jnp.max(jnp.abs(jnp.minimum(-g, r / mu)))
                  for g, r in zip(jax.tree.leaves(ineq), jax.tree.leaves(mult.ineq))]
        parts.append(jnp.max(jnp.abs(jnp.minimum(-glob, mult.glob / mu))))
    return jnp.max(jnp.stack(parts))
