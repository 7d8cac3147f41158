"""Register a robot in a stereo recording: select configurations, segment, CSO → SDR → SDR+prior.

Reads only the stereo images, CameraInfo, the left↔right transform from ``/tf_static``, joint
states and the ``roboseg_sim`` metadata (drape stamp, for ``phase``); never ground-truth mask
topics nor robot-base transforms. The result ``T_cam_base`` maps base-frame points into the left
OpenCV optical frame (metres).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np
import torch

from roboseg.camera import Intrinsics, StereoRig
from roboseg.errors import CameraError, RecordingError, RobotModelError
from roboseg.recording import RecordingReader, StereoFrame
from roboseg.registration.cso import CSOConfig, cso
from roboseg.registration.sdr import RegistrationResult, SDRConfig, sdr, sdr_multistart
from roboseg.registration.sdr_prior import (
    PriorConfig,
    PriorResult,
    render_prior,
    sdr_with_prior,
)
from roboseg.registration.views import View, crop_to_masks, stereo_views, views_for_width
from roboseg.robot import RobotModel

__all__ = [
    "Phase",
    "Method",
    "MaskSource",
    "RegisterConfig",
    "Configuration",
    "Registration",
    "spread_configurations",
    "phase_window",
    "register",
]

log = logging.getLogger(__name__)

Phase = Literal["undraped", "draped", "all"]
Method = Literal["sdr", "sdr_prior"]
DisparityRetry = Literal["failed", "always"]
#: ``masks(frame) -> (left [H, W] bool, right [H, W] bool)``: segmentations given by the caller.
MaskSource = Callable[[StereoFrame], tuple[np.ndarray, np.ndarray]]
SIM_METADATA = "roboseg_sim"


@dataclass(frozen=True)
class RegisterConfig:
    """What to register on and how.

    ``configs`` stereo configurations spread over joint space among the frames of ``phase``
    (``undraped``/``draped`` need the ``roboseg_sim`` metadata) within ``[start_ns, stop_ns)``;
    ``robot`` the namespace whose joints are used (None: the only/first one). Frames whose mask
    covers less than ``min_mask_fraction`` of either image are dropped. Everything is fitted in
    the region of interest: the masks' bounding box grown by ``roi_margin`` per side. CSO scores
    the first ``cso_configs`` (most spread) configurations with the mesh decimated by
    ``cso_reduction``; multi-start SDR from its candidates renders at most ``coarse_width`` px
    wide (None: ``width``; every start first runs ``screen_iterations`` iterations and only the
    best continues, None: all run to the end), then the best start is refined at most ``width``
    px wide with the mesh decimated by ``sdr_reduction`` (decimation biases SDR by millimetres).
    ``sdr.boundary_offset`` lets each segmentation's boundary shift by up to that many pixels
    (robustness to masks that are uniformly too fat or thin). When the recording holds several
    robots (the masks show all of them), the SDR estimate is refined once more on the mask
    pixels within ``other_robots_margin`` × image width of this robot's silhouette (SDR with
    prior does the same around each prior), so the other robots neither pull the fit nor lower
    its IoU; 0 turns this off. ``trim_masks``: the masks may hold more than the robot (motion
    segmentation while people walk past, a model's false positives on other objects): the SDR
    estimate is refined once more on the mask pixels within that same margin of its silhouette,
    and SDR with prior keeps those around each prior, as for several robots. A result whose
    mean IoU is below ``min_iou`` is reported as a poor fit, and so is an SDR-with-prior result
    whose IoU against the prior-free segmentation is. SDR with prior runs ``prior``'s
    iterations and refreshes with ``sdr``'s settings (offsets, disparity term, lr). With the
    stereo disparity term (``sdr.disparity_weight`` > 0) the fit is done again without it when
    it fails that check (``disparity_retry=failed``) or always (``always``), and the fit with
    the higher mean IoU is kept.
    """

    configs: int = 9
    phase: Phase = "all"
    start_ns: int | None = None
    stop_ns: int | None = None
    robot: str | None = None
    method: Method = "sdr_prior"
    width: int = 320
    coarse_width: int | None = 160
    screen_iterations: int | None = 40
    cso_configs: int = 4
    roi_margin: float = 0.3
    cso_reduction: float = 0.98
    sdr_reduction: float = 0.0
    min_mask_fraction: float = 0.002
    min_iou: float = 0.5
    other_robots_margin: float = 0.05
    trim_masks: bool = False
    disparity_retry: DisparityRetry = "failed"
    cso: CSOConfig = field(
        default_factory=lambda: CSOConfig(n_particles=1000, iterations=20, width=48, restarts=2)
    )
    sdr: SDRConfig = field(
        default_factory=lambda: SDRConfig(max_iterations=200, boundary_offset=4.0)
    )
    prior: PriorConfig = field(default_factory=PriorConfig)

    def __post_init__(self) -> None:
        if self.configs < 1:
            raise CameraError(f"configs must be >= 1, got {self.configs}")
        if self.phase not in ("undraped", "draped", "all"):
            raise RecordingError(f"phase must be undraped, draped or all, got {self.phase!r}")
        if self.method not in ("sdr", "sdr_prior"):
            raise CameraError(f"method must be sdr or sdr_prior, got {self.method!r}")
        if self.disparity_retry not in get_args(DisparityRetry):
            raise CameraError(
                f"disparity_retry must be one of {get_args(DisparityRetry)}, got "
                f"{self.disparity_retry!r}"
            )
        if self.other_robots_margin < 0:
            raise CameraError(
                f"other_robots_margin must be >= 0 (fraction of the image width), got "
                f"{self.other_robots_margin}"
            )


@dataclass(frozen=True)
class Configuration:
    """A frame used for registration: recording index, stamp (ns), joints (rad/m, URDF order)."""

    index: int
    stamp_ns: int
    joints: np.ndarray


@dataclass
class Registration:
    """Outcome of :func:`register`.

    ``T_cam_base`` [4, 4]: base frame → left optical frame (metres) of the final method;
    ``result`` that method's :class:`RegistrationResult`; ``sdr`` the plain SDR result;
    ``prior`` the SDR-with-prior result (None for method ``sdr``); ``dropped`` one line per frame
    or problem left out; ``images``/``masks`` per view ``[C, H, W(, 3)]`` of the used frames;
    ``cso_fitness`` the swarm's best mean IoU and ``cso_runs`` how many swarms it took;
    ``links`` the links rendered and compared (None: all of them).
    """

    T_cam_base: np.ndarray
    method: Method
    result: RegistrationResult
    sdr: RegistrationResult
    prior: PriorResult | None
    configurations: list[Configuration]
    camera_frame: str
    base_frame: str
    robot: str
    robots_in_masks: list[str]
    joint_names: list[str]
    dropped: list[str]
    warnings: list[str]
    views: list[View]
    images: list[np.ndarray]
    masks: list[np.ndarray]
    cso_fitness: float
    cso_runs: int
    seconds: dict[str, float]
    links: list[str] | None = None

    @property
    def converged(self) -> bool:
        """False when SDR diverged or the fit is poor (see :attr:`warnings`)."""
        return self.result.reason != "diverged" and not any(
            w.startswith("poor fit") for w in self.warnings
        )


def spread_configurations(q: np.ndarray, n: int, scale: np.ndarray | None = None) -> list[int]:
    """Indices of ``n`` rows of ``q`` [N, D] spread out over joint space (greedy farthest-point
    order in joints divided by ``scale`` [D], e.g. the joint ranges; first the row farthest from
    the mean). Returns all N indices in that order when ``n >= N``."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or len(q) == 0:
        return []
    x = q / (np.ones(q.shape[1]) if scale is None else np.maximum(np.asarray(scale), 1e-9))
    first = int(np.argmax(np.linalg.norm(x - x.mean(axis=0), axis=1)))
    order = [first]
    dist = np.linalg.norm(x - x[first], axis=1)
    while len(order) < min(n, len(q)):
        nxt = int(np.argmax(dist))
        if dist[nxt] <= 0 and len(order) >= 1:  # only repeats left
            rest = [i for i in range(len(q)) if i not in order]
            order.extend(rest[: n - len(order)])
            break
        order.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(x - x[nxt], axis=1))
    return order


