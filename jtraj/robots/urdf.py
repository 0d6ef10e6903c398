"""Spatial serial arms from URDF files: :func:`from_urdf` and the built-in real arms.

The URDF (a small XML format) is read once, at load time, with the standard library's
``xml.etree.ElementTree``; the result is a :class:`~jtraj.robots.spatial.SpatialSerial`
whose parameters are arrays. Conventions of the format (ROS URDF specification):

* ``<origin xyz rpy>`` places a child frame in its parent: ``R = Rz(yaw) Ry(pitch)
  Rx(roll)`` (fixed-axis roll, pitch, yaw), translation ``xyz``;
* a joint's frame is its child link's frame at ``q = 0``; ``<axis xyz>`` (default
  ``1 0 0``, normalised here) is expressed in it;
* ``<inertial>`` gives a link's mass, its centre of mass (``origin xyz``) and its
  inertia tensor about the centre of mass in a frame rotated by ``origin rpy``.

The chain runs from ``base_link`` to ``tip_link``. Revolute, continuous (revolute
without position limits) and prismatic joints on that path are the degrees of freedom.
Every other link that moves with a body is merged into it, its mass, centre of mass and
inertia combined by the parallel-axis theorem: links behind fixed joints, and the
branches behind movable joints off the path (a gripper's fingers), which are locked at
0 (clamped into their limits; mimic joints follow the joint they mimic). Links behind
fixed joints after the last movable joint ride on the last body and the tip frame is
placed in it. Links that do not move with the chain (the base's own parts, other
branches from the base) do not enter the dynamics of a fixed-base arm.

Limits: ``<limit lower upper>`` gives the joint box (none for continuous joints),
``velocity`` the bound on ``|qd|`` and ``effort`` the bound on ``|tau|``. URDF has no
acceleration or jerk limits: they are arguments (:data:`DEFAULT_QDD_MAX`, no jerk bound
by default). A limit given as an argument (``limits=`` or one of :data:`URDF_LIMITS` among
the overrides, as ``jtraj ... --robot-param qd_max=2`` passes it) replaces the file's,
which may then be missing or zero (files that describe a model for simulation only, such
as example-robot-data's double pendulum, write ``effort="0" velocity="0"``).
"""

from __future__ import annotations

import math
import os
import site
import sys
import sysconfig
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ._base import Limits
from ._params import with_params
from .spatial import SpatialSerial, spatial_serial

#: acceleration bound [rad/s^2 or m/s^2] of every joint when the caller gives none
DEFAULT_QDD_MAX = 10.0

MOVABLE = ("revolute", "continuous", "prismatic")
UNSUPPORTED = ("floating", "planar")

#: published joint limits of the Franka Emika Panda (Franka Control Interface
#: documentation, "Robot and interface specifications": limits in the joint space)
PANDA_QDD_MAX = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)  # rad/s^2
PANDA_QDDD_MAX = (7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0)  # rad/s^3

INSTALL_HINT = "install the robots extra: pip install 'jtraj[robots]'"


# ----- parsing ---------------------------------------------------------------------------
def _floats(text, what, count=3, default=None):
    if text is None:
        if default is None:
            raise ValueError(f"{what}: expected {count} numbers, got nothing")
        return np.asarray(default, dtype=float)
    try:
        vals = np.asarray([float(x) for x in text.split()], dtype=float)
    except ValueError:
        raise ValueError(f"{what}: expected {count} numbers, got {text!r}{_xacro_note(text)}") from None
    if vals.shape != (count,) or not np.isfinite(vals).all():
        raise ValueError(f"{what}: expected {count} finite numbers, got {text!r}")
    return vals


def _attr_float(el, key, what):
    text = el.get(key)
    if text is None:
        return None
    try:
        val = float(text)
    except ValueError:
        val = math.nan
    if math.isnan(val):
        raise ValueError(f"{what}: attribute {key} must be a number, got {text!r}{_xacro_note(text)}")
    return val


def rpy_matrix(rpy) -> np.ndarray:
    """URDF's fixed-axis roll-pitch-yaw: ``R = Rz(y) Ry(p) Rx(r)``."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _origin(el, what):
    """(R, t) of an element's ``<origin>`` child (identity when absent)."""
    o = None if el is None else el.find("origin")
    if o is None:
        return np.eye(3), np.zeros(3)
    return (rpy_matrix(_floats(o.get("rpy"), f"{what} <origin rpy>", default=(0, 0, 0))),
            _floats(o.get("xyz"), f"{what} <origin xyz>", default=(0, 0, 0)))


