"""Synthetic breathing patient with AprilTags seen by a stereo camera, and a closed-loop drill.

* :func:`breathing_waveform` / :class:`BreathingTruth`: the true periodic breathing motion
  (known ``ω0``, per-axis amplitudes as half peak-to-peak, like the Table S1 definition).
* :class:`TagScene` + :func:`render_stereo`: planar 36h11 tags (edge of the black square, default
  3 cm) glued to a textured patient surface, each displaced by the breathing motion, rendered into
  both images by homography warping with 4× supersampling (pixel-centre convention exact), plus
  Gaussian sensor noise.
* :func:`simulate_compensation`: tissue moving with breathing, a tip driven by the paper's
  compensated velocity command (breathing model fitted online to noisy tracked positions),
  either as a point mass or through a robot Jacobian; reports drill-tip motion relative to tissue.

Frames: the patient/robot base frame ("base", metres) with ``T_cam_base`` to the left optical
frame; anatomical axes ML/CC/AP are base x/y/z.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from roboseg.camera import Intrinsics, StereoRig, look_at
from roboseg.errors import RobosegError
from roboseg.recording.topics import camera_info_topic, image_topic
from roboseg.recording.writer import RecordingWriter
from roboseg.tracking.breathing import BreathingModel
from roboseg.tracking.control import (
    BASE_Z,
    alignment_angular_velocity,
    compensated_linear_velocity,
    geometric_jacobian,
    min_norm_joint_velocities,
)
from roboseg.tracking.tags import TAG_DICTIONARY

log = logging.getLogger(__name__)

AXES = ("ML", "CC", "AP")


@dataclass(frozen=True)
class BreathingTruth:
    """True breathing: ``d(t) = amplitudes · w(t)`` (m, base frame) with a unit waveform ``w``.

    ``w(t) = Σ_n h_n cos(n ω0 t + φ_n)`` rescaled to a half peak-to-peak of exactly 1, so
    ``|amplitudes|`` are the per-axis amplitudes as the breathing model defines them.
    """

    omega0: float = 2 * np.pi * 0.25  # rad/s (15 breaths/min)
    amplitudes: tuple[float, float, float] = (-0.14e-3, -1.29e-3, 4.54e-3)  # ML, CC, AP (m)
    harmonics: tuple[float, ...] = (1.0, 0.25, 0.08)
    phases: tuple[float, ...] = (0.0, 0.6, -0.4)

    def _raw(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return sum(
            h * np.cos((n + 1) * self.omega0 * t + p)
            for n, (h, p) in enumerate(zip(self.harmonics, self.phases, strict=True))
        )

    @property
    def _scale(self) -> tuple[float, float]:
        ts = np.linspace(0.0, 2 * np.pi / self.omega0, 4096, endpoint=False)
        w = self._raw(ts)
        return 0.5 * (w.max() + w.min()), 0.5 * (w.max() - w.min())

    def waveform(self, t: np.ndarray | float) -> np.ndarray:
        """Unit waveform ``w(t)`` (zero mid-range, half peak-to-peak 1)."""
        mid, half = self._scale
        return (self._raw(t) - mid) / half

    def displacement(self, t: np.ndarray | float) -> np.ndarray:
        """``[N, 3]`` (or ``[3]``) breathing displacement in metres, base frame."""
        w = np.asarray(self.waveform(t))
        return w[..., None] * np.asarray(self.amplitudes)

    def velocity(self, t: np.ndarray | float, dt: float = 1e-5) -> np.ndarray:
        """``[N, 3]`` breathing velocity (m/s) by central differences."""
        t = np.asarray(t, dtype=np.float64)
        return (self.displacement(t + dt) - self.displacement(t - dt)) / (2 * dt)


@dataclass(frozen=True)
class TagSpec:
    """One tag glued to the patient: id, rest centre (m, base frame), rotation ``R_base_tag``
    (tag x right, y up on the printed tag, z = outward normal), breathing gain (motion scale)."""

    tag_id: int
    centre_base: tuple[float, float, float]
    R_base_tag: np.ndarray = field(default_factory=lambda: np.eye(3))
    gain: float = 1.0


def tag_texture(tag_id: int, pixels_per_cell: int = 16) -> np.ndarray:
    """Grey texture of a 36h11 tag with a 1-cell white margin: ``10 × 10`` cells, uint8."""
    d = cv2.aruco.getPredefinedDictionary(TAG_DICTIONARY)
    marker = cv2.aruco.generateImageMarker(d, tag_id, 8 * pixels_per_cell)
    return cv2.copyMakeBorder(
        marker, *(4 * [pixels_per_cell]), borderType=cv2.BORDER_CONSTANT, value=255
    )


def _rigid_axes(R_base_tag: np.ndarray, centre_base: np.ndarray, T_cam_base: np.ndarray):
    R_cam_tag = T_cam_base[:3, :3] @ R_base_tag
    t_cam = T_cam_base[:3, :3] @ centre_base + T_cam_base[:3, 3]
    return R_cam_tag, t_cam


def tag_corners_image(
    K: np.ndarray,
    T_cam_base: np.ndarray,
    R_base_tag: np.ndarray,
    centre_base: np.ndarray,
    size: float,
) -> np.ndarray:
    """Projected corners ``[4, 2]`` (pixels) of the tag's black square, OpenCV corner order
    (top-left, top-right, bottom-right, bottom-left of the upright tag; tag y is up)."""
    h = size / 2
    local = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    R, t = _rigid_axes(R_base_tag, centre_base, T_cam_base)
    x = (local @ R.T + t) @ np.asarray(K).T
    return x[:, :2] / x[:, 2:3]


def render_tag(
    image: np.ndarray,
    K: np.ndarray,
    T_cam_base: np.ndarray,
    R_base_tag: np.ndarray,
    centre_base: np.ndarray,
    size: float,
    texture: np.ndarray,
    supersample: int = 4,
) -> None:
    """Composite a tag (black-square edge ``size`` m, texture from :func:`tag_texture`) in place.

    The tag plane is warped by the homography ``S K [r1 r2 t] A`` (``A``: texture pixel → tag
    metres, ``S``: image pixel → supersampled patch pixel), then area-averaged down, so each output
    pixel is the mean over its footprint centred on its integer coordinate.
    """
    s = int(supersample)
    cells = 10
    ppc = texture.shape[0] / cells
    cell = size / 8
    R, t = _rigid_axes(R_base_tag, np.asarray(centre_base, np.float64), T_cam_base)
    if t[2] <= 0:
        return
    half = 5 * cell
    outline = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
    x = (outline @ R.T + t) @ np.asarray(K).T
    if np.any(x[:, 2] <= 0):
        return
    uv = x[:, :2] / x[:, 2:3]
    H_img, W_img = image.shape[:2]
    x0 = max(int(np.floor(uv[:, 0].min())) - 2, 0)
    y0 = max(int(np.floor(uv[:, 1].min())) - 2, 0)
    x1 = min(int(np.ceil(uv[:, 0].max())) + 3, W_img)
    y1 = min(int(np.ceil(uv[:, 1].max())) + 3, H_img)
    if x1 <= x0 or y1 <= y0:
        return
    # texture pixel centre (u, v) → tag plane (x, y): x right, y up (z out of the tag, as OpenCV)
    A = np.array(
        [
            [cell / ppc, 0, 0.5 * cell / ppc - half],
            [0, -cell / ppc, half - 0.5 * cell / ppc],
            [0, 0, 1],
        ]
    )
    S = np.array([[s, 0, s * (0.5 - x0) - 0.5], [0, s, s * (0.5 - y0) - 0.5], [0, 0, 1]])
    H = S @ np.asarray(K) @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
    size_ss = ((x1 - x0) * s, (y1 - y0) * s)
    tex = cv2.warpPerspective(texture.astype(np.float32), H, size_ss, flags=cv2.INTER_LINEAR)
    alpha = cv2.warpPerspective(
        np.ones_like(texture, np.float32), H, size_ss, flags=cv2.INTER_LINEAR
    )
    tex = cv2.resize(tex, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    alpha = cv2.resize(alpha, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    patch = image[y0:y1, x0:x1].astype(np.float32)
    if patch.ndim == 3:
        tex, alpha = tex[..., None], alpha[..., None]
    image[y0:y1, x0:x1] = np.clip(patch * (1 - alpha) + tex * alpha, 0, 255).astype(image.dtype)


def skin_texture(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth skin-toned RGB background (uint8 ``H×W×3``): low-frequency shading and blotches."""
    shape = (max(height // 48, 2), max(width // 48, 2))
    shade = cv2.resize(
        rng.normal(0.0, 1.0, shape).astype(np.float32),
        (width, height),
        interpolation=cv2.INTER_CUBIC,
    )
    blotch = cv2.resize(
        rng.normal(0.0, 1.0, shape).astype(np.float32),
        (width, height),
        interpolation=cv2.INTER_CUBIC,
    )
    base = np.array([205.0, 160.0, 140.0], np.float32)
    tint = np.array([0.0, -8.0, -6.0], np.float32)
    img = base * (1.0 + 0.06 * shade[..., None]) + tint * blotch[..., None]
    return np.clip(img, 0, 255).astype(np.uint8)


def add_sensor_noise(image: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """``image`` (uint8) plus rounded Gaussian noise of ``std`` grey levels, saturated.

    Uses OpenCV's generator (fast), seeded from ``rng`` so results stay deterministic.
    """
    noise = np.empty((image.shape[0], image.size // image.shape[0]), np.int16)  # one channel
    cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
    cv2.randn(noise, 0.0, float(std))
    out = image.astype(np.int16)
    out += noise.reshape(image.shape)
    np.clip(out, 0, 255, out=out)
    return out.astype(np.uint8)


@dataclass
class TagScene:
    """Patient tags in the base frame, moving with :class:`BreathingTruth`, seen by a stereo rig.

    ``K_left``/``K_right`` (3×3, full image), ``T_right_left``, ``T_cam_base`` (left camera),
    image size ``width × height``. ``noise_std`` is the sensor noise in grey levels.
    """

    K_left: np.ndarray
    K_right: np.ndarray
    T_right_left: np.ndarray
    T_cam_base: np.ndarray
    width: int
    height: int
    tags: Sequence[TagSpec]
    truth: BreathingTruth = field(default_factory=BreathingTruth)
    tag_size: float = 0.03
    noise_std: float = 2.0
    seed: int = 0

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        self._rng = rng
        self._background = skin_texture(self.width, self.height, rng)
        self._textures = {s.tag_id: tag_texture(s.tag_id) for s in self.tags}

    def tag_positions_base(self, t: float) -> dict[int, np.ndarray]:
        """True tag centres (m, base frame) at time ``t`` (s)."""
        d = self.truth.displacement(t)
        return {s.tag_id: np.asarray(s.centre_base) + s.gain * d for s in self.tags}

    def tag_positions_cam(self, t: float) -> dict[int, np.ndarray]:
        """True tag centres (m, left optical frame) at time ``t``."""
        T = self.T_cam_base
        return {i: T[:3, :3] @ p + T[:3, 3] for i, p in self.tag_positions_base(t).items()}

    def render(
        self, t: float, hidden: dict[str, set[int]] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Left and right RGB images (uint8 ``H×W×3``) at time ``t``.

        ``hidden`` maps ``"left"``/``"right"`` to tag ids not drawn in that view (occlusion).
        """
        hidden = hidden or {}
        T_right_base = self.T_right_left @ self.T_cam_base
        views = (("left", self.K_left, self.T_cam_base), ("right", self.K_right, T_right_base))
        out = []
        positions = self.tag_positions_base(t)
        for name, K, T in views:
            img = self._background.copy()
            for spec in self.tags:
                if spec.tag_id in hidden.get(name, set()):
                    continue
                render_tag(
                    img,
                    K,
                    T,
                    spec.R_base_tag,
                    positions[spec.tag_id],
                    self.tag_size,
                    self._textures[spec.tag_id],
                )
            if self.noise_std > 0:
                img = add_sensor_noise(img, self.noise_std, self._rng)
            out.append(img)
        return out[0], out[1]


def rotation_about(axis: Sequence[float], angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` rad about ``axis`` (Rodrigues)."""
    R, _ = cv2.Rodrigues(np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle)
    return R


def default_patient_tags(tilt: float = 0.25) -> list[TagSpec]:
    """Three tags around a drilling site at the base origin (ids 5, 10, 12; ~8–12 cm apart)."""
    return [
        TagSpec(10, (0.0, 0.06, 0.0), rotation_about((1, 0.3, 0), tilt), 1.0),
        TagSpec(5, (0.05, -0.07, 0.01), rotation_about((0.2, 1, 0), -tilt), 0.7),
        TagSpec(12, (-0.06, -0.02, 0.005), rotation_about((1, -1, 0), tilt * 0.6), 0.9),
    ]


# ------------------------------------------------------------------ closed-loop drilling


@dataclass(frozen=True)
class CompensationResult:
    """Closed-loop outcome: time (s), tip and tissue positions (m, base), forces (N), and the
    RMS (m) of the tip-minus-tissue position about its mean over ``t ≥ evaluated_from``: along
    AP (base z, the compensated axis and drilling direction) and as a 3-D norm."""

    t: np.ndarray
    tip: np.ndarray
    tissue: np.ndarray
    forces: np.ndarray
    relative_rms_ap: float
    relative_rms_3d: float
    evaluated_from: float


def simulate_compensation(
    compensate: bool,
    truth: BreathingTruth | None = None,
    duration: float = 40.0,
    dt: float = 0.01,
    camera_rate: float = 30.0,
    tracking_noise: float = 0.15e-3,
    stiffness: float = 3000.0,
    f_desired: float = 15.0,
    k: float = 2.0,
    c: float = 5e-5,
    feed_velocity: float = 0.0,
    horizon: float = 15.0,
    seed: int = 0,
    robot_fk: Callable[[np.ndarray], np.ndarray] | None = None,
    q0: np.ndarray | None = None,
    jacobian_damping: float = 1e-3,
) -> CompensationResult:
    """Drill tip pressing on breathing tissue under the paper's velocity command.

    The tissue entry point moves as ``truth.displacement(t)`` (base frame, AP = base z). The
    tool axis is base z, pointing out of the tissue (so ``R_base_tip = I`` when aligned). The
    contact force is ``f_m = stiffness · max(0, penetration)`` (N/m). Tracked entry-point
    positions (``tracking_noise`` m std, at ``camera_rate`` Hz) feed an online
    :class:`BreathingModel` over ``horizon`` s; once fitted and if ``compensate``, its AP velocity
    is the ``ż(t)`` term. The tip moves by the commanded velocity: directly (point mass) or, with
    ``robot_fk`` (``[B, D] → T_base_tool [B, 4, 4]``) and ``q0``, through ``q̇ = J⁺[v; ω]``
    integrated with forward Euler. The relative motion is evaluated after ``horizon + 5`` s.
    """
    truth = truth or BreathingTruth()
    rng = np.random.default_rng(seed)
    steps = int(round(duration / dt))
    model = BreathingModel(horizon=horizon, refit_interval=0.5)
    surface0 = np.zeros(3)
    if robot_fk is not None:
        if q0 is None:
            raise ValueError("robot_fk needs q0")
        q = np.asarray(q0, np.float64).copy()
        T0 = robot_fk(q[None])[0]
        offset = T0[:3, 3] - surface0  # tissue sits at the tool's initial position
        R_tip = T0[:3, :3]
    else:
        offset = np.zeros(3)
        R_tip = np.eye(3)
    tip = offset + surface0  # in touch with the surface, no force yet
    next_obs = 0.0
    ts, tips, tissues, forces = [], [], [], []
    for i in range(steps):
        t = i * dt
        tissue = offset + surface0 + truth.displacement(t)
        if t >= next_obs:
            obs = tissue + rng.normal(0.0, tracking_noise, 3)
            model.update(t, obs)
            next_obs += 1.0 / camera_rate
        tool_axis = R_tip[:, 2]
        penetration = float((tissue - tip) @ tool_axis)
        f_m = stiffness * max(penetration, 0.0)
        entry_tip = R_tip.T @ (tissue - tip)
        z_dot = 0.0
        if compensate:
            vel = model.velocity(t)
            z_dot = float(vel[2]) if vel is not None else 0.0
        v = compensated_linear_velocity(
            R_tip, entry_tip, feed_velocity, f_desired, f_m, k, c, z_dot, BASE_Z
        )
        if robot_fk is None:
            tip = tip + v * dt
        else:
            w = alignment_angular_velocity(R_tip[:, 2], BASE_Z, gain=k)
            J = geometric_jacobian(robot_fk, q)
            q = q + min_norm_joint_velocities(J, np.concatenate([v, w]), jacobian_damping) * dt
            T = robot_fk(q[None])[0]
            tip, R_tip = T[:3, 3], T[:3, :3]
        ts.append(t)
        tips.append(tip.copy())
        tissues.append(tissue)
        forces.append(f_m)
    t_arr = np.asarray(ts)
    tip_arr, tissue_arr = np.asarray(tips), np.asarray(tissues)
    start = horizon + 5.0
    sel = t_arr >= start
    rel = tip_arr[sel] - tissue_arr[sel]
    rel = rel - rel.mean(axis=0)
    rms_3d = float(np.sqrt(np.mean(np.sum(rel * rel, axis=1))))
    rms_ap = float(np.sqrt(np.mean(rel[:, 2] ** 2)))
    log.info(
        "compensation=%s: tip-tissue RMS %.3f mm (AP), %.3f mm (3-D)",
        compensate,
        rms_ap * 1e3,
        rms_3d * 1e3,
    )
    return CompensationResult(t_arr, tip_arr, tissue_arr, np.asarray(forces), rms_ap, rms_3d, start)


# ------------------------------------------------------------------ breathing recording

#: MCAP metadata record holding the true breathing parameters of a simulated recording.
TRUTH_METADATA = "roboseg_truth"
LEFT_FRAME = "camera_left_optical_frame"
RIGHT_FRAME = "camera_right_optical_frame"
#: tf frame of the patient/robot base in breathing recordings (base x/y/z = ML/CC/AP).
BASE_FRAME = "robot_0/base"
#: Horizontal field of view of the ZED 2i with its 4 mm lens option (degrees).
ZED2I_4MM_HFOV_DEG = 72.0


def zed2i_4mm_rig(width: int = 1920, height: int = 1080, baseline: float = 0.12) -> StereoRig:
    """Rectified ZED 2i-like pair with the 4 mm lens (HFOV 72°: fx ≈ 1321 px at 1920 wide)."""
    f = 0.5 * width / np.tan(np.radians(ZED2I_4MM_HFOV_DEG) / 2)
    intr = Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
    T = np.eye(4)
    T[0, 3] = -baseline
    return StereoRig(intr, intr, T)


def breathing_scene(
    seed: int = 0,
    rig: StereoRig | None = None,
    distance: float = 1.0,
    truth: BreathingTruth | None = None,
    tag_size: float = 0.03,
    noise_std: float = 2.0,
) -> TagScene:
    """The default breathing scene: three tags around the base origin seen from ``distance`` m,
    obliquely from the patient's side and above (base z = AP is up)."""
    rig = rig or zed2i_4mm_rig()
    direction = np.array([0.3, -0.5, 0.8])
    eye = distance * direction / np.linalg.norm(direction)
    T_cam_base = look_at(eye, np.zeros(3), (0.0, 0.0, 1.0))
    return TagScene(
        rig.left.K,
        rig.right.K,
        np.asarray(rig.T_right_left),
        T_cam_base,
        rig.left.width,
        rig.left.height,
        default_patient_tags(),
        truth or BreathingTruth(),
        tag_size,
        noise_std,
        seed,
    )


def write_breathing_recording(
    path: str | Path,
    seed: int = 0,
    frames: int = 150,
    fps: float = 10.0,
    distance: float = 1.0,
    occluded_fraction: float = 0.1,
    jpeg_quality: int = 95,
) -> Path:
    """Write an MCAP recording of the breathing patient with AprilTags (stereo JPEGs at ``fps``).

    The camera is :func:`zed2i_4mm_rig` (1920×1080; tags need ~25 px or more, so the recording
    keeps this resolution). Tag 12 is hidden in the right image for ``occluded_fraction`` of the
    frames (one contiguous stretch), so it is seen by the left camera only there. ``/tf_static``
    holds ``T_left_base`` (parent :data:`LEFT_FRAME`, child :data:`BASE_FRAME`) and
    ``T_left_right``. The ``roboseg_truth`` metadata record holds ``omega0`` (rad/s), the signed
    amplitudes ``amplitude_ML_mm`` / ``amplitude_CC_mm`` / ``amplitude_AP_mm`` (half peak-to-peak,
    of a tag with gain 1: tag 10), per-tag gains and the expected visibility of tag 12.
    """
    path = Path(path)
    if frames < 1 or fps <= 0:
        raise RobosegError(
            f"breathing recording needs frames >= 1 and fps > 0, got {frames}, {fps}"
        )
    rig = zed2i_4mm_rig()
    scene = breathing_scene(seed, rig, distance)
    rng = np.random.default_rng(seed + 1)
    n_hidden = int(round(occluded_fraction * frames))
    start_hidden = int(rng.integers(0, max(frames - n_hidden, 0) + 1))
    hidden_frames = set(range(start_hidden, start_hidden + n_hidden))
    truth = scene.truth
    amps = dict(zip(AXES, (a * 1e3 for a in truth.amplitudes), strict=True))
    meta = {
        "omega0": repr(truth.omega0),
        **{f"amplitude_{k}_mm": repr(v) for k, v in amps.items()},
        "reference_tag": "10",
        "tag_gains": ",".join(f"{s.tag_id}:{s.gain}" for s in scene.tags),
        "tag_size_m": repr(scene.tag_size),
        "distance_m": repr(distance),
        "visibility_tag_12": repr(1.0 - len(hidden_frames) / frames),
        "axes": "base x=ML, y=CC, z=AP",
    }
    t0_ns = 1_700_000_000_000_000_000
    with RecordingWriter(path, metadata={TRUTH_METADATA: meta}) as writer:
        writer.write_tf_static(
            [
                (LEFT_FRAME, BASE_FRAME, scene.T_cam_base),
                (LEFT_FRAME, RIGHT_FRAME, np.linalg.inv(scene.T_right_left)),
            ],
            t0_ns,
        )
        for i in range(frames):
            stamp = t0_ns + int(round(i / fps * 1e9))
            hidden = {"right": {12}} if i in hidden_frames else None
            left, right = scene.render(i / fps, hidden)
            for side, frame_id, image, intr in (
                ("left", LEFT_FRAME, left, rig.left),
                ("right", RIGHT_FRAME, right, rig.right),
            ):
                writer.write_image(
                    image_topic(side=side), stamp, frame_id, image, "jpeg", jpeg_quality
                )
                writer.write_camera_info(
                    camera_info_topic(side=side), stamp, frame_id, intr.K, intr.width, intr.height
                )
    log.info("wrote breathing recording %s (%d frames at %.1f fps)", path, frames, fps)
    return path
