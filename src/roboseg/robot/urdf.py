"""URDF parsing (hostile-file safe) into plain data, and extraction of the serial chain.

Only what the robot model needs is kept: link geometry (visual and collision), joints with their
``<origin>`` (``T_parent_joint``), axis and limits. Every malformed input raises one
:class:`~roboseg.errors.RobotModelError` line naming the file and the element or value at fault.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import defusedxml
import defusedxml.ElementTree as DET
import numpy as np

from roboseg.errors import RobotModelError

from .transforms import origin_matrix

log = logging.getLogger(__name__)

MOVABLE_TYPES = ("revolute", "continuous", "prismatic")
JOINT_TYPES = (*MOVABLE_TYPES, "fixed")


@dataclass(frozen=True)
class Geometry:
    """One ``<visual>`` or ``<collision>`` shape of a link.

    ``kind`` is ``box`` (``params`` = x, y, z extents), ``cylinder`` (radius, length along z),
    ``sphere`` (radius) or ``mesh`` (``params`` = x, y, z scale, ``filename`` as written).
    ``T_link_geom`` [4, 4] maps geometry coordinates into the link frame (metres).
    """

    kind: str
    params: tuple[float, ...]
    T_link_geom: np.ndarray
    filename: str | None = None


@dataclass(frozen=True)
class Link:
    name: str
    visuals: tuple[Geometry, ...]
    collisions: tuple[Geometry, ...]

    @property
    def has_geometry(self) -> bool:
        return bool(self.visuals or self.collisions)

    def geometry(self, which: str) -> tuple[Geometry, ...]:
        """Shapes of kind ``which`` ('visual'/'collision'), falling back to the other kind."""
        if which == "visual":
            return self.visuals or self.collisions
        return self.collisions or self.visuals


@dataclass(frozen=True)
class Joint:
    """A URDF joint; ``T_parent_joint`` is its ``<origin>``, ``axis`` a unit vector."""

    name: str
    type: str
    parent: str
    child: str
    T_parent_joint: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float

    @property
    def movable(self) -> bool:
        return self.type in MOVABLE_TYPES


@dataclass(frozen=True)
class Urdf:
    name: str
    path: Path
    links: dict[str, Link]
    joints: tuple[Joint, ...]


@dataclass(frozen=True)
class Frame:
    """A link of the chain; ``parent`` indexes the chain's frames (-1 for the root)."""

    name: str
    parent: int
    joint: Joint | None


def _floats(text: str | None, n: int, where: str, default: tuple[float, ...]) -> np.ndarray:
    """Parse ``n`` whitespace-separated finite floats (``default`` when ``text`` is None)."""
    if text is None:
        return np.asarray(default, dtype=np.float64)
    try:
        values = [float(t) for t in text.split()]
    except ValueError:
        values = []
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise RobotModelError(f"{where}: expected {n} finite numbers, got {text!r}")
    return np.asarray(values, dtype=np.float64)


def _origin(elem: ET.Element, where: str) -> np.ndarray:
    """``T`` [4, 4] of the ``<origin xyz rpy>`` child of ``elem`` (identity when absent)."""
    o = elem.find("origin")
    if o is None:
        return np.eye(4)
    xyz = _floats(o.get("xyz"), 3, f"{where} <origin xyz>", (0.0, 0.0, 0.0))
    rpy = _floats(o.get("rpy"), 3, f"{where} <origin rpy>", (0.0, 0.0, 0.0))
    return origin_matrix(xyz, rpy)