def _read_root(source):
    if isinstance(source, os.PathLike) or (isinstance(source, str) and not source.lstrip().startswith("<")):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"source: no URDF file at {str(path)!r} (expected a path or a URDF XML string)")
        text = path.read_text()
        where = str(path)
    elif isinstance(source, str):
        text, where = source, "the URDF string"
    else:
        raise ValueError(f"source must be a path or a URDF XML string, got {type(source).__name__}")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as err:
        raise ValueError(f"source: malformed XML in {where}: {err}") from None
    if root.tag != "robot":
        raise ValueError(f"source: expected a <robot> root element in {where}, got <{root.tag}>")
    if any(isinstance(el.tag, str) and el.tag.startswith("{") and "xacro" in el.tag.partition("}")[0]
           for el in root.iter()):  # an element in a xacro namespace (www.ros.org/wiki/xacro, wiki.ros.org/xacro)
        raise ValueError(f"source: {where} holds xacro macros, not plain URDF; {_XACRO_HINT}")
    return root


_XACRO_HINT = "expand the file first: xacro arm.urdf.xacro > arm.urdf (pip install xacro, or ROS's xacro package)"


def _xacro_note(text: str) -> str:
    """The hint for a number that is a xacro expression, else ''."""
    return f" (a xacro expression: {_XACRO_HINT})" if "${" in text or "$(" in text else ""


class _Link:
    def __init__(self, el):
        self.name = el.get("name")
        what = f"<link name={self.name!r}> <inertial>"
        inertial = el.find("inertial")
        self.mass, self.com, self.inertia = 0.0, np.zeros(3), np.zeros((3, 3))
        #: why the inertia cannot be used (None: it can): raised only where the link moves
        #: with the chain, so that a bad inertia elsewhere (on the fixed base, or on a
        #: branch above the chain) does not stop an arm from loading
        self.problem = None
        if inertial is None:
            return
        m_el = inertial.find("mass")
        mass = None if m_el is None else _attr_float(m_el, "value", f"{what} <mass>")
        if mass is None or not math.isfinite(mass) or mass < 0:
            raise ValueError(f"{what}: expected <mass value> >= 0, got {None if m_el is None else m_el.get('value')!r}")
        R, t = _origin(inertial, what)
        i_el = inertial.find("inertia")
        vals = {}
        for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"):
            v = None if i_el is None else _attr_float(i_el, k, f"{what} <inertia>")
            if v is None or not math.isfinite(v):
                if mass > 0:
                    raise ValueError(f"{what}: expected <inertia> with finite ixx, ixy, ixz, iyy, iyz, izz")
                v = 0.0
            vals[k] = v
        I = np.array([[vals["ixx"], vals["ixy"], vals["ixz"]], [vals["ixy"], vals["iyy"], vals["iyz"]],
                      [vals["ixz"], vals["iyz"], vals["izz"]]])
        ev = np.linalg.eigvalsh(I)
        if ev.min() < -1e-12 * max(abs(ev).max(), 1e-300):
            self.problem = f"{what}: the inertia tensor must be positive semidefinite, its eigenvalues are {ev.tolist()}"
        self.mass, self.com, self.inertia = mass, t, R @ I @ R.T


