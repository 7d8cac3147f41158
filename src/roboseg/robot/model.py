"""The robot model: serial kinematic chain + link meshes, batched forward kinematics in torch.

Frames follow the URDF: ``T_base_<frame>`` maps points of a link frame into the root (base) link
frame, metres. Joint vectors ``q`` list the movable joints in chain order from the root
(radians for revolute/continuous, metres for prismatic).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from roboseg.errors import RobotModelError

from .default import default_urdf_path
from .meshes import MeshData, decimate, geometry_mesh
from .transforms import motion_basis, motion_coefficients
from .urdf import Frame, Urdf, parse_urdf, serial_chain

log = logging.getLogger(__name__)

GEOMETRY_KINDS = ("visual", "collision")


@dataclass(frozen=True)
class LinkShape:
    """One undecimated shape of a link: ``p_link = T_link_geom @ (scale * p_mesh)``."""

    link: int  # index into RobotModel.link_names
    mesh: MeshData
    scale: np.ndarray  # [3]
    T_link_geom: np.ndarray  # [4, 4]


def _assemble(
    shapes: Sequence[LinkShape], reduction: float, cache_dir: Path | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate shapes into (vertices [V, 3] in their link frames, faces [F, 3], link [V])."""
    vertices, faces, links, offset = [], [], [], 0
    for shape in shapes:
        mesh = decimate(shape.mesh, reduction, cache_dir)
        v = (mesh.vertices * shape.scale) @ shape.T_link_geom[:3, :3].T + shape.T_link_geom[:3, 3]
        f = mesh.faces if np.prod(shape.scale) > 0 else mesh.faces[:, ::-1]  # keep outward normals
        vertices.append(v)
        faces.append(f + offset)
        links.append(np.full(len(v), shape.link, dtype=np.int64))
        offset += len(v)
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(vertices), np.concatenate(faces), np.concatenate(links)


