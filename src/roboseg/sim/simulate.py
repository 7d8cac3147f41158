"""Write one simulated stereo recording of one or two draped robots (the paper's protocol).

Same camera and robot bases for the whole recording: first an undraped phase, then the robots
are draped in place and the undraped motion is replayed (then continued) under the drape. The
recording holds what a real rig writes (stereo JPEGs, camera infos, joint states, the
calibration on ``/tf_static``) plus ground-truth masks per camera (the silhouette of the full
robot model under everything) and a ``roboseg_sim`` metadata record naming the stamp where
draping starts.

World frame = base frame of robot 0 (z up, metres). ``/tf_static`` holds
``T_left_base`` for each robot (parent ``camera_left_optical_frame``, child
``robot_<i>/<root_link>``) and ``T_left_right`` (child ``camera_right_optical_frame``).
"""

from __future__ import annotations

import itertools
import logging
import math
import multiprocessing
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from roboseg.camera import StereoRig, look_at
from roboseg.errors import RobosegError
from roboseg.recording import msgs
from roboseg.recording.topics import camera_info_topic, image_topic, joint_states_topic, mask_topic
from roboseg.recording.writer import RecordingWriter, encode_image, encode_mask
from roboseg.render.raster import rasterize
from roboseg.robot import RobotModel, load_robot
from roboseg.sim.drape import Drape, DrapeParams, sample_drape_params
from roboseg.sim.frame import Surface, ViewLight, composite_view
from roboseg.sim.lighting import Lighting, sample_lighting
from roboseg.sim.occluders import (
    TAPE_COLOURS,
    Capsule,
    Occluder,
    draw_capsules,
    sample_occluders,
    sample_walkers,
)
from roboseg.sim.scene import StaticScene, render_static, sample_scene
from roboseg.sim.shading import NoiseBank, pixel_rays, to_uint8, vertex_normals
from roboseg.sim.trajectory import random_joint_trajectory

log = logging.getLogger(__name__)

LEFT_FRAME = "camera_left_optical_frame"
RIGHT_FRAME = "camera_right_optical_frame"
SIM_METADATA = "roboseg_sim"
#: First stamp of every simulated recording (ns since the epoch, 2023-11-14 22:13:20 UTC).
T0_NS = 1_700_000_000_000_000_000

#: Robot paint (linear RGB): links alternate white and light grey like the LBR Med.
ROBOT_PAINT = ((0.80, 0.80, 0.78), (0.55, 0.56, 0.58))


@dataclass(frozen=True)
class SimConfig:
    """What to simulate. Sizes in pixels, distances in metres, times in seconds."""

    frames: int = 120
    seed: int = 0
    robots: int = 1
    urdf: str | None = None
    width: int = 960
    height: int = 540
    baseline: float = 0.12
    fps: float = 15.0
    undraped_fraction: float = 0.35
    distance: tuple[float, float] = (1.0, 2.5)
    jpeg_quality: int = 90
    workers: int = 1  # processes rendering frames (<= 1: in the calling process)
    #: None: every recording is its own random room (domain randomisation). An int: the
    #: recording is one session of that site (see :func:`site_draws`): the room, the drape kind
    #: and the side of the table the camera stands on come from ``site``; the camera placement,
    #: the drape's folds, people, tools, light and motion come from ``seed``.
    site: int | None = None
    #: with ``site``: how far (deg) a session's camera azimuth strays from the site's side
    site_azimuth_deg: float = 60.0
    #: people walking across the view, each crossing the camera's line of sight during the
    #: undraped phase (their own random stream: recordings without walkers are unchanged)
    walkers: int = 0

    def validate(self) -> None:
        """Raise :class:`RobosegError` naming the first invalid value."""
        if self.frames < 1:
            raise RobosegError(f"frames must be >= 1, got {self.frames}")
        if self.workers < 0:
            raise RobosegError(f"workers must be >= 0, got {self.workers}")
        if self.robots not in (1, 2):
            raise RobosegError(f"robots must be 1 or 2, got {self.robots}")
        if self.width < 16 or self.height < 16:
            raise RobosegError(
                f"camera size must be at least 16x16, got {self.width}x{self.height}"
            )
        if not 0.0 <= self.undraped_fraction < 1.0:
            raise RobosegError(f"undraped_fraction must be in [0, 1), got {self.undraped_fraction}")
        if self.fps <= 0:
            raise RobosegError(f"fps must be > 0, got {self.fps}")
        if self.walkers < 0:
            raise RobosegError(f"walkers must be >= 0, got {self.walkers}")
        if self.site is not None and not 0.0 <= self.site_azimuth_deg <= 180.0:
            raise RobosegError(
                f"site_azimuth_deg must be in [0, 180], got {self.site_azimuth_deg}"
            )
        lo, hi = self.distance
        if not 0.3 <= lo <= hi:
            raise RobosegError(
                f"camera distance range must satisfy 0.3 <= lo <= hi, got {lo}, {hi}"
            )