class _Joint:
    def __init__(self, el):
        self.name = el.get("name")
        self.type = el.get("type")
        what = f"<joint name={self.name!r}>"
        if self.type in UNSUPPORTED:
            raise ValueError(f"{what}: type {self.type!r} is not supported (a floating or planar joint; expected "
                             f"one of revolute, continuous, prismatic, fixed)")
        if self.type not in MOVABLE + ("fixed",):
            raise ValueError(f"{what}: expected type revolute, continuous, prismatic or fixed, got {self.type!r}")
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None or not parent.get("link") or not child.get("link"):
            raise ValueError(f"{what}: expected <parent link=...> and <child link=...>")
        self.parent, self.child = parent.get("link"), child.get("link")
        self.R, self.t = _origin(el, what)
        axis = el.find("axis")
        a = _floats(None if axis is None else axis.get("xyz"), f"{what} <axis xyz>", default=(1, 0, 0))
        if self.type in MOVABLE and np.linalg.norm(a) < 1e-12:
            raise ValueError(f"{what}: <axis xyz> must be a non-zero vector, got {a.tolist()}")
        self.axis = a / max(np.linalg.norm(a), 1e-300)
        lim = el.find("limit")
        self.has_limit = lim is not None
        get = (lambda k: None) if lim is None else (lambda k: _attr_float(lim, k, f"{what} <limit>"))  # noqa: E731
        self.lower, self.upper, self.velocity, self.effort = (get(k) for k in ("lower", "upper", "velocity", "effort"))
        if self.type == "continuous":
            self.lower = self.upper = None
        mimic = el.find("mimic")
        self.mimic = None
        if mimic is not None:
            mult, off = (_attr_float(mimic, k, f"{what} <mimic>") for k in ("multiplier", "offset"))
            self.mimic = (mimic.get("joint"), 1.0 if mult is None else mult, 0.0 if off is None else off)

    def motion(self, q):
        """(R, t) of the joint's motion by q in its own frame."""
        if self.type in ("revolute", "continuous"):
            K = np.array([[0, -self.axis[2], self.axis[1]], [self.axis[2], 0, -self.axis[0]],
                          [-self.axis[1], self.axis[0], 0]])
            return np.eye(3) + np.sin(q) * K + (1 - np.cos(q)) * K @ K, np.zeros(3)
        if self.type == "prismatic":
            return np.eye(3), self.axis * q
        return np.eye(3), np.zeros(3)


def _lock_value(joint, joints):
    """The position at which a movable joint off the chain is locked."""
    if joint.mimic is not None and joint.mimic[0] in joints:
        ref = joints[joint.mimic[0]]
        return joint.mimic[1] * _lock_value(ref, joints) + joint.mimic[2] if ref.mimic is None else 0.0
    lo = -np.inf if joint.lower is None else joint.lower
    hi = np.inf if joint.upper is None else joint.upper
    return float(np.clip(0.0, lo, hi)) if lo <= hi else 0.0


# ----- the chain -------------------------------------------------------------------------
#: the limits a URDF file gives (``<limit lower upper velocity effort>``), which
#: :func:`from_urdf` takes from its overrides in their place
URDF_LIMITS = ("q_min", "q_max", "qd_max", "tau_max")


