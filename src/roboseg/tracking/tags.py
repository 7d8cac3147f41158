"""Stereo AprilTag tracking: detection in a region of interest and DLT triangulation.

Paper, Methods "Stereo AprilTag marker tracking": AprilTags (family 36h11) are detected only in a
region of interest (ROI) of each image, with the intrinsics adjusted for the crop offset
``K' = [[fx, 0, cx - tx], [0, fy, cy - ty], [0, 0, 1]]``; the tag centres of a left/right pair are
triangulated by the direct linear transform (``cv2.triangulatePoints``) with the projection
matrices ``P_left = K'_left [I | 0]`` and ``P_right = K'_right [R | t]`` (``T_right_left``).
Positions are in metres in the left camera's OpenCV optical frame (x right, y down, z forward);
pixel coordinates follow the OpenCV convention (integer coordinates are pixel centres).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum

import cv2
import numpy as np

from roboseg.errors import CameraError

log = logging.getLogger(__name__)

#: OpenCV dictionary of the AprilTag family the paper uses.
TAG_DICTIONARY = cv2.aruco.DICT_APRILTAG_36h11

_REFINEMENT = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}


@dataclass(frozen=True)
class Roi:
    """Region of interest: top-left offset ``(tx, ty)`` and size in pixels of the full image."""

    tx: int
    ty: int
    width: int
    height: int

    def clip(self, image_width: int, image_height: int) -> Roi:
        """This ROI intersected with an ``image_width × image_height`` image."""
        x0, y0 = max(self.tx, 0), max(self.ty, 0)
        x1 = min(self.tx + self.width, image_width)
        y1 = min(self.ty + self.height, image_height)
        if x1 <= x0 or y1 <= y0:
            raise CameraError(f"roi {self} lies outside the {image_width}x{image_height} image")
        return Roi(x0, y0, x1 - x0, y1 - y0)


def roi_intrinsics(K: np.ndarray, tx: float, ty: float) -> np.ndarray:
    """Intrinsics ``K'`` of a crop with top-left pixel ``(tx, ty)``: principal point ``c - t``."""
    K_roi = np.array(K, dtype=np.float64, copy=True)
    K_roi[0, 2] -= tx
    K_roi[1, 2] -= ty
    return K_roi


def tag_centre(corners: np.ndarray) -> np.ndarray:
    """Image of a square tag's centre: the intersection of the diagonals of its 4 corners.

    A homography maps the square's centre to the intersection of the imaged diagonals, so this is
    the homography-mapped centre (exact under perspective, unlike the corner mean).
    ``corners``: ``[4, 2]`` pixels in order around the tag. Returns ``[2]`` pixels.
    """
    c = np.asarray(corners, dtype=np.float64)
    h = lambda p: np.array([p[0], p[1], 1.0])  # noqa: E731
    diag_a = np.cross(h(c[0]), h(c[2]))
    diag_b = np.cross(h(c[1]), h(c[3]))
    x = np.cross(diag_a, diag_b)
    if abs(x[2]) < 1e-12:  # degenerate quadrilateral: fall back to the corner mean
        return c.mean(axis=0)
    return x[:2] / x[2]


def _line_through(points: np.ndarray) -> np.ndarray:
    """Homogeneous line ``(a, b, c)`` (``a x + b y + c = 0``) fitted by total least squares."""
    mean = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - mean, full_matrices=False)
    normal = vt[-1]
    return np.array([normal[0], normal[1], -normal @ mean])


