"""Classical promptable segmentation: OpenCV GrabCut from a person's prompt, then tracked.

On the prompted frame, GrabCut starts from the prompt: outside the box is background, inside it
probably the robot; foreground / background clicks are certain (small discs). Without a box,
discs around the foreground clicks are probably the robot and the rest probably background.

Each later (or earlier) frame starts from the previous mask carried along the dense optical
flow between the two frames (OpenCV's DIS flow, which follows large displacements of thin
parts better than Farnebäck's: measured on a synthetic arm moving up to ~20 px per frame, mean
IoU 0.995 against 0.82): its interior eroded by a band is certainly the
robot, the band inside probably, the band outside probably background and the rest background.
GrabCut runs on a crop about that region (local colour models, less work). A result whose area
jumps (less than half or more than twice the carried mask's) is replaced by the carried mask.

Images are segmented ``work_width`` pixels wide; prompts and masks are scaled accordingly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from roboseg.errors import PromptError, SegmentationError
from roboseg.registration.prompts import CameraPrompt

__all__ = [
    "GrabCutConfig",
    "GrabCutTracker",
    "grabcut",
    "grabcut_deferring",
    "gmm_log_likelihood",
    "keep_out_background",
    "silhouette_trimap",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GrabCutConfig:
    """GrabCut settings (``grabcut:`` in ``conf/register.yaml``).

    ``work_width`` px; ``iterations`` on the prompted frame, ``track_iterations`` per later
    frame; ``band``: half-width of the uncertain band about a carried mask, fraction of the
    width; ``margin``: the crop GrabCut sees is the uncertain region's box grown by this
    fraction of its size per side; ``point_radius`` px (at ``work_width``) of a click's disc;
    ``flow``: carry masks along the optical flow (else unmoved); ``max_frames``: at most this
    many frames are segmented (evenly strided through the recording's window).
    """

    work_width: int = 480
    iterations: int = 5
    track_iterations: int = 3
    band: float = 0.02
    margin: float = 0.3
    point_radius: int = 3
    flow: bool = True
    max_frames: int = 200

    def __post_init__(self) -> None:
        if self.work_width < 16:
            raise SegmentationError(f"grabcut.work_width must be >= 16 px, got {self.work_width}")
        if self.iterations < 1 or self.track_iterations < 1:
            raise SegmentationError("grabcut.iterations and grabcut.track_iterations must be >= 1")
        if not 0 < self.band < 0.5 or self.margin < 0:
            raise SegmentationError("grabcut.band must be in (0, 0.5) and grabcut.margin >= 0")
        if self.max_frames < 1:
            raise SegmentationError(f"grabcut.max_frames must be >= 1, got {self.max_frames}")


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _cut(
    image: np.ndarray, trimap: np.ndarray, iterations: int, margin: float
) -> tuple[np.ndarray, tuple[int, int, int, int], np.ndarray, np.ndarray, np.ndarray] | None:
    """GrabCut on the crop about ``trimap``'s labels other than ``GC_BGD``: ``(robot mask of the
    crop, (y0, y1, x0, x1), the crop BGR, background GMM, robot GMM)``; None without any robot
    label."""
    h, w = trimap.shape
    if not np.isin(trimap, (cv2.GC_FGD, cv2.GC_PR_FGD)).any():
        return None
    active = trimap != cv2.GC_BGD
    rows, cols = np.flatnonzero(active.any(1)), np.flatnonzero(active.any(0))
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    gy, gx = round(margin * (y1 - y0)) + 2, round(margin * (x1 - x0)) + 2
    y0, y1, x0, x1 = max(0, y0 - gy), min(h, y1 + gy), max(0, x0 - gx), min(w, x1 + gx)
    sub = np.ascontiguousarray(trimap[y0:y1, x0:x1])
    if not np.isin(sub, (cv2.GC_BGD, cv2.GC_PR_BGD)).any():
        raise SegmentationError("GrabCut needs some background: the prompt covers the image")
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    crop = np.ascontiguousarray(cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_RGB2BGR))
    cv2.grabCut(crop, sub, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    return (sub == cv2.GC_FGD) | (sub == cv2.GC_PR_FGD), (y0, y1, x0, x1), crop, bgd, fgd


def grabcut(image: np.ndarray, trimap: np.ndarray, iterations: int, margin: float) -> np.ndarray:
    """GrabCut of RGB uint8 ``image`` ``[h, w, 3]`` from ``trimap`` ``[h, w]`` uint8 of
    ``cv2.GC_*`` labels, on the crop about the labels other than ``GC_BGD`` (grown by
    ``margin`` × its size per side): robot mask ``[h, w]`` bool (empty without any robot
    label). Raises :class:`SegmentationError` when the crop holds no background to learn from.
    """
    out = np.zeros(trimap.shape, bool)
    cut = _cut(image, trimap, iterations, margin)
    if cut is not None:
        mask, (y0, y1, x0, x1), *_ = cut
        out[y0:y1, x0:x1] = mask
    return out


def gmm_log_likelihood(model: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Log-density ``[M]`` of colours ``pixels`` ``[M, 3]`` (BGR, 0-255) under a GrabCut colour
    model ``[1, 65]`` as ``cv2.grabCut`` fills it: 5 weights, then 5 means [3], then 5
    covariances [3, 3]. Empty components (weight 0) are skipped."""
    m = np.asarray(model, np.float64).ravel()
    k = 5
    weights, means, covs = m[:k], m[k : 4 * k].reshape(k, 3), m[4 * k :].reshape(k, 3, 3)
    x = np.asarray(pixels, np.float64)
    out = np.full(len(x), -np.inf)
    for w, mu, cov in zip(weights, means, covs, strict=True):
        if w <= 0:
            continue
        c = cov + 1e-6 * np.eye(3)  # a guard: OpenCV already keeps them invertible
        d = x - mu
        maha = np.einsum("ni,ij,nj->n", d, np.linalg.inv(c), d)
        out = np.logaddexp(
            out, math.log(w) - 0.5 * (maha + math.log(np.linalg.det(c)) + 3 * math.log(2 * math.pi))
        )
    return out