def _geometry(elem: ET.Element, where: str) -> Geometry:
    g = elem.find("geometry")
    shape = None if g is None else next(iter(g), None)
    if shape is None:
        raise RobotModelError(f"{where}: <geometry> is missing or empty")
    T = _origin(elem, where)
    kind = shape.tag
    if kind == "box":
        params = _floats(shape.get("size"), 3, f"{where} <box size>", ())
    elif kind == "cylinder":
        params = np.array(
            [
                _floats(shape.get("radius"), 1, f"{where} <cylinder radius>", ())[0],
                _floats(shape.get("length"), 1, f"{where} <cylinder length>", ())[0],
            ]
        )
    elif kind == "sphere":
        params = _floats(shape.get("radius"), 1, f"{where} <sphere radius>", ())
    elif kind == "mesh":
        filename = shape.get("filename")
        if not filename:
            raise RobotModelError(f"{where}: <mesh> has no filename")
        scale_text = shape.get("scale")
        if scale_text is not None and len(scale_text.split()) == 1:
            scale_text = " ".join([scale_text] * 3)  # a single uniform factor is common
        scale = _floats(scale_text, 3, f"{where} <mesh scale>", (1.0, 1.0, 1.0))
        return Geometry("mesh", tuple(float(s) for s in scale), T, filename)
    else:
        raise RobotModelError(f"{where}: unsupported geometry <{kind}>")
    if np.any(params <= 0):
        raise RobotModelError(f"{where}: <{kind}> dimensions must be positive, got {params}")
    return Geometry(kind, tuple(float(p) for p in params), T)


def _link(elem: ET.Element, file: str) -> Link:
    name = elem.get("name")
    if not name:
        raise RobotModelError(f"{file}: a <link> has no name")
    shapes = {}
    for tag in ("visual", "collision"):
        shapes[tag] = tuple(
            _geometry(e, f"{file}: link {name!r} <{tag}>") for e in elem.findall(tag)
        )
    return Link(name, shapes["visual"], shapes["collision"])


def _joint(elem: ET.Element, file: str) -> Joint:
    name = elem.get("name")
    if not name:
        raise RobotModelError(f"{file}: a <joint> has no name")
    where = f"{file}: joint {name!r}"
    jtype = elem.get("type")
    if jtype not in JOINT_TYPES:
        raise RobotModelError(
            f"{where}: unsupported type {jtype!r} (supported: {', '.join(JOINT_TYPES)})"
        )
    parent, child = elem.find("parent"), elem.find("child")
    if parent is None or child is None or not parent.get("link") or not child.get("link"):
        raise RobotModelError(f"{where}: needs <parent link=...> and <child link=...>")
    axis = _floats(
        None if elem.find("axis") is None else elem.find("axis").get("xyz"),
        3,
        f"{where} <axis xyz>",
        (1.0, 0.0, 0.0),
    )
    norm = float(np.linalg.norm(axis))
    if jtype != "fixed" and norm < 1e-9:
        raise RobotModelError(f"{where}: <axis xyz> must not be zero")
    axis = axis / norm if norm > 0 else axis
    lower, upper = -math.pi, math.pi
    limit = elem.find("limit")
    if jtype in ("revolute", "prismatic"):
        if limit is None or limit.get("lower") is None or limit.get("upper") is None:
            if jtype == "prismatic":
                raise RobotModelError(f"{where}: prismatic joint needs <limit lower upper>")
            log.warning("%s: no <limit lower upper>, using [-pi, pi]", where)
        else:
            lower = float(_floats(limit.get("lower"), 1, f"{where} <limit lower>", ())[0])
            upper = float(_floats(limit.get("upper"), 1, f"{where} <limit upper>", ())[0])
            if lower > upper:
                raise RobotModelError(f"{where}: <limit> lower {lower} > upper {upper}")
    return Joint(
        name=name,
        type=jtype,
        parent=parent.get("link"),
        child=child.get("link"),
        T_parent_joint=_origin(elem, where),
        axis=axis,
        lower=lower,
        upper=upper,
    )