def from_urdf(source, *, base_link: str | None = None, tip_link: str | None = None,
              gravity=(0.0, 0.0, -9.81), limits: dict | None = None, qdd_max=DEFAULT_QDD_MAX,
              qddd_max=None, h_min: float = 0.005, h_max: float = 0.1, name: str | None = None,
              **overrides) -> SpatialSerial:
    """A spatial serial arm from a URDF file or string (see the module docstring).

    Args:
        source: path of a ``.urdf`` file, or the URDF XML text itself.
        base_link: the fixed base (default: the tree's root link).
        tip_link: the link whose frame is the tip; default: the child of the last
            movable joint when the movable joints below ``base_link`` form one branch
            (otherwise a ``ValueError`` lists the candidates).
        gravity: gravitational acceleration vector in the base frame [m/s^2].
        limits: overrides for :meth:`Limits.make` (e.g. ``{"tau_max": ...}``); they win
            over the URDF's limits and the arguments below.
        qdd_max: acceleration bound per joint (scalar or (n,)), default
            :data:`DEFAULT_QDD_MAX`; URDFs have none.
        qddd_max: jerk bound per joint (scalar or (n,)), default none.
        h_min, h_max: sampling-period bounds [s].
        name: label of the robot (default: the URDF's robot name).
        **overrides: parameters replaced after loading through
            :func:`jtraj.robots.with_params` (e.g. ``masses=...``); those of
            :data:`URDF_LIMITS` replace the file's limits, as ``limits`` does.

    Raises:
        ValueError: naming the element and what is expected, for a missing file or
            malformed XML, floating or planar joints, a closed loop, an unknown base or
            tip link, a mimic joint in the chain, a moving body without mass or with an
            inertia that is not positive definite, or missing joint limits.
    """
    root = _read_root(source)
    links = {}
    for el in root.findall("link"):
        if not el.get("name"):
            raise ValueError("<link>: expected a name attribute")
        if el.get("name") in links:
            raise ValueError(f"<link name={el.get('name')!r}>: defined twice")
        links[el.get("name")] = _Link(el)
    joints, parent_joint, children = {}, {}, {}
    for el in root.findall("joint"):
        j = _Joint(el)
        if j.name in joints:
            raise ValueError(f"<joint name={j.name!r}>: defined twice")
        for ln in (j.parent, j.child):
            if ln not in links:
                raise ValueError(f"<joint name={j.name!r}>: link {ln!r} is not defined by a <link> element")
        if j.child in parent_joint:
            raise ValueError(f"<link name={j.child!r}>: has two parent joints ({parent_joint[j.child].name!r} and "
                             f"{j.name!r}): a closed kinematic loop; expected a tree")
        joints[j.name] = j
        parent_joint[j.child] = j
        children.setdefault(j.parent, []).append(j)
    if not links:
        raise ValueError("source: expected at least one <link> element")
    roots = [ln for ln in links if ln not in parent_joint]
    if len(roots) != 1:
        raise ValueError(f"source: expected one root link (a tree), got {sorted(roots) or 'none (a closed loop)'}")
    reachable, stack = set(), [roots[0]]
    while stack:
        ln = stack.pop()
        reachable.add(ln)
        stack.extend(j.child for j in children.get(ln, ()))
    if len(reachable) != len(links):
        raise ValueError(f"source: links {sorted(set(links) - reachable)} are not connected to the root "
                         f"{roots[0]!r} (a closed kinematic loop); expected a tree")

    base = roots[0] if base_link is None else base_link
    if base not in links:
        raise ValueError(f"base_link {base!r} is not a link of the URDF; links: {sorted(links)}")
    if tip_link is None:
        tip = _default_tip(base, children)
    else:
        tip = tip_link
        if tip not in links:
            raise ValueError(f"tip_link {tip!r} is not a link of the URDF; links: {sorted(links)}")
    path, ln = [], tip
    while ln != base:
        if ln not in parent_joint:
            raise ValueError(f"tip_link {tip!r} is not in the tree below base_link {base!r}")
        path.append(parent_joint[ln])
        ln = parent_joint[ln].parent
    path.reverse()
    chain = [j for j in path if j.type in MOVABLE]
    if not chain:
        raise ValueError(f"no movable joint between base_link {base!r} and tip_link {tip!r}; expected at least one "
                         f"revolute, continuous or prismatic joint")
    for j in chain:
        if j.mimic is not None:
            raise ValueError(f"<joint name={j.name!r}>: a mimic joint in the chain from {base!r} to {tip!r} is not "
                             f"supported (expected independent joints)")
    on_chain = {j.name for j in chain}

    # every link below the base: its body (-1: the base) and its pose in that body's frame
    body_of, pose = {base: -1}, {base: (np.eye(3), np.zeros(3))}
    placements = [None] * len(chain)
    index = {j.name: k for k, j in enumerate(chain)}
    stack = [base]
    while stack:
        ln = stack.pop()
        Rp, tp = pose[ln]
        for j in children.get(ln, ()):
            Rj, tj = Rp @ j.R, Rp @ j.t + tp
            if j.name in on_chain:
                placements[index[j.name]] = (Rj, tj, body_of[ln])
                body_of[j.child], pose[j.child] = index[j.name], (np.eye(3), np.zeros(3))
            else:
                Rm, tm = j.motion(_lock_value(j, joints) if j.type in MOVABLE else 0.0)
                body_of[j.child], pose[j.child] = body_of[ln], (Rj @ Rm, Rj @ tm + tj)
            stack.append(j.child)

    n = len(chain)
    mass, first, second = np.zeros(n), np.zeros((n, 3)), [[] for _ in range(n)]
    for ln, b in body_of.items():
        L = links[ln]
        if b < 0 or L.mass == 0:
            continue
        if L.problem:
            raise ValueError(L.problem)
        R, t = pose[ln]
        c = R @ L.com + t
        mass[b] += L.mass
        first[b] += L.mass * c
        second[b].append((L.mass, c, R @ L.inertia @ R.T))
    com, inertia = np.zeros((n, 3)), np.zeros((n, 3, 3))
    for b in range(n):
        child = chain[b].child
        if mass[b] <= 0:
            raise ValueError(f"<link name={child!r}>: the body moved by joint {chain[b].name!r} has no mass (with "
                             f"the links fixed to it); expected a positive <mass>")
        com[b] = first[b] / mass[b]
        for m, c, I in second[b]:
            d = c - com[b]
            inertia[b] += I + m * (d @ d * np.eye(3) - np.outer(d, d))
        ev = np.linalg.eigvalsh(inertia[b])
        if ev.min() <= 1e-14 * max(ev.max(), 1e-300):
            raise ValueError(f"<link name={child!r}>: the inertia of the body moved by joint {chain[b].name!r} (with "
                             f"the links fixed to it) must be positive definite, its eigenvalues are {ev.tolist()}")
    for k, (_, _, parent) in enumerate(placements):
        if parent != k - 1:  # cannot happen for a path, kept as an internal check
            raise ValueError(f"<joint name={chain[k].name!r}>: not a serial chain")
    tip_R, tip_t = pose[tip]

    limits = {k: overrides.pop(k) for k in URDF_LIMITS if k in overrides} | dict(limits or {})
    lim = _limits(chain, n, limits, qdd_max, qddd_max, h_min, h_max)
    robot = spatial_serial(
        np.stack([p[0] for p in placements]), np.stack([p[1] for p in placements]),
        np.stack([j.axis for j in chain]),
        tuple("prismatic" if j.type == "prismatic" else "revolute" for j in chain),
        mass, com, inertia, tip_rotation=tip_R, tip_translation=tip_t, gravity=gravity,
        joint_names=[j.name for j in chain], limits=lim,
        name=name if name is not None else (root.get("name") or "urdf"))
    if overrides:
        robot = with_params(robot, **overrides)
    return robot