@dataclass
class SimSummary:
    """What :func:`simulate_recording` wrote."""

    path: Path
    frames: int
    undraped_frames: int
    drape_start_stamp_ns: int | None
    seconds: float
    drape_kinds: list[str] = field(default_factory=list)
    setup_seconds: float = 0.0  # robots, drapes, static room (ray cast), before the first frame


def frame_stamps(n: int, fps: float) -> np.ndarray:
    """Stamps (ns, int64) of ``n`` frames at ``fps`` Hz from :data:`T0_NS`."""
    return T0_NS + np.round(np.arange(n) * 1e9 / fps).astype(np.int64)


def undraped_count(frames: int, fraction: float) -> int:
    """Frames before draping: ``round(fraction·frames)``, at least one undraped and one draped
    frame when there are two or more frames (one frame: draped only)."""
    if frames < 2:
        return 0
    return int(min(max(round(fraction * frames), 1), frames - 1))


def protocol_trajectory(
    lower: np.ndarray,
    upper: np.ndarray,
    frames: int,
    n_undraped: int,
    fps: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Joint positions ``[frames, D]``: a random undraped trajectory, then (draped) its replay,
    then new random motion from where the replay ended (the paper's replayed configurations)."""
    if n_undraped == 0:
        return random_joint_trajectory(lower, upper, frames, fps, rng)
    first = random_joint_trajectory(lower, upper, n_undraped, fps, rng)
    rest = frames - 2 * n_undraped
    parts = [first, first[: frames - n_undraped]]
    if rest > 0:
        parts.append(random_joint_trajectory(lower, upper, rest, fps, rng, start=first[-1]))
    return np.concatenate(parts, axis=0)[:frames]


def yaw_transform(x: float, y: float, yaw: float) -> np.ndarray:
    """``T_world_base`` of a robot base at ``(x, y, 0)`` rotated by ``yaw`` (rad) about z."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, 0.0]
    return T


def sample_camera(
    rng: np.random.Generator,
    bases: list[np.ndarray],
    distance: tuple[float, float],
    azimuth: tuple[float, float] = (-math.pi, math.pi),
) -> tuple[np.ndarray, np.ndarray]:
    """Camera eye and look-at target (world): the target about 0.45 m above the bases' centre,
    the eye ``distance`` away (longer for two robots) at 15–55° elevation, at an azimuth (rad,
    about world z from +x) drawn from ``azimuth`` (default: any)."""
    centre = np.mean([T[:3, 3] for T in bases], axis=0)
    target = centre + np.array([0.1, 0.0, 0.45]) + rng.normal(0.0, 0.08, 3)
    lo, hi = distance
    if len(bases) > 1:
        lo, hi = max(lo, 1.8), max(hi, 2.8)
    d = rng.uniform(lo, hi)
    az = rng.uniform(*azimuth)
    el = rng.uniform(math.radians(15), math.radians(55))
    eye = target + d * np.array(
        [math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)]
    )
    return eye, target


def robot_albedo(robot: RobotModel) -> torch.Tensor:
    """Per-vertex paint ``[V, 3]``: links alternate :data:`ROBOT_PAINT` colours."""
    paint = torch.tensor(ROBOT_PAINT, dtype=torch.float32)
    return paint[robot.vertex_link % len(ROBOT_PAINT)]


def _transform(T: np.ndarray, points: torch.Tensor) -> torch.Tensor:
    """``T [4,4] · points [V,3]`` (float32)."""
    Tt = torch.as_tensor(T, dtype=torch.float32)
    return points @ Tt[:3, :3].T + Tt[:3, 3]


@dataclass
class _Robot:
    """One robot of the scene: full model (labels and appearance), drape mesh, pose, motion."""

    full: RobotModel
    albedo: torch.Tensor
    drape: Drape
    T_world_base: np.ndarray
    q: np.ndarray  # [N, D]
    tape: list[tuple[int, int]]
    closed: bool  # mesh closed and consistently wound: back faces may be culled


@dataclass
class _Camera:
    """One stereo side: intrinsics, pose, static layers and pixel rays."""

    frame_id: str
    side: str
    K: np.ndarray
    T_cam_world: np.ndarray
    static_rgb: np.ndarray
    static_depth: np.ndarray
    rays: torch.Tensor


@dataclass
class _World:
    """Everything fixed for one recording that the frames are rendered from."""

    robots: list[_Robot]
    cameras: list[_Camera]
    scene: StaticScene
    occluders: list[Occluder]
    lighting: Lighting
    eye: np.ndarray
    noise_sigma: float
    noise: NoiseBank
    blur_sigma: float


@dataclass(frozen=True)
class SiteDraws:
    """What one site fixes for all its sessions: the room's random stream, the drape kind's
    random stream (kind, tint, opacity, gloss; a session's folds stay its own) and the
    azimuth (rad) of the side of the table the cameras stand on."""

    scene: np.random.Generator
    drape: np.random.Generator
    azimuth: float


def site_draws(site: int) -> SiteDraws:
    """The random streams of site ``site`` (independent of any session seed)."""
    scene, drape, side = (np.random.default_rng(s) for s in
                          np.random.SeedSequence([int(site), 7_411]).spawn(3))
    return SiteDraws(scene, drape, float(side.uniform(-math.pi, math.pi)))


def _build_robots(
    cfg: SimConfig, rng: np.random.Generator, drape_rng: np.random.Generator | None = None
) -> list[_Robot]:
    """The robots of the scene; their drape parameters come from ``drape_rng`` when given (a
    site's: one draw, the same drape on every robot of the site), else one draw from ``rng``
    per robot; their folds, tape and motion from ``rng``."""
    full = load_robot(cfg.urdf)
    closed = is_closed(full.vertices.double().numpy(), full.faces.numpy(), full.vertex_link.numpy())
    log.info("robot %s: mesh %s", full.name, "closed" if closed else "open (no face culling)")
    site_params = None if drape_rng is None else sample_drape_params(drape_rng)
    out = []
    for i in range(cfg.robots):
        if i == 0:
            T = np.eye(4)
        else:
            T = yaw_transform(
                rng.uniform(1.05, 1.35), rng.uniform(-0.5, 0.5), math.pi + rng.uniform(-0.4, 0.4)
            )
        params = sample_drape_params(rng) if site_params is None else site_params
        drape = Drape.around(full.vertices, full.vertex_link, params, rng)
        lower, upper = full.lower.double().numpy(), full.upper.double().numpy()
        n_u = undraped_count(cfg.frames, cfg.undraped_fraction)
        q = protocol_trajectory(lower, upper, cfg.frames, n_u, cfg.fps, rng)
        faces = drape.faces.numpy()
        picks = rng.integers(0, len(faces), int(rng.integers(2, 6)))
        tape = [(int(faces[k, 0]), int(faces[k, 1])) for k in picks]
        out.append(_Robot(full, robot_albedo(full), drape, T, q, tape, closed))
    return out


def _tape_capsules(robot: _Robot, drape_world: torch.Tensor, eye: np.ndarray) -> list[Capsule]:
    """Strips of tape on the drape, lifted 1.5 cm towards the camera so they sit on top."""
    caps = []
    for k, (a, b) in enumerate(robot.tape):
        pa, pb = drape_world[a].double().numpy(), drape_world[b].double().numpy()
        mid = 0.5 * (pa + pb)
        to_eye = eye - mid
        lift = 0.015 * to_eye / max(np.linalg.norm(to_eye), 1e-9)
        axis = pb - pa
        axis = 0.03 * axis / max(np.linalg.norm(axis), 1e-9)
        colour = TAPE_COLOURS[k % len(TAPE_COLOURS)]
        caps.append(Capsule(mid - axis + lift, mid + axis + lift, 0.012, colour, alpha=0.55))
    return caps


def simulate_recording(cfg: SimConfig, path: str | Path) -> SimSummary:
    """Simulate ``cfg`` and write the MCAP recording ``path`` (atomically); return a summary."""
    cfg.validate()
    t_start = time.perf_counter()
    path = Path(path)
    streams = np.random.SeedSequence(cfg.seed).spawn(7)  # the first six as before walkers
    rng_robot, rng_cam, rng_scene, rng_occ, rng_light, rng_noise, rng_walk = (
        np.random.default_rng(s) for s in streams
    )
    site = None if cfg.site is None else site_draws(cfg.site)
    robots = _build_robots(cfg, rng_robot, None if site is None else site.drape)
    bases = [r.T_world_base for r in robots]
    if site is None:
        eye, target = sample_camera(rng_cam, bases, cfg.distance)
    else:
        spread = math.radians(cfg.site_azimuth_deg)
        eye, target = sample_camera(rng_cam, bases, cfg.distance,
                                    (site.azimuth - spread, site.azimuth + spread))
        rng_scene = site.scene
    up = np.array([0.0, 0.0, 1.0]) + np.append(rng_cam.normal(0.0, 0.04, 2), 0.0)
    T_left_world = np.asarray(look_at(eye, target, up), dtype=np.float64)
    rig = StereoRig.zed2i_like(width=cfg.width, height=cfg.height, baseline=cfg.baseline)
    T_right_left = np.asarray(rig.T_right_left, dtype=np.float64)
    # a site's room is laid out once, for the camera side of the table (its equipment stands
    # beyond the robots, seen from any of its sessions' placements)
    room_view = eye[:2] if site is None else 3.0 * np.array(
        [math.cos(site.azimuth), math.sin(site.azimuth)])
    scene = sample_scene(rng_scene, [T[:3, 3] for T in bases], room_view)
    incision = np.array(
        [
            scene.ellipsoids[0].site[0],
            scene.ellipsoids[0].site[1],
            scene.ellipsoids[0].centre[2] + scene.ellipsoids[0].radii[2],
        ]
    )
    occluders = sample_occluders(rng_occ, eye, target, scene.floor_z, incision)
    n_frames = cfg.frames
    if cfg.walkers:
        undraped_s = undraped_count(n_frames, cfg.undraped_fraction) / cfg.fps
        occluders += sample_walkers(rng_walk, eye, target, scene.floor_z, cfg.walkers,
                                    (0.1 * undraped_s, 0.9 * undraped_s))
    lighting = sample_lighting(rng_light, n_frames / cfg.fps)
    world = _World(
        robots=robots,
        cameras=_build_cameras(scene, rig, T_left_world, T_right_left),
        scene=scene,
        occluders=occluders,
        lighting=lighting,
        eye=eye,
        noise_sigma=float(rng_light.uniform(1.0, 4.0)),
        noise=NoiseBank(cfg.height, cfg.width, rng_noise),
        blur_sigma=float(rng_light.choice([0.0, rng_light.uniform(0.3, 1.2)])),
    )

    stamps = frame_stamps(n_frames, cfg.fps)
    n_u = undraped_count(n_frames, cfg.undraped_fraction)
    drape_start = int(stamps[n_u]) if n_u < n_frames else None
    meta = {
        "seed": str(cfg.seed),
        "site": "" if cfg.site is None else str(cfg.site),
        "frames": str(n_frames),
        "robots": str(cfg.robots),
        "urdf": str(robots[0].full.urdf_path),
        "fps": str(cfg.fps),
        "undraped_frames": str(n_u),
        "drape_start_stamp_ns": str(drape_start if drape_start is not None else -1),
        "drape_kinds": ",".join(r.drape.params.kind for r in robots),
        "distance_m": f"{float(np.linalg.norm(eye - target)):.3f}",
        **({"walkers": str(cfg.walkers)} if cfg.walkers else {}),
    }
    root = robots[0].full.root_link
    with RecordingWriter(path, metadata=None) as writer:
        writer.write_metadata(SIM_METADATA, meta)
        tf = [
            (LEFT_FRAME, f"robot_{i}/{root}", T_left_world @ r.T_world_base)
            for i, r in enumerate(robots)
        ]
        tf.append((LEFT_FRAME, RIGHT_FRAME, np.linalg.inv(T_right_left)))
        writer.write_tf_static(tf, int(stamps[0]))
        setup = time.perf_counter() - t_start
        for i, frame in enumerate(_rendered_frames(world, cfg, n_u)):
            _write_frame(writer, world, int(stamps[i]), frame)
    seconds = time.perf_counter() - t_start
    log.info(
        "wrote %s: %d frames (%d undraped) in %.1f s (setup %.1f s)",
        path,
        n_frames,
        n_u,
        seconds,
        setup,
    )
    kinds = [r.drape.params.kind for r in robots]
    return SimSummary(path, n_frames, n_u, drape_start, seconds, kinds, setup)


def _build_cameras(
    scene: StaticScene, rig: StereoRig, T_left_world: np.ndarray, T_right_left: np.ndarray
) -> list[_Camera]:
    out = []
    for side, frame_id, intr, T in (
        ("left", LEFT_FRAME, rig.left, T_left_world),
        ("right", RIGHT_FRAME, rig.right, T_right_left @ T_left_world),
    ):
        K = np.asarray(intr.K, dtype=np.float64)
        rgb, depth = render_static(scene, K, T, intr.height, intr.width)
        rays = pixel_rays(torch.as_tensor(K, dtype=torch.float32), intr.height, intr.width)
        out.append(_Camera(frame_id, side, K, T, rgb, depth, rays))
    return out


@dataclass
class _FrameData:
    """Everything written for one frame: joints per robot, then per camera JPEG and mask PNG."""

    joints: list[list[float]]
    jpegs: list[bytes]
    masks: list[bytes]


def _render_frame(
    world: _World, cfg: SimConfig, i: int, draped: bool, noise: list[tuple[int, int]]
) -> _FrameData:
    """Render and encode both views of frame ``i``; ``noise`` holds the noise-bank window of
    each camera (drawn in frame order by the caller, so workers need no random state)."""
    t = i / cfg.fps
    state = world.lighting.at(t)
    robots, cameras = world.robots, world.cameras
    capsules = [c for occ in world.occluders for c in occ.capsules(t)]
    robot_v, robot_f, albedo, cloth_v, cloth_f, tint = [], [], [], [], [], []
    v_off = d_off = 0
    drape_params: DrapeParams | None = None
    for r in robots:
        q = torch.as_tensor(r.q[i : i + 1], dtype=torch.float32)
        robot_v.append(_transform(r.T_world_base, r.full.posed_vertices(q)[0]))
        robot_f.append(r.full.faces + v_off)
        albedo.append(r.albedo)
        v_off += r.full.vertices.shape[0]
        if draped:
            cloth = r.drape.pose(r.full.link_transforms(q)[0], floor_z=world.scene.floor_z)
            cloth_world = _transform(r.T_world_base, cloth)
            cloth_v.append(cloth_world)
            cloth_f.append(r.drape.faces + d_off)
            d_off += cloth.shape[0]
            tint.append(torch.tensor(r.drape.params.tint).expand(cloth.shape[0], 3))
            capsules += _tape_capsules(r, cloth_world, world.eye)
            # each drape keeps its tint; opacity and gloss are robot 0's
            drape_params = drape_params or r.drape.params
    robot = _views(
        torch.cat(robot_v), torch.cat(robot_f), torch.cat(albedo), cameras, cull=robots[0].closed
    )
    drape = (
        _views(torch.cat(cloth_v), torch.cat(cloth_f), torch.cat(tint), cameras, cull=True)
        if draped
        else None
    )
    jpegs, masks = [], []
    for c, cam in enumerate(cameras):
        H, W = cam.static_depth.shape
        light_cam = torch.as_tensor(cam.T_cam_world[:3, :3] @ state.light_dir, dtype=torch.float32)
        layer = draw_capsules(capsules, cam.K, cam.T_cam_world, H, W)
        linear = composite_view(
            cam.static_rgb,
            cam.static_depth,
            robot[c],
            None if drape is None else drape[c],
            drape_params,
            layer,
            cam.rays,
            ViewLight(light_cam, state.intensity, state.ambient),
        )
        rgb = to_uint8(
            linear,
            state.exposure,
            state.white_balance,
            world.noise_sigma,
            world.noise.window(*noise[c]),
            world.blur_sigma,
        )
        jpegs.append(encode_image(rgb, "jpeg", cfg.jpeg_quality))
        # the label: the full model's silhouette, whatever covers it
        masks.append(encode_mask((robot[c].face_id >= 0).numpy()))
    return _FrameData([r.q[i].tolist() for r in robots], jpegs, masks)


def _write_frame(writer: RecordingWriter, world: _World, stamp: int, frame: _FrameData) -> None:
    """Write the messages of one rendered frame (all at ``stamp``)."""
    for k, r in enumerate(world.robots):
        writer.write_joint_state(
            joint_states_topic(f"robot_{k}"), stamp, r.full.joint_names, frame.joints[k]
        )
    for c, cam in enumerate(world.cameras):
        H, W = cam.static_depth.shape
        writer.write_compressed(
            image_topic(side=cam.side), stamp, cam.frame_id, frame.jpegs[c], msgs.JPEG_FORMAT
        )
        writer.write_compressed(
            mask_topic(side=cam.side, kind="robot_mask_gt"),
            stamp,
            cam.frame_id,
            frame.masks[c],
            msgs.PNG_MASK_FORMAT,
        )
        writer.write_camera_info(camera_info_topic(side=cam.side), stamp, cam.frame_id, cam.K, W, H)


_WORKER_WORLD: tuple[_World, SimConfig] | None = None


def _init_worker(world: _World, cfg: SimConfig) -> None:
    """Pool initializer: the recording's world (inherited, not pickled, under ``fork``)."""
    global _WORKER_WORLD
    torch.set_num_threads(1)
    _WORKER_WORLD = (world, cfg)


def _render_batch(jobs: list[tuple[int, bool, list[tuple[int, int]]]]) -> list[_FrameData]:
    assert _WORKER_WORLD is not None, "worker not initialised"
    world, cfg = _WORKER_WORLD
    return [_render_frame(world, cfg, i, draped, noise) for i, draped, noise in jobs]


def _rendered_frames(
    world: _World, cfg: SimConfig, n_undraped: int, batch: int = 2, ahead: int = 2
) -> Iterator[_FrameData]:
    """Every frame in order, rendered here or (``cfg.workers > 1``) by a process pool with at
    most ``ahead`` batches per worker in flight. Noise windows are drawn here in frame order,
    so the output does not depend on the number of workers."""
    jobs = (
        (i, i >= n_undraped, [world.noise.draw() for _ in world.cameras]) for i in range(cfg.frames)
    )
    if cfg.workers <= 1 or cfg.frames <= batch:
        for i, draped, noise in jobs:
            yield _render_frame(world, cfg, i, draped, noise)
        return
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
    with ProcessPoolExecutor(
        cfg.workers, mp_context=ctx, initializer=_init_worker, initargs=(world, cfg)
    ) as pool:
        pending: deque[Future] = deque()
        while True:
            chunk = list(itertools.islice(jobs, batch))
            if chunk:
                pending.append(pool.submit(_render_batch, chunk))
            if pending and (not chunk or len(pending) >= ahead * cfg.workers):
                yield from pending.popleft().result()
            if not chunk and not pending:
                return


def front_faces(verts_world: torch.Tensor, faces: torch.Tensor, eyes: torch.Tensor) -> torch.Tensor:
    """Bool ``[F]``: faces (outward counter-clockwise winding) facing at least one camera centre
    of ``eyes [C, 3]`` (world). For a closed, consistently wound mesh the other faces never
    decide a pixel: every ray that meets the mesh enters it through a front face."""
    a, b, c = (verts_world[faces[:, k]] for k in range(3))
    n = torch.cross(b - a, c - a, dim=-1)
    centre = (a + b + c) / 3.0
    facing = ((centre[None] - eyes[:, None]) * n[None]).sum(-1) < 0  # [C, F]
    return facing.any(0)


def is_closed(vertices: np.ndarray, faces: np.ndarray, vertex_link: np.ndarray) -> bool:
    """True when every edge of the mesh is shared by exactly two faces in opposite directions
    (closed, consistently wound) and every link's signed volume is positive (outward normals),
    so back faces can be culled without changing the raster."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed, counts = np.unique(edges, axis=0, return_counts=True)
    if np.any(counts != 1):
        return False
    reverse = np.unique(edges[:, ::-1], axis=0)
    if not np.array_equal(directed, reverse):
        return False
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0  # signed, per face
    per_link = np.bincount(vertex_link[faces[:, 0]], weights=volume)
    return bool(np.all(per_link[np.unique(vertex_link)] > 0))


def _views(
    verts_world: torch.Tensor,
    faces: torch.Tensor,
    albedo: torch.Tensor,
    cameras: list[_Camera],
    cull: bool,
) -> list[Surface]:
    """One mesh (world frame) rasterised in all cameras at once: a :class:`Surface` per view.
    With ``cull`` each view skips its back faces (half the work, same image for closed
    meshes)."""
    normals = vertex_normals(verts_world, faces)
    Ts = [torch.as_tensor(cam.T_cam_world, dtype=torch.float32) for cam in cameras]
    verts = torch.stack([verts_world @ T[:3, :3].T + T[:3, 3] for T in Ts])
    Ks = torch.stack([torch.as_tensor(cam.K, dtype=torch.float32) for cam in cameras])
    H, W = cameras[0].static_depth.shape
    r = rasterize(verts, faces, Ks, H, W, cull_back_faces=cull)
    return [
        Surface(verts[c], normals @ Ts[c][:3, :3].T, faces, albedo, r.depth[c], r.face_id[c])
        for c in range(len(cameras))
    ]