def refit_on_own_pixels(
    verts: torch.Tensor,
    faces: torch.Tensor,
    views: Sequence[View],
    masks: Sequence[np.ndarray],
    res: RegistrationResult,
    silhouettes: Sequence[np.ndarray],
    margins_px: Sequence[float],
    cfg: RegisterConfig,
) -> tuple[RegistrationResult, list[np.ndarray]]:
    """SDR again from ``res`` on only the mask pixels within ``margins_px`` of the estimate's
    ``silhouettes`` (per view ``[C, H, W]`` bool; :func:`near_silhouettes`): other robots in the
    masks removed. Returns the refit and its masks, or ``res`` and ``masks`` unchanged when a view
    would keep no pixel or the refit diverges."""
    own = [near_silhouettes(m, s, r) for m, s, r in zip(masks, silhouettes, margins_px,
                                                          strict=True)]
    if not all(m.any() for m in own):
        return res, list(masks)
    own_views, own_masks = crop_to_masks(list(views), own, cfg.roi_margin)
    refit = sdr(verts, faces, views_for_width(own_views, cfg.width), own_masks, res.T_cam_base,
                cfg.sdr)
    return (refit, own) if refit.reason != "diverged" else (res, list(masks))


def near_silhouettes(masks: np.ndarray, silhouettes: np.ndarray, margin_px: float) -> np.ndarray:
    """``masks`` ``[C, H, W]`` bool without the pixels farther than ``margin_px`` (Euclidean,
    between pixel centres) from every pixel of the matching ``silhouettes`` ``[C, H, W]`` bool:
    the part of a segmentation that one robot's estimate can explain, other robots removed.
    An empty silhouette keeps nothing of its mask."""
    masks = np.asarray(masks, dtype=bool)
    out = np.zeros_like(masks)
    for i, (m, s) in enumerate(zip(masks, np.asarray(silhouettes, dtype=bool), strict=True)):
        if s.any():
            dist = cv2.distanceTransform((~s).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            out[i] = m & (dist <= margin_px)
    return out


def phase_window(
    metadata: dict[str, dict[str, str]],
    phase: Phase,
    start_ns: int | None = None,
    stop_ns: int | None = None,
    source: str = "recording",
) -> tuple[int | None, int | None]:
    """``[lo, hi)`` stamp window (ns, None = open) of ``phase`` intersected with start/stop.

    ``undraped`` ends and ``draped`` begins at the ``roboseg_sim`` ``drape_start_stamp_ns``.
    """
    lo, hi = start_ns, stop_ns
    if phase == "all":
        return lo, hi
    raw = metadata.get(SIM_METADATA, {}).get("drape_start_stamp_ns")
    if raw is None:
        raise RecordingError(
            f"{source}: phase={phase} needs the {SIM_METADATA} metadata (drape_start_stamp_ns); "
            "use phase=all with start/stop stamps instead"
        )
    drape = int(raw)
    if drape < 0:  # simulated without a drape: all frames undraped
        if phase == "draped":
            raise RecordingError(f"{source}: phase=draped but the recording has no draped frames")
        return lo, hi
    if phase == "undraped":
        return lo, drape if hi is None else min(hi, drape)
    return (drape if lo is None else max(lo, drape)), hi


def _views_from_recording(reader: RecordingReader) -> tuple[list[View], str]:
    calib = reader.camera_calib()
    if calib.T_right_left is None:
        raise RecordingError(
            f"{reader.path}: no transform between {calib.left.frame_id} and "
            f"{calib.right.frame_id} on /tf_static (stereo calibration needed)"
        )
    rig = StereoRig(
        Intrinsics.from_K(calib.left.K, calib.left.width, calib.left.height),
        Intrinsics.from_K(calib.right.K, calib.right.width, calib.right.height),
        calib.T_right_left,
    )
    return stereo_views(rig), calib.left.frame_id


def _pick_robot(reader: RecordingReader, wanted: str | None) -> str:
    robots = reader.robots
    if not robots:
        raise RecordingError(f"{reader.path}: no /<robot>/joint_states topic")
    if wanted is None:
        if len(robots) > 1:
            log.warning(
                "%s has robots %s; using %s (set robot=...)", reader.path, robots, robots[0]
            )
        return robots[0]
    if wanted not in robots:
        raise RecordingError(f"{reader.path}: robot={wanted} not found (robots: {robots})")
    return wanted


def _candidates(
    reader: RecordingReader, robot: str, window: tuple[int | None, int | None]
) -> tuple[list[Configuration], list[str]]:
    """Frames (stereo pair and joints present) inside the stamp window, and what was skipped."""
    lo, hi = window
    found = []
    for f in reader.frames(decode=False):
        if (lo is None or f.stamp_ns >= lo) and (hi is None or f.stamp_ns < hi):
            found.append(Configuration(f.index, f.stamp_ns, f.joints[robot].copy()))
    st = reader.stats
    dropped = []
    if st.skipped_no_joint_state:
        dropped.append(f"{st.skipped_no_joint_state} frames: no joint state within tolerance")
    if st.skipped_unpaired:
        dropped.append(f"{st.skipped_unpaired} frames: no matching right image")
    if st.skipped_corrupt:
        dropped.append(f"{st.skipped_corrupt} frames: unreadable")
    return found, dropped


def _segment_fn(segmentor: Any) -> Callable[[np.ndarray, np.ndarray | None], np.ndarray]:
    def segment(images: np.ndarray, prior: np.ndarray | None) -> np.ndarray:
        return segmentor.predict(images, prior) > segmentor.meta.threshold

    return segment


#: IoU by which another robot's joints must beat the registered robot's at the estimate before
#: the estimate is taken to sit on that robot's pixels
CLAIM_MARGIN = 0.05


class _Fitter:
    """Swarm → multi-start SDR → refinement of one robot (joints ``q`` [C, D] of the used
    configurations) on given masks per view ``[C, H, W]``. With ``margins`` (px per view; several
    robots in the masks) the estimate is refined once more on the mask pixels within that
    distance of its own silhouette, and those masks are returned instead of the given ones.
    A fit with the stereo disparity term (``sdr.disparity_weight``) is done again without it
    when it fails the fit check (or always: ``disparity_retry``), and the one with the higher
    mean IoU kept (noted in :attr:`notes` when that is the plain one)."""

    def __init__(
        self,
        cfg: RegisterConfig,
        views: list[View],
        coarse: RobotModel,
        fine: RobotModel,
        q: torch.Tensor,
        margins: list[float] | None,
    ) -> None:
        self.cfg, self.views, self.coarse, self.fine, self.q = cfg, views, coarse, fine, q
        self.verts = fine.posed_vertices(q)
        self.margins = margins
        self.notes: list[str] = []  # what the fits did besides fitting, for the warnings
        # several robots: the term-free first fit of the current call, shared by the fit with
        # the disparity term and its retry without it (same masks, starts and settings)
        self._first: tuple[SDRConfig, RegistrationResult] | None = None

    def silhouettes(
        self, T_cam_base: np.ndarray, q: torch.Tensor | None = None
    ) -> list[np.ndarray]:
        """Hard silhouettes per view ``[C, H, W]`` bool at ``T_cam_base`` (joints ``q``, default
        the registered robot's)."""
        verts = self.verts if q is None else self.fine.posed_vertices(q)
        return [render_prior(verts, self.fine.faces, v, T_cam_base) > 0.5 for v in self.views]

    def __call__(
        self, masks: list[np.ndarray], seconds: dict[str, float]
    ) -> tuple[RegistrationResult, list[np.ndarray], Any]:
        cfg = self.cfg
        self._first = None
        t1 = time.perf_counter()
        roi_views, roi_masks = crop_to_masks(self.views, masks, cfg.roi_margin)
        log.info("region of interest: %s", [(v.name, v.width, v.height) for v in roi_views])
        n_cso = max(1, min(cfg.cso_configs, len(self.q)))
        found_cso = cso(
            self.coarse.posed_vertices(self.q[:n_cso]),
            self.coarse.faces,
            roi_views,
            [m[:n_cso] for m in roi_masks],
            cfg.cso,
        )
        seconds["cso"] = seconds.get("cso", 0.0) + time.perf_counter() - t1
        t1 = time.perf_counter()
        starts = [c.T_cam_base for c in found_cso.candidates]
        res, fitted = self._fit(roi_views, roi_masks, starts, masks, cfg.sdr)
        if cfg.sdr.disparity_weight > 0 and (
            cfg.disparity_retry == "always" or not _passes(res, cfg.min_iou)
        ):
            # the term holds the distance of blurry masks, but masks whose two views disagree
            # (a robot segmented in one image only, clutter or a passer-by on one side) give
            # it a wrong disparity to hold: the plain cost decides then
            no_term = replace(cfg.sdr, disparity_weight=0.0)
            plain, plain_masks = self._fit(roi_views, roi_masks, starts, masks, no_term)
            if plain.reason != "diverged" and (
                res.reason == "diverged" or plain.mean_iou > res.mean_iou
            ):
                self.notes.append(
                    f"the fit with the stereo disparity term ended at mean IoU "
                    f"{res.mean_iou:.3f} ({res.reason}); fitted again without it: "
                    f"{plain.mean_iou:.3f}, kept"
                )
                res, fitted = plain, plain_masks
        seconds["sdr"] = seconds.get("sdr", 0.0) + time.perf_counter() - t1
        return res, fitted, found_cso

    def _fit(
        self,
        roi_views: list[View],
        roi_masks: list[np.ndarray],
        starts: list[np.ndarray],
        masks: list[np.ndarray],
        sdr_cfg: SDRConfig,
    ) -> tuple[RegistrationResult, list[np.ndarray]]:
        """SDR from ``starts`` with ``sdr_cfg`` (:meth:`_sdr`), refitted on the estimate's own
        pixels when other robots are in the masks; the result and the masks it was fitted on
        (full size, per view ``[C, H, W]``) — what :func:`register`'s fit check judges."""
        if self.margins is None:
            return self._sdr(roi_views, roi_masks, starts, sdr_cfg), masks
        # the centroid disparity of masks holding other robots or clutter is not this robot's:
        # the first fit goes without the term, the refit on the estimate's own pixels with it
        plain = replace(sdr_cfg, disparity_weight=0.0)
        if self._first is None or self._first[0] != plain:
            self._first = (plain, self._sdr(roi_views, roi_masks, starts, plain))
        res = self._first[1]
        if res.reason != "diverged":
            return refit_on_own_pixels(
                self.verts, self.fine.faces, self.views, masks, res,
                self.silhouettes(res.T_cam_base), self.margins, replace(self.cfg, sdr=sdr_cfg),
            )
        return res, masks

    def _sdr(
        self,
        roi_views: list[View],
        roi_masks: list[np.ndarray],
        starts: list[np.ndarray],
        sdr_cfg: SDRConfig,
    ) -> RegistrationResult:
        """Multi-start SDR at ``coarse_width`` from ``starts`` (T_cam_base 4×4), then refined at
        ``width`` when the two differ."""
        cfg, faces = self.cfg, self.fine.faces
        coarse_views = views_for_width(roi_views, cfg.coarse_width or cfg.width)
        sdr_views = views_for_width(roi_views, cfg.width)
        res = sdr_multistart(
            self.verts,
            faces,
            coarse_views,
            roi_masks,
            starts,
            sdr_cfg,
            screen_iterations=cfg.screen_iterations,
        )
        if coarse_views[0].width != sdr_views[0].width:
            refined = sdr(self.verts, faces, sdr_views, roi_masks, res.T_cam_base, sdr_cfg)
            if refined.reason != "diverged":
                res = refined
        return res


def _passes(res: RegistrationResult, min_iou: float) -> bool:
    """The fit check of :func:`register`: not diverged, mean residual IoU ≥ ``min_iou``."""
    return res.reason != "diverged" and res.mean_iou >= min_iou


def pooled_iou(silhouettes: list[np.ndarray], masks: list[np.ndarray]) -> float:
    """Mean over views of the IoU pooled over configurations (``[C, H, W]`` bool per view)."""
    values = []
    for s, m in zip(silhouettes, masks, strict=True):
        union = np.count_nonzero(s | m)
        values.append(np.count_nonzero(s & m) / union if union else 1.0)
    return float(np.mean(values))


def _other_robots_joints(
    path: Path, robot: str, robot_model: RobotModel, used: list[Configuration]
) -> dict[str, torch.Tensor]:
    """Joints ``[C, D]`` of every other robot of the recording at the used frames, for the robots
    with the registered robot's joint names and a joint state at each of those frames."""
    with RecordingReader(path, on_error="skip") as probe:
        names = [r for r in probe.robots if r != robot]
        joints = probe.joint_names()
    out: dict[str, torch.Tensor] = {}
    for name in names:
        if sorted(joints.get(name, [])) != sorted(robot_model.joint_names):
            continue
        with RecordingReader(
            path, robots=[name], joint_order={name: robot_model.joint_names}, on_error="skip"
        ) as reader:
            by_index = {f.index: f.joints[name] for f in reader.frames(decode=False)}
        if all(c.index in by_index for c in used):
            rows = np.stack([by_index[c.index] for c in used])
            out[name] = torch.as_tensor(rows, dtype=robot_model.dtype)
    return out


def _claimed_by(
    fit: _Fitter,
    T_cam_base: np.ndarray,
    masks: list[np.ndarray],
    other_q: dict[str, torch.Tensor],
    seconds: dict[str, float],
) -> tuple[str, float, float, np.ndarray] | None:
    """``(robot, own IoU, its IoU, its pose)`` when another robot's joints, registered on
    ``masks`` (the pixels near the estimate) as the estimate was (swarm, multi-start SDR), match
    them better (by :data:`CLAIM_MARGIN`) than the registered robot's: the estimate then sits
    on that robot's pixels. None otherwise. A swarm, not SDR from the estimate: robots of one
    model whose joints differ fit each other's silhouettes with the base turned (measured: a
    draped robot's estimate on the other robot's blob, 157° off about the base z axis, from
    where SDR with that robot's joints reached IoU 0.44 against the estimate's 0.49). Its time
    goes to ``seconds["claim_check"]``."""
    t0 = time.perf_counter()
    own = pooled_iou(fit.silhouettes(T_cam_base), masks)
    best: tuple[str, float, float, np.ndarray] | None = None
    for name, q in other_q.items():
        res, _, _ = _Fitter(fit.cfg, fit.views, fit.coarse, fit.fine, q, None)(masks, {})
        if res.reason == "diverged":
            continue
        theirs = pooled_iou(fit.silhouettes(res.T_cam_base, q), masks)
        log.info("%s's joints registered on the estimate's pixels: IoU %.3f (the estimate's "
                 "%.3f)", name, theirs, own)
        if theirs > own + CLAIM_MARGIN and (best is None or theirs > best[2]):
            best = (name, own, theirs, res.T_cam_base)
    seconds["claim_check"] = seconds.get("claim_check", 0.0) + time.perf_counter() - t0
    return best


def register(
    recording: str | Path,
    robot_model: RobotModel,
    *,
    segmentor: Any | None = None,
    masks: MaskSource | None = None,
    config: RegisterConfig | None = None,
    frames: Collection[int] | None = None,
    links: Sequence[str] | None = None,
) -> Registration:
    """Register ``robot_model`` in the stereo camera of ``recording``.

    Segmentations come from ``masks`` (given by the caller) or from ``segmentor`` (an
    :class:`~roboseg.segmentor.OnnxSegmentor`; a 4-channel model gets a zero prior first).
    Method ``sdr``: CSO then multi-start SDR; ``sdr_prior`` continues with SDR with the
    in-context prior (needs ``segmentor``; only meaningful for a 4-channel model).
    ``frames``: recording frame indices the caller can segment (None: any); ``links``: render
    and compare only these links (e.g. those that moved, when the masks come from motion:
    the others are part of the background); None: every link.
    """
    cfg = config or RegisterConfig()
    if (segmentor is None) == (masks is None):
        raise CameraError("register needs exactly one of a segmentation model or given masks")
    if cfg.method == "sdr_prior" and segmentor is None:
        raise CameraError("method=sdr_prior needs a segmentation model (model=PATH)")
    warnings: list[str] = []
    if cfg.method == "sdr_prior" and getattr(segmentor, "in_channels", 4) != 4:
        warnings.append("the model has 3 input channels: the prior is ignored by sdr_prior")
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    path = Path(recording)
    with RecordingReader(path, on_error="skip") as probe:
        robot = _pick_robot(probe, cfg.robot)
        robots_in_masks = probe.robots
    with RecordingReader(
        path, robots=[robot], joint_order={robot: robot_model.joint_names}, on_error="skip"
    ) as reader:
        names = reader.joint_names()[robot]
        if sorted(names) != sorted(robot_model.joint_names):
            raise RobotModelError(
                f"{path}: joints of {robot} {names} do not match the URDF {robot_model.joint_names}"
            )
        views, camera_frame = _views_from_recording(reader)
        window = phase_window(reader.metadata(), cfg.phase, cfg.start_ns, cfg.stop_ns, str(path))
        found, dropped = _candidates(reader, robot, window)
        if frames is not None and found:
            wanted = set(frames)
            kept = [c for c in found if c.index in wanted]
            if not kept:
                raise RecordingError(
                    f"{path}: the segmentation covers none of the {len(found)} frames in "
                    f"phase={cfg.phase} window {window}"
                )
            found = kept
        if not found:
            raise RecordingError(
                f"{path}: no usable stereo frame with joint states in phase={cfg.phase} "
                f"window {window} ({'; '.join(dropped) or 'no frames there'})"
            )
        scale = (robot_model.upper - robot_model.lower).double().numpy()
        order = spread_configurations(np.stack([c.joints for c in found]), len(found), scale)
        segment = _segment_fn(segmentor) if segmentor is not None else None
        used, imgs, msks = [], [[], []], [[], []]
        n_pixels = [v.width * v.height for v in views]
        for k in order:
            if len(used) == cfg.configs:
                break
            c = found[k]
            frame = next(reader.frames(c.index, c.index + 1))
            if segment is not None:
                pair = segment(np.stack([frame.left, frame.right]), None)
                pair = (pair[0], pair[1])
            else:
                pair = masks(frame)  # type: ignore[misc]
            fractions = [
                float(np.count_nonzero(m)) / n for m, n in zip(pair, n_pixels, strict=True)
            ]
            if min(fractions) < cfg.min_mask_fraction:
                side = "left" if fractions[0] < fractions[1] else "right"
                dropped.append(
                    f"frame {c.index} at {c.stamp_ns} ns: {side} mask covers "
                    f"{100 * min(fractions):.2f} % of the image (robot not visible or unsegmented)"
                )
                continue
            used.append(c)
            for i, (img, m) in enumerate(zip((frame.left, frame.right), pair, strict=True)):
                imgs[i].append(img)
                msks[i].append(np.asarray(m, dtype=bool))
    if not used:
        raise CameraError(
            f"{path}: every candidate frame has an empty mask; nothing to register "
            f"({len(dropped)} problems: {dropped[-1] if dropped else ''})"
        )
    if len(used) < cfg.configs:
        warnings.append(f"only {len(used)} of {cfg.configs} configurations usable")
    images = [np.stack(x) for x in imgs]
    mask_stacks = [np.stack(x) for x in msks]
    seconds["read_segment"] = time.perf_counter() - t0
    log.info("registering on %d configurations of %s (%s)", len(used), robot, path.name)

    q = torch.as_tensor(np.stack([c.joints for c in used]), dtype=robot_model.dtype)
    shapes = robot_model if links is None else robot_model.with_links(links)
    if links is not None:
        log.info("rendering and comparing links %s only", list(links))
    coarse = shapes.decimated(cfg.cso_reduction) if cfg.cso_reduction > 0 else shapes
    fine = shapes.decimated(cfg.sdr_reduction) if cfg.sdr_reduction > 0 else shapes
    others = len(robots_in_masks) > 1 and cfg.other_robots_margin > 0
    trim = others or (cfg.trim_masks and cfg.other_robots_margin > 0)
    margins = [cfg.other_robots_margin * v.width for v in views]
    fit = _Fitter(cfg, views, coarse, fine, q, margins if trim else None)
    verts = fit.verts
    full = mask_stacks
    res_sdr, mask_stacks, found_cso = fit(full, seconds)
    if others and res_sdr.reason != "diverged":
        other_q = _other_robots_joints(path, robot, robot_model, used)
        claimed = _claimed_by(fit, res_sdr.T_cam_base, mask_stacks, other_q, seconds)
        if claimed is not None:
            name, own_iou, other_iou, T_other = claimed
            warnings.append(
                f"the first fit sat on {name}'s pixels (IoU with {name}'s joints {other_iou:.3f} "
                f"> {own_iou:.3f} with {robot}'s); fitted again without them"
            )
            without = [
                m & ~near_silhouettes(np.ones_like(m), s, r)
                for m, s, r in zip(
                    full, fit.silhouettes(T_other, other_q[name]), margins, strict=True
                )
            ]
            if all(m.any() for m in without):
                res_sdr, mask_stacks, found_cso = fit(without, seconds)
                again = _claimed_by(fit, res_sdr.T_cam_base, mask_stacks, other_q, seconds)
                if again is not None:
                    warnings.append(
                        f"poor fit: the estimate of {robot} is explained better by "
                        f"{again[0]}'s joints (IoU {again[2]:.3f} > {again[1]:.3f})"
                    )
            else:
                warnings.append(f"poor fit: no mask pixels left for {robot} besides {name}'s")
    warnings.extend(fit.notes)
    res, prior = res_sdr, None
    if cfg.method == "sdr_prior":
        t1 = time.perf_counter()
        # the rounds optimise as SDR did (boundary offsets, disparity term, lr)
        prior_cfg = replace(cfg.prior, sdr=cfg.sdr, width=cfg.width, roi_margin=cfg.roi_margin)
        segment_prior = segment
        if trim:

            def segment_prior(imgs: np.ndarray, prior_render: np.ndarray) -> np.ndarray:
                r = cfg.other_robots_margin * imgs.shape[2]
                return near_silhouettes(segment(imgs, prior_render), prior_render > 0.5, r)

        prior = sdr_with_prior(
            verts,
            fine.faces,
            views,
            images,
            segment_prior,  # type: ignore[arg-type]
            res_sdr.T_cam_base,
            prior_cfg,  # type: ignore[arg-type]
        )
        res = prior.result
        # masks segmented with the estimate's own prior can echo it, so the estimate must also
        # explain the prior-free segmentation that SDR fitted
        free_iou = pooled_iou(fit.silhouettes(res.T_cam_base), mask_stacks)
        if free_iou < cfg.min_iou:
            warnings.append(
                f"poor fit: the SDR-with-prior estimate overlaps the prior-free segmentation "
                f"with IoU {free_iou:.3f} < {cfg.min_iou} (its IoU against masks segmented "
                "with its own prior can echo the prior)"
            )
        mask_stacks = prior.masks
        seconds["sdr_prior"] = time.perf_counter() - t1
    seconds["total"] = time.perf_counter() - t0
    if res.reason == "diverged":
        warnings.append("SDR diverged (robot left the images, non-finite cost or IoU collapse)")
    mean_iou = res.mean_iou
    if mean_iou < cfg.min_iou:
        warnings.append(f"poor fit: mean IoU {mean_iou:.3f} < {cfg.min_iou}")
    for c, row in zip(used, res.per_frame_iou, strict=False):
        if float(row.min()) < cfg.min_iou:
            warnings.append(f"frame {c.index}: IoU {row.round(3).tolist()} (left, right)")
    if len(robots_in_masks) > 1:
        warnings.append(
            f"recording has robots {robots_in_masks}: masks contain all of them; "
            + (
                f"fitted {robot} on the mask pixels within {margins[0]:.0f} px of its estimate"
                if others
                else f"{robot} was fitted against every robot's pixels (other_robots_margin=0)"
            )
        )
    for w in warnings:
        log.warning("%s", w)
    return Registration(
        T_cam_base=res.T_cam_base,
        method=cfg.method,
        result=res,
        sdr=res_sdr,
        prior=prior,
        configurations=used,
        camera_frame=camera_frame,
        base_frame=f"{robot}/{robot_model.root_link}",
        robot=robot,
        robots_in_masks=robots_in_masks,
        joint_names=list(robot_model.joint_names),
        dropped=dropped,
        warnings=warnings,
        views=views,
        images=images,
        masks=mask_stacks,
        cso_fitness=found_cso.best.fitness,
        cso_runs=found_cso.runs,
        seconds=seconds,
        links=None if links is None else list(links),
    )


def estimate_silhouettes(reg: Registration, robot_model: RobotModel) -> list[np.ndarray]:
    """Per view, hard silhouettes ``[C, H, W]`` bool of the robot at the estimate, at the image
    resolution, for the configurations used (e.g. for overlays)."""
    from roboseg.registration.sdr_prior import render_prior

    q = torch.as_tensor(np.stack([c.joints for c in reg.configurations]), dtype=robot_model.dtype)
    verts = robot_model.posed_vertices(q)
    return [render_prior(verts, robot_model.faces, v, reg.T_cam_base) > 0.5 for v in reg.views]