def _default_tip(base, children):
    """The child of the last movable joint below ``base``, when the movable joints form
    one branch."""
    def movable_below(ln):
        return any(j.type in MOVABLE or movable_below(j.child) for j in children.get(ln, ()))

    leaves, stack = [], [base]
    while stack:
        ln = stack.pop()
        for j in children.get(ln, ()):
            if j.type in MOVABLE and not movable_below(j.child):
                leaves.append(j.child)
            stack.append(j.child)
    if len(leaves) != 1:
        raise ValueError(f"tip_link: the movable joints below base_link {base!r} end in "
                         f"{sorted(leaves) or 'no link'}; expected exactly one, give tip_link= explicitly")
    return leaves[0]


def _limits(chain, n, limits, qdd_max, qddd_max, h_min, h_max):
    over = dict(limits or {})
    lo = np.array([-np.inf if j.lower is None else j.lower for j in chain])
    hi = np.array([np.inf if j.upper is None else j.upper for j in chain])
    vel = [j.velocity for j in chain]
    eff = [j.effort for j in chain]
    box = {"q_min", "q_max"} <= set(over)
    problems, needed = [], set()  # every missing or unusable limit, reported together
    for j in chain:
        checks = [
            (j.type != "continuous" and (j.lower is None or j.upper is None) and not box,
             "expected <limit lower=... upper=...>", ("q_min", "q_max")),
            (j.lower is not None and j.upper is not None and not j.lower < j.upper and not box,
             f"<limit> must have lower < upper, got {j.lower} and {j.upper}", ("q_min", "q_max")),
            (j.velocity is None and "qd_max" not in over, "expected <limit velocity=...>", ("qd_max",)),
            (j.velocity is not None and not j.velocity > 0 and "qd_max" not in over,
             f"<limit velocity> must be > 0, got {j.velocity}", ("qd_max",)),
            (j.effort is None and "tau_max" not in over, "expected <limit effort=...>", ("tau_max",)),
            (j.effort is not None and not j.effort > 0 and "tau_max" not in over,
             f"<limit effort> must be > 0, got {j.effort}", ("tau_max",)),
        ]
        texts = [text for bad, text, names in checks if bad]
        needed.update(name for bad, _, names in checks if bad for name in names)
        if texts:
            problems.append(f"<joint name={j.name!r}> ({j.type}): {', '.join(texts)}")
    if problems:
        given = ", ".join(f"{k}=..." for k in URDF_LIMITS if k in needed)
        raise ValueError(f"{'; '.join(problems)} (or limits=dict({given}))")
    kw = dict(q_min=lo, q_max=hi, qd_max=None if None in vel else np.array(vel),
              tau_max=None if None in eff else np.array(eff), qdd_max=qdd_max, qddd_max=qddd_max,
              h_min=h_min, h_max=h_max)
    kw.update(over)
    if np.isinf(np.asarray(kw["q_min"], float)).all() and np.isinf(np.asarray(kw["q_max"], float)).all():
        kw["q_min"] = kw["q_max"] = None
    return Limits.make(n, **kw)