def grabcut_deferring(
    image: np.ndarray,
    trimap: np.ndarray,
    reference: np.ndarray,
    iterations: int,
    margin: float,
    defer_nats: float,
) -> np.ndarray:
    """GrabCut as :func:`grabcut`, then every pixel where the cut disagrees with ``reference``
    (``[h, w]`` bool, e.g. the silhouette the trimap came from) keeps the cut's label only where
    the pixel's own colour backs it: its log-likelihood under the cut's robot colour model minus
    that under its background model exceeds ``defer_nats`` (for robot; below ``-defer_nats``
    for background). Elsewhere the reference stands.

    GrabCut's smoothness term shortens outlines where the robot's edge is faint (a pale arm
    against a pale wall, a shadowed side): the cut then lies inside the true outline on those
    sides, and a pose refit on such cuts moves away (farther from the camera) round after
    round. Where the colours cannot tell, deferring keeps the estimate's outline; where they
    can, the cut still moves it."""
    ref = np.asarray(reference, bool)
    cut = _cut(image, trimap, iterations, margin)
    if cut is None:
        return np.zeros(trimap.shape, bool)
    mask, (y0, y1, x0, x1), crop, bgd, fgd = cut
    own = ref[y0:y1, x0:x1]
    differ = mask != own
    if differ.any():
        colours = crop[differ].astype(np.float64)
        llr = gmm_log_likelihood(fgd, colours) - gmm_log_likelihood(bgd, colours)
        backed = np.where(mask[differ], llr > defer_nats, llr < -defer_nats)
        merged = own.copy()
        merged[differ] = np.where(backed, mask[differ], own[differ])
        mask = merged
    out = ref.copy()
    out[y0:y1, x0:x1] = mask
    return out


def silhouette_trimap(
    silhouette: np.ndarray, inner_px: int, outer_px: int, background: np.ndarray | None = None
) -> np.ndarray:
    """GrabCut labels ``[h, w]`` uint8 from a rendered robot silhouette ``[h, w]`` bool (e.g. at
    a pose estimate a few millimetres off): robot for sure inside it eroded by ``inner_px``,
    probably robot in the rest of it, probably background within ``outer_px`` outside it,
    background for sure beyond, and wherever ``background`` (``[h, w]`` bool, optional) holds
    outside the silhouette. The cut then places the outline on the image's own edges within that
    band."""
    sil = np.asarray(silhouette, bool)
    s8 = sil.astype(np.uint8)
    sure = cv2.erode(s8, _disc(inner_px)).astype(bool) if inner_px > 0 else sil
    near = cv2.dilate(s8, _disc(outer_px)).astype(bool) if outer_px > 0 else sil
    out = np.full(sil.shape, cv2.GC_BGD, np.uint8)
    out[near & ~sil] = cv2.GC_PR_BGD
    out[sil] = cv2.GC_PR_FGD
    out[sure] = cv2.GC_FGD
    if background is not None:
        out[np.asarray(background, bool) & ~sil] = cv2.GC_BGD
    return out


def keep_out_background(first_mask: np.ndarray, margin_px: int) -> np.ndarray:
    """Sure background ``[H, W]`` bool for GrabCut's keep-out: what round 0's mask
    (``[H, W]`` bool) calls background farther than ``margin_px`` from its robot pixels.

    Round 0's segmentor tends to draw the robot thinner than it is; keeping out every pixel it
    misses forbids the cut to grow back over the robot's true edge, so rounds started from an
    estimate too far away stay too far. A margin leaves the robot's edge to the colours and
    still keeps out what lies well away from it (a person passing by)."""
    m8 = np.asarray(first_mask, np.uint8)
    if margin_px > 0:
        m8 = cv2.dilate(m8, _disc(margin_px))
    return m8 == 0