def refine_corners_by_edges(
    gray: np.ndarray, corners: np.ndarray, samples_per_px: float = 2.0, blur_sigma: float = 0.0
) -> np.ndarray | None:
    """Sub-pixel corners of a tag's black square from its four edges.

    Along each side (between 15 % and 85 % of its length) the intensity profile across the edge is
    sampled bilinearly; the edge point is where it crosses the mid-level between the black border
    (inside) and the white margin (outside). A total-least-squares line is fitted per side and
    adjacent lines are intersected. The profile reaches at most 0.45 cell into either side, so only
    the black border and the white quiet zone are seen. ``corners``: ``[4, 2]`` initial corners.
    Returns ``[4, 2]`` refined corners, or ``None`` when an edge has too few valid crossings.
    """
    c = np.asarray(corners, dtype=np.float64)
    centre = c.mean(axis=0)
    img = gray.astype(np.float32)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    side_len = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
    half = float(np.clip(0.45 * side_len.min() / 8.0, 0.75, 2.5))
    offsets = np.linspace(-half, half, 13)
    lines = []
    for k in range(4):
        a, b = c[k], c[(k + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([-d[1], d[0]])
        if n @ (0.5 * (a + b) - centre) < 0:
            n = -n  # outward normal
        m = max(int(side_len[k] * 0.7 * samples_per_px), 4)
        s = np.linspace(0.15, 0.85, m) * side_len[k]
        pts = a + s[:, None] * d  # [m, 2]
        grid = pts[:, None, :] + offsets[None, :, None] * n  # [m, o, 2]
        prof = cv2.remap(
            img,
            grid[..., 0].astype(np.float32),
            grid[..., 1].astype(np.float32),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).astype(np.float64)
        lo = prof[:, :2].mean(axis=1, keepdims=True)
        hi = prof[:, -2:].mean(axis=1, keepdims=True)
        rel = (prof - lo) / np.maximum(hi - lo, 1e-6) - 0.5  # −0.5 inside … +0.5 outside
        edge_pts = []
        for j in range(m):
            if hi[j, 0] - lo[j, 0] < 10.0:
                continue  # no contrast (occluded or blurred)
            sign = np.nonzero(np.diff(np.sign(rel[j])) > 0)[0]
            if len(sign) != 1:
                continue
            i = sign[0]
            f = rel[j, i] / (rel[j, i] - rel[j, i + 1])
            o = offsets[i] + f * (offsets[i + 1] - offsets[i])
            edge_pts.append(pts[j] + o * n)
        if len(edge_pts) < 3:
            return None
        lines.append(_line_through(np.asarray(edge_pts)))
    refined = np.empty((4, 2))
    for k in range(4):
        x = np.cross(lines[(k - 1) % 4], lines[k])  # corner k joins side k-1 and side k
        if abs(x[2]) < 1e-12:
            return None
        refined[k] = x[:2] / x[2]
    if np.max(np.linalg.norm(refined - c, axis=1)) > max(2.0, 0.25 * side_len.min() / 8 * 4):
        return None
    return refined


def make_detector(refinement: str = "edges") -> cv2.aruco.ArucoDetector:
    """OpenCV ArUco detector for AprilTag 36h11 with the named corner refinement.

    ``"edges"`` uses OpenCV's contour refinement, then :func:`refine_corners_by_edges` is applied
    by :func:`detect_tags`.
    """
    if refinement not in _REFINEMENT and refinement != "edges":
        raise CameraError(
            f"corner refinement {refinement!r} is not one of {sorted([*_REFINEMENT, 'edges'])}"
        )
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = _REFINEMENT.get(refinement, cv2.aruco.CORNER_REFINE_CONTOUR)
    params.cornerRefinementWinSize = 3
    params.cornerRefinementMinAccuracy = 0.001
    params.cornerRefinementMaxIterations = 100
    dictionary = cv2.aruco.getPredefinedDictionary(TAG_DICTIONARY)
    return cv2.aruco.ArucoDetector(dictionary, params)


def detect_tags(
    image: np.ndarray,
    roi: Roi | None = None,
    detector: cv2.aruco.ArucoDetector | None = None,
    edge_refinement: bool = True,
) -> dict[int, np.ndarray]:
    """Detect AprilTags in ``image`` (``H×W`` grey or ``H×W×3`` RGB) inside ``roi``.

    Returns ``{tag id: corners [4, 2]}`` in **ROI pixel coordinates** (pair them with
    :func:`roi_intrinsics`), refined by :func:`refine_corners_by_edges` when ``edge_refinement``
    (OpenCV's corners are kept where that fails). Tags whose id appears twice are dropped
    (ambiguous). An empty dict means no tag was found.
    """
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if roi is not None:
        roi = roi.clip(image.shape[1], image.shape[0])
        image = image[roi.ty : roi.ty + roi.height, roi.tx : roi.tx + roi.width]
    detector = detector or make_detector()
    corners, ids, _ = detector.detectMarkers(np.ascontiguousarray(image))
    if ids is None:
        return {}
    found: dict[int, np.ndarray] = {}
    duplicates: set[int] = set()
    for tag_id, c in zip(ids.ravel().tolist(), corners, strict=True):
        if tag_id in found:
            duplicates.add(tag_id)
        corners4 = np.asarray(c, dtype=np.float64).reshape(4, 2)
        if edge_refinement:
            refined = refine_corners_by_edges(image, corners4)
            if refined is None:
                log.debug("tag %d: edge refinement failed, OpenCV corners kept", tag_id)
            else:
                corners4 = refined
        found[tag_id] = corners4
    for tag_id in duplicates:
        log.warning("tag %d detected more than once in one image; ignored", tag_id)
        del found[tag_id]
    return found


def stereo_projection_matrices(
    K_left: np.ndarray, K_right: np.ndarray, T_right_left: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``P_left = K_left [I | 0]`` and ``P_right = K_right [R | t]`` (3×4, left optical frame)."""
    P_left = np.asarray(K_left, dtype=np.float64) @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P_right = np.asarray(K_right, dtype=np.float64) @ np.asarray(T_right_left, np.float64)[:3, :]
    return P_left, P_right


def triangulate_dlt(
    P_left: np.ndarray, P_right: np.ndarray, uv_left: np.ndarray, uv_right: np.ndarray
) -> np.ndarray:
    """DLT triangulation of ``N`` correspondences (``[N, 2]`` pixels) → ``[N, 3]`` points.

    Points are in the frame the projection matrices map from; rows whose homogeneous scale
    vanishes (point at infinity) are NaN — callers must check (:class:`StereoTagTracker` does).
    """
    uv_l = np.asarray(uv_left, dtype=np.float64).reshape(-1, 2)
    uv_r = np.asarray(uv_right, dtype=np.float64).reshape(-1, 2)
    if len(uv_l) == 0:
        return np.zeros((0, 3))
    X = cv2.triangulatePoints(P_left, P_right, uv_l.T.copy(), uv_r.T.copy())
    w = X[3]
    out = np.full((uv_l.shape[0], 3), np.nan)
    ok = np.abs(w) > 1e-12
    out[ok] = (X[:3, ok] / w[ok]).T
    return out


def reprojection_error(P: np.ndarray, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixel distance between ``uv [N, 2]`` and the projection of ``points [N, 3]`` by ``P``."""
    X = np.hstack([points, np.ones((len(points), 1))])
    x = X @ P.T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = x[:, :2] / x[:, 2:3]
    return np.linalg.norm(proj - uv, axis=1)


class TagStatus(str, Enum):
    """Outcome for one tag in one stereo frame."""

    TRIANGULATED = "triangulated"
    LEFT_ONLY = "left_only"  # seen in the left image only: not triangulated
    RIGHT_ONLY = "right_only"  # seen in the right image only: not triangulated
    REJECTED = "rejected"  # seen in both, but behind the cameras or inconsistent reprojection


@dataclass(frozen=True)
class TagObservation:
    """One tag in one stereo frame. ``position_cam`` (metres, left optical frame) is set only when
    ``status`` is ``TRIANGULATED``; ``reprojection_px`` is the worse of the two views."""

    tag_id: int
    status: TagStatus
    position_cam: np.ndarray | None = None
    reprojection_px: float | None = None


@dataclass(frozen=True)
class FrameTags:
    """All tags of one stereo frame (``observations`` empty = no tag found in either image)."""

    stamp_ns: int
    observations: dict[int, TagObservation]

    @property
    def triangulated(self) -> dict[int, np.ndarray]:
        """``{tag id: position [3]}`` of the tags triangulated in this frame."""
        return {
            i: o.position_cam
            for i, o in self.observations.items()
            if o.status is TagStatus.TRIANGULATED and o.position_cam is not None
        }


class StereoTagTracker:
    """Detect AprilTags in a left/right ROI pair and triangulate their centres (DLT).

    ``K_left``/``K_right`` are full-image intrinsics (3×3), ``T_right_left`` the stereo extrinsics.
    ``roi_left``/``roi_right`` (``None`` = whole image) are cropped before detection and their
    offsets folded into ``K'``. A tag seen in both views is ``REJECTED`` when its triangulated
    centre is not in front of both cameras or reprojects worse than ``max_reprojection_px``.
    """

    def __init__(
        self,
        K_left: np.ndarray,
        K_right: np.ndarray,
        T_right_left: np.ndarray,
        roi_left: Roi | None = None,
        roi_right: Roi | None = None,
        max_reprojection_px: float = 2.0,
        refinement: str = "edges",
    ) -> None:
        self.K_left = np.asarray(K_left, dtype=np.float64)
        self.K_right = np.asarray(K_right, dtype=np.float64)
        self.T_right_left = np.asarray(T_right_left, dtype=np.float64)
        self.roi_left = roi_left
        self.roi_right = roi_right
        self.max_reprojection_px = float(max_reprojection_px)
        self.detector = make_detector(refinement)
        self.edge_refinement = refinement == "edges"

    def _roi_K(
        self, K: np.ndarray, roi: Roi | None, image: np.ndarray
    ) -> tuple[Roi | None, np.ndarray]:
        if roi is None:
            return None, K
        roi = roi.clip(image.shape[1], image.shape[0])
        return roi, roi_intrinsics(K, roi.tx, roi.ty)

    def process(self, stamp_ns: int, left: np.ndarray, right: np.ndarray) -> FrameTags:
        """Detect and triangulate the tags of one stereo frame."""
        roi_l, K_l = self._roi_K(self.K_left, self.roi_left, left)
        roi_r, K_r = self._roi_K(self.K_right, self.roi_right, right)
        det_l = detect_tags(left, roi_l, self.detector, self.edge_refinement)
        det_r = detect_tags(right, roi_r, self.detector, self.edge_refinement)
        obs: dict[int, TagObservation] = {}
        for i in sorted(set(det_l) - set(det_r)):
            obs[i] = TagObservation(i, TagStatus.LEFT_ONLY)
        for i in sorted(set(det_r) - set(det_l)):
            obs[i] = TagObservation(i, TagStatus.RIGHT_ONLY)
        both = sorted(set(det_l) & set(det_r))
        if both:
            P_l, P_r = stereo_projection_matrices(K_l, K_r, self.T_right_left)
            uv_l = np.stack([tag_centre(det_l[i]) for i in both])
            uv_r = np.stack([tag_centre(det_r[i]) for i in both])
            X = triangulate_dlt(P_l, P_r, uv_l, uv_r)
            err = np.maximum(reprojection_error(P_l, X, uv_l), reprojection_error(P_r, X, uv_r))
            X_right = X @ self.T_right_left[:3, :3].T + self.T_right_left[:3, 3]
            for k, i in enumerate(both):
                good = (
                    bool(np.all(np.isfinite(X[k])))
                    and X[k, 2] > 0
                    and X_right[k, 2] > 0
                    and float(err[k]) <= self.max_reprojection_px
                )
                if good:
                    obs[i] = TagObservation(i, TagStatus.TRIANGULATED, X[k].copy(), float(err[k]))
                else:
                    e = float(err[k]) if np.isfinite(err[k]) else None
                    obs[i] = TagObservation(i, TagStatus.REJECTED, None, e)
        return FrameTags(int(stamp_ns), dict(sorted(obs.items())))


@dataclass
class TagTracks:
    """Per-tag position histories over a sequence of :class:`FrameTags`.

    ``visibility(tag)`` is the fraction of frames in which the tag was triangulated (the paper's
    "successfully triangulated x % of the time"); frames with no tag at all still count.
    """

    frames: list[FrameTags] = field(default_factory=list)

    def add(self, frame: FrameTags) -> None:
        self.frames.append(frame)

    def extend(self, frames: Iterable[FrameTags]) -> None:
        for f in frames:
            self.add(f)

    @property
    def tag_ids(self) -> list[int]:
        return sorted({i for f in self.frames for i in f.observations})

    def visibility(self) -> dict[int, float]:
        """``{tag id: fraction of frames with a triangulated position}`` (0 … 1)."""
        n = len(self.frames)
        return {
            i: sum(1 for f in self.frames if i in f.triangulated) / n if n else 0.0
            for i in self.tag_ids
        }

    def trajectory(
        self, tag_id: int, T_cam_base: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(stamps_ns [M], positions [M, 3])`` of one tag over the frames it was triangulated.

        Positions are in the left camera frame, or in the robot base frame when ``T_cam_base``
        (a registration result, ``p_cam = T_cam_base @ p_base``) is given. ``M`` may be 0.
        """
        stamps = [f.stamp_ns for f in self.frames if tag_id in f.triangulated]
        pos = [f.triangulated[tag_id] for f in self.frames if tag_id in f.triangulated]
        P = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        if T_cam_base is not None:
            P = camera_to_base(P, T_cam_base)
        return np.asarray(stamps, dtype=np.int64), P


def camera_to_base(points_cam: np.ndarray, T_cam_base: np.ndarray) -> np.ndarray:
    """Map ``[N, 3]`` camera-frame points into the robot base frame: ``T_cam_base⁻¹ p``."""
    T = np.asarray(T_cam_base, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    return (np.asarray(points_cam, dtype=np.float64) - t) @ R