# ----- the built-in arms of example-robot-data ------------------------------------------
def robot_data_dir() -> Path:
    """The ``robots`` folder of the ``example-robot-data`` package (a cmeel wheel with no
    Python module: its files lie under ``<site-packages>/cmeel.prefix/share``). The
    environment variable ``JTRAJ_ROBOT_DATA`` names another folder."""
    env = os.environ.get("JTRAJ_ROBOT_DATA")
    if env:
        p = Path(env)
        if not p.is_dir():
            raise ValueError(f"JTRAJ_ROBOT_DATA={env!r} is not a folder")
        return p
    prefixes = [sysconfig.get_paths().get("purelib"), sysconfig.get_paths().get("platlib")]
    try:
        prefixes += site.getsitepackages()
    except AttributeError:  # some virtualenvs
        pass
    prefixes += [site.getusersitepackages() if hasattr(site, "getusersitepackages") else None]
    prefixes += [p for p in sys.path if p.endswith("-packages")]
    candidates = [Path(p) / "cmeel.prefix" for p in prefixes if p] + [Path(sys.prefix)]
    for c in candidates:
        d = c / "share" / "example-robot-data" / "robots"
        if d.is_dir():
            return d
    raise ImportError(f"the URDF files of the built-in arms come from the example-robot-data package: "
                      f"{INSTALL_HINT}")


def _data_file(*parts) -> Path:
    path = robot_data_dir().joinpath(*parts)
    if not path.is_file():
        raise ImportError(f"{path} is missing from the example-robot-data installation: {INSTALL_HINT}")
    return path


def panda(**overrides) -> SpatialSerial:
    """The Franka Emika Panda (7 DOF), from example-robot-data's panda.urdf.

    Tip: the flange frame ``panda_link8`` (0.107 m beyond joint 7's frame). The hand
    (0.73 kg) is mounted and its fingers locked closed: their masses ride on body 7.
    Joint box, velocity and torque limits from the URDF (the published ones);
    acceleration and jerk bounds are Franka's published joint-space limits,
    qdd_max = (15, 7.5, 10, 12.5, 15, 20, 20) rad/s^2 and
    qddd_max = (7500, 3750, 5000, 6250, 7500, 10000, 10000) rad/s^3.
    """
    return from_urdf(_data_file("panda_description", "urdf", "panda.urdf"), tip_link="panda_link8",
                     qdd_max=PANDA_QDD_MAX, qddd_max=PANDA_QDDD_MAX, name="panda", **overrides)


def ur5(**overrides) -> SpatialSerial:
    """The Universal Robots UR5 (6 DOF), from example-robot-data's ur5_robot.urdf.

    Tip: ``tool0``, the tool flange (UR's TCP with no tool). Joint box (+-2 pi, elbow
    +-pi), velocity and torque limits from the URDF; UR publishes no joint acceleration
    limit: qdd_max = :data:`DEFAULT_QDD_MAX` on every joint (an assumption), no jerk bound.
    """
    return from_urdf(_data_file("ur_description", "urdf", "ur5_robot.urdf"), tip_link="tool0",
                     name="ur5", **overrides)


def ur10(**overrides) -> SpatialSerial:
    """The Universal Robots UR10 (6 DOF), from example-robot-data's ur10_robot.urdf.

    Tip ``tool0``, limits as :func:`ur5`."""
    return from_urdf(_data_file("ur_description", "urdf", "ur10_robot.urdf"), tip_link="tool0",
                     name="ur10", **overrides)


def kinova(**overrides) -> SpatialSerial:
    """The Kinova Jaco2 j2s6s200 (6 DOF), from example-robot-data's kinova.urdf.

    Tip ``j2s6s200_end_effector``. Joints 1, 4 and 6 are continuous (no joint box); the
    URDF's (fixed) fingers ride on body 6. qdd_max = :data:`DEFAULT_QDD_MAX`."""
    return from_urdf(_data_file("kinova_description", "robots", "kinova.urdf"),
                     tip_link="j2s6s200_end_effector", name="kinova", **overrides)


def so100(**overrides) -> SpatialSerial:
    """The SO-100 arm (5 DOF), from example-robot-data's so100.urdf.

    Tip ``gripper`` (the wrist-roll body), the jaw locked at 0. qdd_max = :data:`DEFAULT_QDD_MAX`."""
    return from_urdf(_data_file("so_arm_description", "urdf", "so100.urdf"), tip_link="gripper",
                     name="so100", **overrides)