def _keep_components(mask: np.ndarray, seeds: np.ndarray, min_ratio: float = 0.1) -> np.ndarray:
    """Components of ``mask`` touching ``seeds`` (bool) or, without any, those of at least
    ``min_ratio`` × the largest's area."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask.astype(bool)
    hit = np.unique(labels[seeds & mask])
    hit = hit[hit > 0]
    if len(hit) == 0:
        area = stats[1:, cv2.CC_STAT_AREA]
        hit = np.flatnonzero(area >= min_ratio * area.max()) + 1
    return np.isin(labels, hit)


class GrabCutTracker:
    """GrabCut on a prompted frame, then frame by frame along the optical flow.

    ``start(image, prompt)`` segments the prompted frame, ``step(image)`` the next one (in
    either direction through time); both return the mask ``[H, W]`` bool at the image's size
    and remember the work-resolution image and mask for the next step. Images RGB uint8.
    """

    def __init__(self, cfg: GrabCutConfig | None = None) -> None:
        self.cfg = cfg or GrabCutConfig()
        self.image: np.ndarray | None = None
        self.mask: np.ndarray | None = None
        self.fallbacks = 0  # frames whose GrabCut result was replaced by the carried mask
        self._flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)

    def _small(self, image: np.ndarray) -> np.ndarray:
        h, w = image.shape[:2]
        width = min(self.cfg.work_width, w)
        height = max(2, round(h * width / w))
        if (width, height) == (w, h):
            return np.ascontiguousarray(image)
        return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)

    @staticmethod
    def _full(mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        h, w = shape[:2]
        if mask.shape == (h, w):
            return mask.copy()
        up = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        return up > 0.5

    def start(self, image: np.ndarray, prompt: CameraPrompt, where: str = "prompt") -> np.ndarray:
        """Segment the prompted frame; ``prompt`` in the image's pixels (``where`` names it in
        errors)."""
        small = self._small(image)
        h, w = small.shape[:2]
        p = prompt.scaled(w / image.shape[1], h / image.shape[0])
        r = max(1, self.cfg.point_radius)
        fg_seed = np.zeros((h, w), np.uint8)
        if p.box is not None:
            trimap = np.full((h, w), cv2.GC_BGD, np.uint8)
            x0, y0, x1, y1 = (round(v) for v in p.box)
            trimap[max(0, y0) : y1 + 1, max(0, x0) : x1 + 1] = cv2.GC_PR_FGD
        else:
            trimap = np.full((h, w), cv2.GC_PR_BGD, np.uint8)
            big = max(r + 1, round(0.08 * w))
            for x, y in p.foreground:
                cv2.circle(trimap, (round(x), round(y)), big, int(cv2.GC_PR_FGD), -1)
        for x, y in p.foreground:
            cv2.circle(trimap, (round(x), round(y)), r, int(cv2.GC_FGD), -1)
            cv2.circle(fg_seed, (round(x), round(y)), r, 1, -1)
        for x, y in p.background:
            cv2.circle(trimap, (round(x), round(y)), r, int(cv2.GC_BGD), -1)
        try:
            mask = grabcut(small, trimap, self.cfg.iterations, self.cfg.margin)
        except SegmentationError as exc:
            raise PromptError(f"{where}: {exc}") from exc
        seeds = fg_seed.astype(bool) if len(p.foreground) else np.zeros((h, w), bool)
        mask = _keep_components(mask, seeds)
        if not mask.any():
            raise PromptError(f"{where}: GrabCut found no robot at the prompt")
        self.image, self.mask = small, mask
        return self._full(mask, image.shape)

    def carry(self, small: np.ndarray) -> np.ndarray:
        """The remembered mask carried to ``small`` (work resolution) along the optical flow."""
        assert self.image is not None and self.mask is not None
        if not self.cfg.flow:
            return self.mask.copy()
        prev = cv2.cvtColor(self.image, cv2.COLOR_RGB2GRAY)
        cur = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
        # backward flow: cur(p) ≈ prev(p + flow(p)), so the mask is sampled there
        flow = self._flow.calc(cur, prev, None)
        h, w = cur.shape
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        moved = cv2.remap(
            self.mask.astype(np.float32),
            gx + flow[..., 0],
            gy + flow[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0.0,
        )
        return moved > 0.5

    def step(self, image: np.ndarray) -> np.ndarray:
        """Segment the next frame from the remembered one."""
        if self.image is None or self.mask is None:
            raise SegmentationError("GrabCutTracker.step before start")
        small = self._small(image)
        carried = self.carry(small)
        h, w = carried.shape
        r = max(1, round(self.cfg.band * w))
        inner = cv2.erode(carried.astype(np.uint8), _disc(r)).astype(bool)
        outer = cv2.dilate(carried.astype(np.uint8), _disc(r)).astype(bool)
        trimap = np.full((h, w), cv2.GC_BGD, np.uint8)
        trimap[outer] = cv2.GC_PR_BGD
        trimap[carried] = cv2.GC_PR_FGD
        trimap[inner] = cv2.GC_FGD
        mask = np.zeros((h, w), bool)
        if carried.any():
            try:
                mask = grabcut(small, trimap, self.cfg.track_iterations, self.cfg.margin)
            except SegmentationError:
                mask = carried
            mask = _keep_components(mask, carried)
        area, before = np.count_nonzero(mask), np.count_nonzero(carried)
        if not before / 2 <= area <= 2 * before:
            self.fallbacks += 1
            mask = carried
        self.image, self.mask = small, mask
        return self._full(mask, image.shape)
