"""Robot models as pure JAX functions.

Use :func:`get` for the built-in robots and :func:`serial_planar` for a planar arm of
any number of links. A new robot subclasses :class:`Robot` and writes its kinematics
and energies; the dynamics follow by autodiff.
"""

from __future__ import annotations

import importlib
from typing import Callable


from .._linalg import det as small_det
from .._linalg import solve as small_solve
from ._base import Actuator, Friction, Limits, Robot
from ._params import own_parameter_names, with_params
from .serial import SerialPlanar, serial_planar
from .spatial import SpatialSerial, spatial_serial
from .urdf import from_urdf

# name -> "module:factory" (imported lazily so that a broken optional model cannot
# break the others)
_REGISTRY: dict[str, str] = {
    "serial3": "jtraj.robots.serial:serial3",
    "serial3_vertical": "jtraj.robots.serial:serial3_vertical",
    "ibm7535": "jtraj.robots.serial:ibm7535",
    "pkm2": "jtraj.robots.pkm2:pkm2",
    "parallel3": "jtraj.robots.parallel3:parallel3",
    "wmr": "jtraj.robots.wmr:wmr",
    "gough_stewart": "jtraj.robots.gough_stewart:gough_stewart",
    "panda": "jtraj.robots.urdf:panda",
    "ur5": "jtraj.robots.urdf:ur5",
    "ur10": "jtraj.robots.urdf:ur10",
    "kinova": "jtraj.robots.urdf:kinova",
    "so100": "jtraj.robots.urdf:so100",
}

def names() -> list[str]:
    """Names accepted by :func:`get`."""
    return sorted(_REGISTRY)


def _factory(name: str) -> Callable[[], Robot]:
    if not isinstance(name, str) or name not in _REGISTRY:
        raise ValueError(f"robot must be one of {names()}, got {name!r}")
    module, attr = _REGISTRY[name].split(":")
    return getattr(importlib.import_module(module), attr)


def summary(name: str) -> str:
    """One line on the built-in robot ``name``: the first paragraph of its factory's
    docstring (``jtraj robots`` lists them)."""
    import inspect

    doc = inspect.getdoc(_factory(name)) or ""
    return " ".join(doc.split("\n\n")[0].split())


def parameter_names(robot: Robot | str) -> list[str]:
    """Names :func:`with_params` accepts for ``robot`` (a robot or a built-in name): its
    numeric parameters and the fields of its :class:`Limits`."""
    if isinstance(robot, str):
        robot = _factory(robot)()
    return own_parameter_names(robot)


def get(name: str, **overrides) -> Robot:
    """A built-in robot by name, optionally with parameters overridden.

    >>> robot = get("serial3", masses=(10, 8, 5.5))
    """
    return with_params(_factory(name)(), **overrides)


def from_metadata(meta: dict) -> Robot:
    """The robot a dataset's or a trained model's metadata names: the URDF arm it stores
    (``meta["urdf"]``: the file's text and tip link, which ``jtraj dataset --urdf``
    records, so that the dataset and the models trained on it need no file), else the
    built-in robot ``meta["robot"]``; with the parameters ``meta["robot_params"]``
    replaced (:func:`with_params`, ``jtraj dataset --robot-param``) and the
    sampling-period bound ``meta["h_max"]`` (a model's) or ``meta["limits"]["h_max"]``
    (a dataset's) where there is one."""
    h_max = meta.get("h_max", (meta.get("limits") or {}).get("h_max"))
    overrides = dict(meta.get("robot_params") or {}) | ({} if h_max is None else {"h_max": float(h_max)})
    urdf = meta.get("urdf")
    if urdf:
        return from_urdf(urdf["text"], tip_link=urdf.get("tip_link"), name=meta["robot"], **overrides)
    return get(meta["robot"], **overrides)


__all__ = ["Actuator", "Friction", "Limits", "Robot", "SerialPlanar", "SpatialSerial", "from_metadata", "from_urdf",
           "get", "names", "parameter_names", "serial_planar", "small_det", "small_solve", "spatial_serial",
           "summary", "with_params"]
