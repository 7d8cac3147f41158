"""Motion segmentation: the robot moving in front of static cameras, by background subtraction.

Per camera, a background model is fitted on frames of the recording spread over joint space (a
per-pixel median with per-frame exposure compensation, or OpenCV's MOG2 subtractor): a person
walking through the view shows in few of the frames and does not enter it. A frame's
foreground (colour distance to the background above a noise-adaptive threshold) is cleaned by
morphological opening and closing; of its connected components, those touching the robot's
*anchor* are the robot: the pixels near the foreground in most of the model's frames, where the
first moving link joins the static part (a robot's moving links always pass there, a person
walking through the view does not), plus components within a small gap of them (the robot cut
by a cable in front of it). A person touching the robot in the image merges with it; the
registration then refits on the mask pixels near its first estimate
(``RegisterConfig.trim_masks``). People or cables that keep moving near the robot all through
the recording are not told apart from it, and the robot's pixels that it covers in most frames
are background (measured on the simulator's undraped phases, 640×360, whose staff sway and
cables swing all the time: IoU 0.25–0.55 against the moving links' silhouettes).

What never moves is background too: the base and any link whose joints stood still. Which
links' image footprint changes follows from the joint states alone (:func:`link_motion`): a
link moved when its surface, posed by forward kinematics in two configurations, lies farther
apart than ``link_motion`` metres (a symmetric nearest-neighbour distance, so a link spinning
about its own axis of symmetry does not count). Registration renders and compares only those
links (``register(..., links=...)``).

Images are processed at ``work_width`` pixels wide (aspect kept); masks are returned at the
image's own size.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

from roboseg.errors import SegmentationError
from roboseg.robot import RobotModel

__all__ = [
    "MotionConfig",
    "BackgroundModel",
    "clean_mask",
    "keep_robot_components",
    "link_surface_points",
    "link_motion",
]

log = logging.getLogger(__name__)

Background = Literal["median", "mog2"]


@dataclass(frozen=True)
class MotionConfig:
    """Motion segmentation settings (``motion:`` in ``conf/register.yaml``).

    ``background``: ``median`` | ``mog2`` (OpenCV's Gaussian-mixture subtractor);
    ``background_frames``: frames fitted (spread over joint space); ``work_width`` px;
    ``threshold``: least RGB distance (0–255 units) of a foreground pixel, raised to
    ``noise_factor`` × the frame's robust noise level (median only); ``open_px`` /
    ``close_px``: morphological radii (px at ``work_width``); ``min_area``: least component
    area, fraction of the image; ``fill_holes``: holes smaller than this fraction of the image
    are filled; the anchor: pixels within ``anchor_radius`` × width (doubled, up to twice,
    while none qualifies) of the foreground in at least ``anchor_fraction`` of the fitted
    frames; components within ``join_gap`` × width of the robot's are kept (see
    :func:`keep_robot_components`); ``link_motion`` (m): least surface displacement of a link
    that counts as moved.
    """

    background: Background = "median"
    background_frames: int = 60
    work_width: int = 480
    threshold: float = 30.0
    noise_factor: float = 4.0
    open_px: int = 1
    close_px: int = 3
    min_area: float = 0.0005
    fill_holes: float = 0.001
    anchor_radius: float = 0.04
    anchor_fraction: float = 0.8
    join_gap: float = 0.02
    link_motion: float = 0.03

    def __post_init__(self) -> None:
        if self.background not in ("median", "mog2"):
            raise SegmentationError(
                f"motion.background must be median or mog2, got {self.background!r}"
            )
        if self.background_frames < 3:
            raise SegmentationError(
                f"motion.background_frames must be >= 3, got {self.background_frames}"
            )
        if self.work_width < 16:
            raise SegmentationError(f"motion.work_width must be >= 16 px, got {self.work_width}")
        if self.open_px < 0 or self.close_px < 0:
            raise SegmentationError("motion.open_px and motion.close_px must be >= 0")
        if not (0.0 < self.anchor_fraction <= 1.0 and self.anchor_radius >= 0.0):
            raise SegmentationError(
                "motion.anchor_fraction must be in (0, 1] and motion.anchor_radius >= 0"
            )
        if self.join_gap < 0:
            raise SegmentationError(f"motion.join_gap must be >= 0, got {self.join_gap}")
        if self.link_motion <= 0:
            raise SegmentationError(f"motion.link_motion must be > 0 m, got {self.link_motion}")


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def clean_mask(fg: np.ndarray, cfg: MotionConfig) -> np.ndarray:
    """Opening, closing, small holes filled and small components removed: ``[h, w]`` bool."""
    m = fg.astype(np.uint8)
    if cfg.open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disc(cfg.open_px))
    if cfg.close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disc(cfg.close_px))
    area = m.size
    if cfg.fill_holes > 0:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(1 - m, connectivity=4)
        h, w = m.shape
        for i in range(1, n):
            x, y, bw, bh, a = stats[i]
            inner = x > 0 and y > 0 and x + bw < w and y + bh < h
            if inner and a < cfg.fill_holes * area:
                m[labels == i] = 1
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    small = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] < cfg.min_area * area) + 1
    if len(small):
        m[np.isin(labels, small)] = 0
    return m.astype(bool)


def keep_robot_components(
    fg: np.ndarray,
    support: np.ndarray,
    anchor: np.ndarray,
    gap: int,
) -> np.ndarray:
    """The components of ``fg`` ``[h, w]`` bool that belong to the robot.

    The robot's components touch its ``anchor`` (pixels near the foreground in most fitted
    frames: where the first moving link joins the static part); without any such component,
    the one of highest mean ``support`` (per-pixel foreground frequency in [0, 1]) among those
    of at least a tenth of the largest's area. Components within ``gap`` px of those are kept
    too (the robot cut in two by a cable in front of it); anything farther, e.g. a person
    walking past, is dropped."""
    fg = fg.astype(bool)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg.astype(np.uint8), connectivity=8)
    if n <= 2:
        return fg
    touching = np.unique(labels[anchor & fg])
    robot = touching[touching > 0]
    if len(robot) == 0:
        area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
        mass = np.bincount(labels.ravel(), weights=support.ravel().astype(np.float64), minlength=n)
        mean = mass[1:] / np.maximum(area, 1.0)
        big = np.flatnonzero(area >= 0.1 * area.max())
        robot = big[[int(np.argmax(mean[big]))]] + 1
    core = np.isin(labels, robot)
    if gap > 0:
        near = cv2.dilate(core.astype(np.uint8), _disc(gap)).astype(bool)
        robot = np.union1d(robot, np.unique(labels[near & fg]))
    return np.isin(labels, robot[robot > 0])


class BackgroundModel:
    """One static camera's background at ``cfg.work_width``, fitted on RGB uint8 frames
    ``[H, W, 3]`` (any number ≥ 3, all of one size), and the robot's foreground in any frame.

    ``support`` ``[h, w]`` float32: fraction of the fitted frames in which each pixel is
    foreground (after cleaning); ``anchor`` ``[h, w]`` bool: the pixels within
    ``anchor_radius`` × width of the foreground in at least ``anchor_fraction`` of them;
    ``fitted_foreground``: mean foreground fraction of the fitted frames; ``dropped_frames``:
    how many frames :meth:`segment` dropped a component of (e.g. a person walking past).
    """

    def __init__(self, frames: Iterable[np.ndarray], cfg: MotionConfig | None = None) -> None:
        self.cfg = cfg or MotionConfig()
        small = [self._small(f) for f in frames]
        if len(small) < 3:
            raise SegmentationError(
                f"motion segmentation needs at least 3 frames, got {len(small)}"
            )
        self.shape = small[0].shape[:2]
        self.background: np.ndarray | None = None
        self.subtractor: cv2.BackgroundSubtractor | None = None
        if self.cfg.background == "median":
            stack = np.stack(small).astype(np.float32)
            first = np.median(stack, axis=0)
            gains = np.stack([self._gain(x, first) for x in stack])  # [N, 3]
            self.background = np.median(stack / gains[:, None, None, :], axis=0)
        else:
            sub = cv2.createBackgroundSubtractorMOG2(
                history=len(small), varThreshold=16.0, detectShadows=False
            )
            # only the dominant colour modes (half the weight) are background: the robot,
            # present at a pixel in a minority of the frames, stays foreground
            sub.setBackgroundRatio(0.5)
            rng = np.random.default_rng(0)  # shuffled: the model sees no temporal drift
            for _ in range(2):  # two passes: the first frames are learnt, not judged
                for i in rng.permutation(len(small)):
                    sub.apply(cv2.cvtColor(small[i], cv2.COLOR_RGB2BGR), learningRate=-1)
            self.subtractor = sub
        raw = [clean_mask(self._foreground_small(x), self.cfg) for x in small]
        self.support = np.mean(np.stack(raw), axis=0).astype(np.float32)
        self.fitted_foreground = float(np.mean([m.mean() for m in raw]))
        self.anchor = np.zeros(self.shape, bool)
        r = max(1, round(self.cfg.anchor_radius * self.shape[1]))
        for radius in (r, 2 * r, 4 * r):  # wider where the robot emerges along a long edge
            near = np.mean([cv2.dilate(m.astype(np.uint8), _disc(radius)) for m in raw], axis=0)
            self.anchor = near >= self.cfg.anchor_fraction
            if self.anchor.any():
                break
        self.dropped_frames = 0  # frames of which segment() dropped a component

    def _small(self, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise SegmentationError(f"frames must be uint8 [H, W, 3] RGB, got {img.shape}")
        h, w = img.shape[:2]
        width = min(self.cfg.work_width, w)
        height = max(2, round(h * width / w))
        if (width, height) == (w, h):
            return img
        return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)

    @staticmethod
    def _gain(x: np.ndarray, background: np.ndarray) -> np.ndarray:
        """Per-channel exposure gain of ``x`` relative to ``background`` (median ratio over the
        well-exposed pixels, clipped to [0.5, 2])."""
        ok = background > 16.0
        gains = []
        for c in range(3):
            sel = ok[..., c]
            g = float(np.median(x[..., c][sel] / background[..., c][sel])) if sel.any() else 1.0
            gains.append(min(2.0, max(0.5, g)))
        return np.asarray(gains, np.float32)

    def _foreground_small(self, small: np.ndarray) -> np.ndarray:
        if self.subtractor is not None:
            fg = self.subtractor.apply(cv2.cvtColor(small, cv2.COLOR_RGB2BGR), learningRate=0)
            return fg > 127
        assert self.background is not None
        x = small.astype(np.float32)
        x = x / self._gain(x, self.background)
        d = np.linalg.norm(x - self.background, axis=2)
        noise = 1.4826 * float(np.median(d))
        return d > max(self.cfg.threshold, self.cfg.noise_factor * noise)

    def foreground(self, image: np.ndarray) -> np.ndarray:
        """Cleaned foreground ``[h, w]`` bool at the work resolution (every moving thing)."""
        small = self._small(image)
        if small.shape[:2] != self.shape:
            raise SegmentationError(
                f"frame of size {image.shape[1]}x{image.shape[0]} does not match the "
                "background model's frames"
            )
        return clean_mask(self._foreground_small(small), self.cfg)

    def segment(self, image: np.ndarray) -> np.ndarray:
        """The robot's mask ``[H, W]`` bool at the image's size: the foreground's components
        consistent with the robot (see :func:`keep_robot_components`)."""
        gap = round(self.cfg.join_gap * self.shape[1])
        every = self.foreground(image)
        fg = keep_robot_components(every, self.support, self.anchor, gap)
        if np.count_nonzero(every & ~fg):
            self.dropped_frames += 1
        h, w = image.shape[:2]
        if fg.shape == (h, w):
            return fg
        up = cv2.resize(fg.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        return up > 0.5


def link_surface_points(
    robot: RobotModel, spacing: float, max_points: int = 4000, seed: int = 0
) -> list[np.ndarray]:
    """Per link of ``robot.link_names``, points ``[P, 3]`` (link frame, metres) spread
    uniformly over its surface, about ``spacing`` metres apart (at most ``max_points``; a link
    without geometry gets none). Seeded."""
    rng = np.random.default_rng(seed)
    verts = robot.vertices.detach().cpu().double().numpy()
    faces = robot.faces.cpu().numpy()
    vlink = robot.vertex_link.cpu().numpy()
    face_link = vlink[faces[:, 0]] if len(faces) else np.zeros(0, np.int64)
    out = []
    for link in range(len(robot.link_names)):
        f = faces[face_link == link]
        if len(f) == 0:
            out.append(np.zeros((0, 3)))
            continue
        a, b, c = verts[f[:, 0]], verts[f[:, 1]], verts[f[:, 2]]
        areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        total = float(areas.sum())
        if total <= 0:
            out.append(a[:1].copy())
            continue
        n = int(np.clip(total / spacing**2, 64, max_points))
        pick = rng.choice(len(f), size=n, p=areas / total)
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        u, v = 1 - s, s * (1 - r2)
        pts = u[:, None] * a[pick] + v[:, None] * b[pick] + (1 - u - v)[:, None] * c[pick]
        out.append(pts)
    return out


def link_motion(
    robot: RobotModel,
    q: np.ndarray,
    configs: int = 8,
    spacing: float = 0.003,
    probes: int = 800,
    quantile: float = 0.9,
    seed: int = 0,
) -> dict[str, float]:
    """How far (metres) each link's surface moved over joint configurations ``q`` ``[N, D]``
    (URDF joint order): the largest, over pairs among ``configs`` configurations spread over
    joint space, of the ``quantile`` of the distances from ``probes`` surface points of the
    link posed in one to its surface (points about ``spacing`` apart) posed in the other, both
    ways (base frame). A link that stood still, or only spun about its own axis of symmetry,
    scores about the sampling ``spacing``."""
    from roboseg.registration.register import spread_configurations

    q = np.asarray(q, np.float64)
    if q.ndim != 2 or q.shape[1] != robot.dof:
        raise SegmentationError(f"joint values must be [N, {robot.dof}], got {q.shape}")
    if len(q) == 0:
        return {name: 0.0 for name in robot.link_names}
    scale = (robot.upper - robot.lower).double().cpu().numpy()
    rows = spread_configurations(q, configs, scale)
    T = robot.link_transforms(torch.as_tensor(q[rows], dtype=robot.dtype, device=robot.device))
    T = T.detach().cpu().double().numpy()  # [C, L, 4, 4]
    dense = link_surface_points(robot, spacing, max_points=20000, seed=seed)
    moved: dict[str, float] = {}
    for link, (name, p) in enumerate(zip(robot.link_names, dense, strict=True)):
        if len(p) == 0:
            moved[name] = 0.0
            continue
        probe = p[: min(probes, len(p))]  # the samples are in random order
        R, t = T[:, link, :3, :3], T[:, link, :3, 3]
        trees = [cKDTree(p @ R[c].T + t[c]) for c in range(len(rows))]
        posed = [probe @ R[c].T + t[c] for c in range(len(rows))]
        worst = 0.0
        for i in range(len(rows)):
            for j in range(i + 1, len(rows)):
                d = np.r_[trees[j].query(posed[i])[0], trees[i].query(posed[j])[0]]
                worst = max(worst, float(np.quantile(d, quantile)))
        moved[name] = worst
    return moved
