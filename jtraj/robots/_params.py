"""Validated parameter overrides shared by :func:`jtraj.robots.get` and the URDF loader."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ._base import Limits, Robot

# parameters that must stay strictly positive when overridden
_POSITIVE = {"lengths", "masses", "leg_mass", "slider_mass", "platform_mass", "link_length",
             "link_mass", "R", "r", "L", "wheel_radius", "track", "mass",
             "link_com", "link_inertia", "inertia", "wheel_inertia", "body_radius",
             "eps1", "eps2", "rho_min", "rho_max", "cyl_mass", "piston_mass", "cyl_inertia",
             "piston_inertia", "platform_radius", "z_home", "rhod_max", "det_min"}


def own_parameter_names(robot: Robot) -> list[str]:
    """Names :func:`with_params` accepts for ``robot``: its numeric parameters and the
    fields of its :class:`Limits`."""
    own = [f.name for f in dataclasses.fields(robot)
           if f.name not in ("limits", "friction", "actuator")
           and not f.metadata.get("static", False)]
    return own + [f.name for f in dataclasses.fields(Limits)]


def with_params(robot: Robot, **overrides) -> Robot:
    """A validated copy of ``robot`` with some parameters replaced.

    Keys are numeric parameters of the robot (e.g. ``masses``, ``gravity_accel``) or
    limit fields (e.g. ``tau_max``). Values must have the shape of the parameter they
    replace. Every value set is stored as an array, scalars as 0-d arrays: a leaf that
    ``jit`` traces, so that robots differing only in these values share compiled
    programs (a Python float field would be static to them).
    """
    allowed = own_parameter_names(robot)
    limit_fields = {f.name for f in dataclasses.fields(Limits)}
    limit_changes, own_changes = {}, {}
    for key, value in overrides.items():
        if key not in allowed:
            raise ValueError(f"unknown override {key!r} for robot {robot.name!r}; "
                             f"expected one of {allowed}")
        current = getattr(robot.limits, key) if key in limit_fields else getattr(robot, key)
        if value is None:
            if key not in limit_fields:
                raise ValueError(f"override {key} cannot be None")
            limit_changes[key] = None
            continue
        if isinstance(value, jax.core.Tracer):  # traced (a derivative): its shape checked only
            shape = np.shape(current) if current is not None else value.shape
            if value.shape != shape:
                raise ValueError(f"override {key} must have shape {shape}, got {value.shape}")
            if key in limit_fields:
                limit_changes[key] = value
            else:
                own_changes[key] = value
            continue
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"override {key} must be numeric, got {value!r}") from err
        shape = np.shape(current) if current is not None else arr.shape
        if arr.shape != shape and not (arr.ndim == 0 and len(shape) == 1):
            raise ValueError(f"override {key} must have shape {shape}, got {arr.shape}")
        arr = np.broadcast_to(arr, shape)
        if np.isnan(arr).any() or (key not in limit_fields and not np.isfinite(arr).all()):
            raise ValueError(f"override {key} must be finite, got {arr.tolist()}")
        if key in _POSITIVE and (arr <= 0).any():
            raise ValueError(f"override {key} must be > 0, got {arr.tolist()}")
        if key in limit_fields:
            limit_changes[key] = arr
        else:
            own_changes[key] = jnp.asarray(arr)
    if limit_changes:
        merged = {f.name: getattr(robot.limits, f.name) for f in dataclasses.fields(Limits)}
        merged.update(limit_changes)
        own_changes["limits"] = Limits.make(robot.n, n_actuators=robot.n_actuators, **merged)
    return dataclasses.replace(robot, **own_changes)