def parse_urdf(path: str | Path) -> Urdf:
    """Read a URDF file with defusedxml (entity expansion and external references refused)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise RobotModelError(f"URDF file not found: {path}")
    try:
        root = DET.parse(str(path)).getroot()
    except (ET.ParseError, defusedxml.DefusedXmlException) as e:
        raise RobotModelError(f"{path}: malformed or unsafe XML ({e})") from None
    if root.tag != "robot":
        raise RobotModelError(f"{path}: root element is <{root.tag}>, expected <robot>")
    file = str(path)
    links: dict[str, Link] = {}
    for elem in root.findall("link"):
        link = _link(elem, file)
        if link.name in links:
            raise RobotModelError(f"{file}: link {link.name!r} is defined twice")
        links[link.name] = link
    joints = tuple(_joint(e, file) for e in root.findall("joint"))
    seen: set[str] = set()
    for j in joints:
        if j.name in seen:
            raise RobotModelError(f"{file}: joint {j.name!r} is defined twice")
        seen.add(j.name)
        for end in (j.parent, j.child):
            if end not in links:
                raise RobotModelError(f"{file}: joint {j.name!r} refers to unknown link {end!r}")
    if not links:
        raise RobotModelError(f"{file}: no <link> elements")
    return Urdf(root.get("name") or path.stem, path, links, joints)


def serial_chain(urdf: Urdf) -> list[Frame]:
    """Frames of the serial chain from the root link, parents before children.

    The chain follows, from the root, the one child branch that carries geometry or movable
    joints; branches without either (e.g. tool-centre frames such as ``link_ee``) are kept as
    extra frames after the chain. Two branches with geometry or movable joints make the robot a
    tree, which is refused, as are several roots and cycles.
    """
    file = str(urdf.path)
    children: dict[str, list[Joint]] = {name: [] for name in urdf.links}
    parent_joint: dict[str, Joint] = {}
    for j in urdf.joints:
        if j.child in parent_joint:
            raise RobotModelError(
                f"{file}: link {j.child!r} is the child of two joints "
                f"({parent_joint[j.child].name!r}, {j.name!r})"
            )
        parent_joint[j.child] = j
        children[j.parent].append(j)
    roots = [name for name in urdf.links if name not in parent_joint]
    if len(roots) != 1:
        raise RobotModelError(f"{file}: expected one root link, found {roots or 'none (a cycle)'}")

    matters: dict[str, bool] = {}

    def subtree_matters(link: str, depth: int = 0) -> bool:
        if link not in matters:
            if depth > len(urdf.links):
                raise RobotModelError(f"{file}: the joints form a cycle through link {link!r}")
            matters[link] = urdf.links[link].has_geometry or any(
                j.movable or subtree_matters(j.child, depth + 1) for j in children[link]
            )
        return matters[link]

    frames = [Frame(roots[0], -1, None)]
    while True:
        here = frames[-1].name
        branches = [j for j in children[here] if subtree_matters(j.child)]
        if len(branches) > 1:
            raise RobotModelError(
                f"{file}: link {here!r} branches into "
                f"{[j.child for j in branches]}, both with geometry or movable joints "
                "(only serial chains are supported)"
            )
        if not branches:
            break
        frames.append(Frame(branches[0].child, len(frames) - 1, branches[0]))

    # geometry-free, fixed side branches (tool frames etc.), depth first
    stack = [(i, j) for i, f in enumerate(frames) for j in reversed(children[f.name])]
    chain = {f.name for f in frames}
    stack = [(i, j) for i, j in stack if j.child not in chain]
    while stack:
        i, j = stack.pop()
        frames.append(Frame(j.child, i, j))
        stack.extend((len(frames) - 1, c) for c in reversed(children[j.child]))
    if len(frames) != len(urdf.links):
        missing = sorted(set(urdf.links) - {f.name for f in frames})
        raise RobotModelError(f"{file}: links {missing} are not connected to the root")
    if not any(f.joint is not None and f.joint.movable for f in frames):
        raise RobotModelError(f"{file}: no movable joints (revolute, continuous or prismatic)")
    return frames