class RobotModel:
    """Serial-chain robot: joint limits, link meshes and batched, differentiable FK.

    Attributes: ``name``, ``root_link`` (base frame), ``joint_names`` / ``dof`` (movable joints
    in chain order), ``lower`` / ``upper`` [D] limits, ``frame_names`` (all links, root first),
    ``link_names`` (links with geometry), ``vertices`` [V, 3] (each in its link frame, metres),
    ``faces`` [F, 3], ``vertex_link`` [V] (index into ``link_names``), ``reduction``.
    """

    def __init__(
        self,
        urdf: Urdf,
        frames: list[Frame],
        shapes: list[LinkShape],
        link_frames: list[int],
        reduction: float = 0.0,
        cache_dir: Path | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.name = urdf.name
        self.urdf_path = urdf.path
        self.root_link = frames[0].name
        self.frame_names = [f.name for f in frames]
        self.link_names = [frames[i].name for i in link_frames]
        movable = [f.joint for f in frames if f.joint is not None and f.joint.movable]
        self.joint_names = [j.name for j in movable]
        self.dof = len(movable)
        self.reduction = reduction
        self._urdf, self._frames, self._shapes = urdf, frames, shapes
        self._cache_dir = cache_dir
        self._parents = [f.parent for f in frames]

        n = len(frames)
        origin = np.tile(np.eye(4), (n, 1, 1))
        A, A2 = np.zeros((n, 4, 4)), np.zeros((n, 4, 4))
        frame_dof = np.full(n, self.dof, dtype=np.int64)  # column dof holds a zero
        revolute, prismatic = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        for i, f in enumerate(frames):
            if f.joint is None:
                continue
            origin[i] = f.joint.T_parent_joint
            if f.joint.movable:
                A[i], A2[i] = motion_basis(f.joint.type, f.joint.axis)
                frame_dof[i] = self.joint_names.index(f.joint.name)
                revolute[i] = f.joint.type in ("revolute", "continuous")
                prismatic[i] = f.joint.type == "prismatic"
        vertices, faces, vertex_link = _assemble(shapes, reduction, cache_dir)

        self._np = {
            "lower": np.array([j.lower for j in movable]),
            "upper": np.array([j.upper for j in movable]),
            "vertices": vertices,
            "_origin": origin,
            "_A": A,
            "_A2": A2,
        }
        self._index = {
            "faces": faces,
            "vertex_link": vertex_link,
            "_frame_dof": frame_dof,
            "_link_frames": np.asarray(link_frames, dtype=np.int64),
        }
        self._masks = {"_revolute": revolute, "_prismatic": prismatic}
        # vertices are stored link by link: block l is vertices[start:end] of link_names[l]
        ends = np.cumsum(np.bincount(vertex_link, minlength=len(link_frames)))
        self._blocks = list(zip([0, *ends[:-1].tolist()], ends.tolist(), strict=True))
        self._place(torch.device(device), dtype)

    # tensors ---------------------------------------------------------------------------------
    lower: torch.Tensor
    upper: torch.Tensor
    vertices: torch.Tensor
    faces: torch.Tensor
    vertex_link: torch.Tensor

    def _place(self, device: torch.device, dtype: torch.dtype) -> None:
        """(Re)create every tensor attribute on ``device``; floats in ``dtype``."""
        self.device, self.dtype = device, dtype
        for k, v in self._np.items():
            setattr(self, k, torch.as_tensor(v, dtype=dtype, device=device))
        for k, v in self._index.items():
            setattr(self, k, torch.as_tensor(v, dtype=torch.long, device=device))
        for k, v in self._masks.items():
            setattr(self, k, torch.as_tensor(v, dtype=torch.bool, device=device))
        self._eye = torch.eye(4, dtype=dtype, device=device)
        ones = torch.ones(len(self.vertices), 1, dtype=dtype, device=device)
        self._vertices_h = torch.cat([self.vertices, ones], dim=1)  # [V, 4] homogeneous

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> RobotModel:
        """A copy with tensors on ``device`` / in float ``dtype`` (unchanged when None)."""
        other = copy.copy(self)
        device = torch.device(device) if device is not None else self.device
        other._place(device, dtype or self.dtype)
        return other

    def decimated(self, reduction: float) -> RobotModel:
        """Same kinematics with every shape's faces reduced by ``reduction`` (disk-cached)."""
        return RobotModel(
            self._urdf,
            self._frames,
            self._shapes,
            self._index["_link_frames"].tolist(),
            reduction,
            self._cache_dir,
            self.device,
            self.dtype,
        )

    def with_links(self, names: Sequence[str]) -> RobotModel:
        """Same kinematics with the geometry of the links ``names`` only (e.g. the links that
        moved during a recording). ``link_names`` and ``vertex_link`` indices are unchanged; the
        other links simply carry no vertices. Raises :class:`RobotModelError` for an unknown or
        an empty selection."""
        unknown = sorted(set(names) - set(self.link_names))
        if unknown or not names:
            what = f"links {unknown} are not" if unknown else "no link is"
            raise RobotModelError(
                f"robot {self.name!r}: {what} among the links with geometry {self.link_names}"
            )
        keep = {self.link_names.index(n) for n in names}
        return RobotModel(
            self._urdf,
            self._frames,
            [s for s in self._shapes if s.link in keep],
            self._index["_link_frames"].tolist(),
            self.reduction,
            self._cache_dir,
            self.device,
            self.dtype,
        )

    # joints ----------------------------------------------------------------------------------
    def check_joints(self, q: torch.Tensor | Sequence[float] | np.ndarray) -> torch.Tensor:
        """Joint values as a [B, D] tensor of the model's device/dtype ([D] becomes [1, D])."""
        q = torch.as_tensor(q).to(device=self.device, dtype=self.dtype)
        if q.dim() == 1:
            q = q.unsqueeze(0)
        if q.dim() != 2 or q.shape[1] != self.dof:
            raise RobotModelError(
                f"robot {self.name!r}: expected {self.dof} joint values "
                f"({', '.join(self.joint_names)}), got shape {tuple(q.shape)}"
            )
        if not bool(torch.isfinite(q).all()):
            columns = torch.nonzero(~torch.isfinite(q))[:, 1].tolist()
            bad = sorted({self.joint_names[c] for c in columns})
            raise RobotModelError(f"robot {self.name!r}: non-finite values for joints {bad}")
        return q

    def joints_from_names(
        self, names: Sequence[str], values: torch.Tensor | Sequence[float] | np.ndarray
    ) -> torch.Tensor:
        """Reorder ``values`` [N] or [B, N], given in the order of ``names``, to the model's
        joint order ([D] or [B, D]). The names must be exactly the model's joints."""
        names = list(names)
        if sorted(names) != sorted(self.joint_names) or len(set(names)) != len(names):
            unknown = sorted(set(names) - set(self.joint_names))
            missing = sorted(set(self.joint_names) - set(names))
            dupes = sorted({n for n in names if names.count(n) > 1})
            raise RobotModelError(
                f"robot {self.name!r}: joint names {names} do not match the model's "
                f"{self.joint_names} (unknown {unknown}, missing {missing}, repeated {dupes})"
            )
        values = torch.as_tensor(values).to(device=self.device, dtype=self.dtype)
        if values.dim() not in (1, 2) or values.shape[-1] != len(names):
            raise RobotModelError(
                f"robot {self.name!r}: {len(names)} joint names but values of shape "
                f"{tuple(values.shape)}"
            )
        order = torch.tensor([names.index(n) for n in self.joint_names], device=self.device)
        return values[..., order]

    def random_joints(
        self, n: int, generator: torch.Generator | None = None, margin: float = 0.1
    ) -> torch.Tensor:
        """[n, D] joint vectors uniform in the limits shrunk by ``margin`` × range per side."""
        if not 0.0 <= margin < 0.5:
            raise RobotModelError(f"joint limit margin must be in [0, 0.5), got {margin}")
        device = generator.device if generator is not None else self.device
        u = torch.rand(n, self.dof, generator=generator, device=device, dtype=torch.float64)
        lower = torch.as_tensor(self._np["lower"], device=device)
        span = torch.as_tensor(self._np["upper"], device=device) - lower
        q = lower + span * (margin + (1.0 - 2.0 * margin) * u)
        return q.to(device=self.device, dtype=self.dtype)

    # kinematics ------------------------------------------------------------------------------
    def frame_transforms(self, q: torch.Tensor) -> torch.Tensor:
        """``T_base_frame`` [B, len(frame_names), 4, 4] for joint values ``q`` [B, D] or [D]."""
        q = self.check_joints(q)
        q_frames = torch.cat([q, q.new_zeros(q.shape[0], 1)], dim=1)[:, self._frame_dof]
        f1, f2 = motion_coefficients(q_frames, self._revolute, self._prismatic)
        motion = self._eye + f1[..., None, None] * self._A + f2[..., None, None] * self._A2
        local = self._origin @ motion  # T_parent_frame, [B, F, 4, 4]
        world = [local[:, 0]]
        for i in range(1, len(self._parents)):
            world.append(world[self._parents[i]] @ local[:, i])
        return torch.stack(world, dim=1)

    def link_transforms(self, q: torch.Tensor) -> torch.Tensor:
        """``T_base_link`` [B, len(link_names), 4, 4] of the links that carry geometry."""
        return self.frame_transforms(q)[:, self._link_frames]

    def posed_vertices(self, q: torch.Tensor) -> torch.Tensor:
        """All mesh vertices [B, V, 3] in the base (root link) frame, metres."""
        T = self.link_transforms(q)[:, :, :3].transpose(2, 3)  # [B, L, 4, 3], (T[:3])^T
        if not self._blocks:
            return T.new_zeros(T.shape[0], 0, 3)
        # one small matmul per link block; much faster on CPU than gathering T per vertex
        return torch.cat(
            [self._vertices_h[s:e] @ T[:, link] for link, (s, e) in enumerate(self._blocks)],
            dim=1,
        )

    def mesh(self, q1: torch.Tensor) -> trimesh.Trimesh:
        """The posed mesh (base frame) for a single configuration ``q1`` [D] or [1, D]."""
        q1 = self.check_joints(q1)
        if q1.shape[0] != 1:
            raise RobotModelError(f"robot {self.name!r}: mesh() takes one configuration")
        vertices = self.posed_vertices(q1)[0].detach().cpu().double().numpy()
        return trimesh.Trimesh(vertices, self.faces.cpu().numpy(), process=False)

    def __repr__(self) -> str:
        return (
            f"RobotModel({self.name!r}, dof={self.dof}, links={len(self.link_names)}, "
            f"vertices={len(self.vertices)}, faces={len(self.faces)}, reduction={self.reduction})"
        )


def load_robot(
    urdf: str | Path | None = None,
    geometry: str = "visual",
    reduction: float = 0.0,
    cache_dir: Path | None = None,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> RobotModel:
    """Load a serial-chain URDF (``None``: the built-in default arm, see :mod:`.default`).

    ``geometry`` picks ``visual`` or ``collision`` shapes (a link having only the other kind uses
    those); ``reduction`` decimates every shape by that fraction of faces (cached on disk in
    ``cache_dir``, default ``$ROBOSEG_CACHE`` or ``~/.cache/roboseg``).
    """
    if geometry not in GEOMETRY_KINDS:
        raise RobotModelError(f"geometry must be one of {GEOMETRY_KINDS}, got {geometry!r}")
    parsed = parse_urdf(default_urdf_path() if urdf is None else urdf)
    frames = serial_chain(parsed)
    shapes: list[LinkShape] = []
    link_frames: list[int] = []
    for i, frame in enumerate(frames):
        link = parsed.links[frame.name]
        if not link.has_geometry:
            continue
        for g in link.geometry(geometry):
            mesh, scale = geometry_mesh(g, parsed.path, link.name)
            shapes.append(LinkShape(len(link_frames), mesh, scale, g.T_link_geom))
        link_frames.append(i)
    model = RobotModel(parsed, frames, shapes, link_frames, reduction, cache_dir, device, dtype)
    log.info("loaded %r", model)
    return model
