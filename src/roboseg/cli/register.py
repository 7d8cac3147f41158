"""``roboseg-register``: localise a robot in a stereo recording and write ``pose.yaml``.

``roboseg-register recording=FILE.mcap model=FILE.onnx method=sdr|sdr_prior out=DIR
[robot.urdf=PATH] [robot.name=robot_0] [phase=undraped] [configs=9] [write_recording=true]``
(``conf/register.yaml``; ``model=`` is stored as ``model_file``; without a model,
``segmentor=motion`` or ``segmentor=prompt|sam2 prompt=FILE.yaml`` make the masks, see
:mod:`roboseg.registration.segmentors`) writes ``DIR/pose.yaml``
(``T_cam_base``: base frame → left optical frame, metres, 4×4 row-major),
``DIR/overlays/*.png`` (estimate tinted green, segmentation outlined red) and, with
``write_recording=true``, ``DIR/<stem>_registered.mcap``: the recording with the estimate in
``/tf_static``. With ``self_training.rounds=N`` (N > 0) a segmenter is fine-tuned on the
recording's own frames labelled by the estimate and the robot registered again from it, up to N
times (:mod:`roboseg.registration.self_training`); pose.yaml then lists every round under
``self_training`` and ``DIR/self_trained.ckpt`` holds the kept round's model. Prints the pose.yaml
path.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import hydra
import numpy as np
import torch
import yaml
from omegaconf import DictConfig, OmegaConf

from roboseg.cli._main import parse_scales, user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import (
    CameraError,
    ModelFileError,
    RecordingError,
    RobosegError,
    SegmentationError,
)
from roboseg.recording import TF_STATIC, RecordingReader
from roboseg.registration.cso import CSOConfig
from roboseg.registration.register import (
    RegisterConfig,
    Registration,
    estimate_silhouettes,
    register,
)
from roboseg.registration.sdr import SDRConfig
from roboseg.registration.sdr_prior import PriorConfig
from roboseg.registration.segmentors import SEGMENTORS, Segmentor, make_segmentor
from roboseg.robot import RobotModel, load_robot

log = logging.getLogger("roboseg.register")

CONVENTION = (
    "p_camera = T_cam_base @ p_base: maps points in base_frame into camera_frame (the left "
    "OpenCV optical frame: x right, y down, z forward); metres; 4x4 row-major"
)
TINT_BGR = np.array((60, 200, 60), np.float32)
SEG_BGR = (40, 40, 230)


def pose_document(
    reg: Registration,
    recording: str,
    model: str | None,
    segmentor: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The contents of ``pose.yaml`` (plain Python types); ``segmentor`` describes where the
    masks came from (default: the model)."""
    r = reg.result
    return {
        "convention": CONVENTION,
        "T_cam_base": [[float(x) for x in row] for row in reg.T_cam_base],
        "camera_frame": reg.camera_frame,
        "base_frame": reg.base_frame,
        "robot": reg.robot,
        "masks_contain_robots": list(reg.robots_in_masks),
        "method": reg.method,
        "termination": r.reason,
        "converged": reg.converged,
        "iterations": int(r.iterations),
        "residual_iou": {k: round(float(v), 4) for k, v in r.per_view_iou.items()},
        "sdr_residual_iou": {k: round(float(v), 4) for k, v in reg.sdr.per_view_iou.items()},
        "per_frame_iou": [[round(float(x), 4) for x in row] for row in r.per_frame_iou],
        "segmentation_refreshes": None if reg.prior is None else reg.prior.refreshes,
        "cso_fitness": round(float(reg.cso_fitness), 4),
        "cso_runs": int(reg.cso_runs),
        "recording": recording,
        "model": model,
        "segmentor": segmentor or {"kind": "model"},
        "compared_links": reg.links,
        "configurations": [
            {
                "index": c.index,
                "stamp_ns": c.stamp_ns,
                "joints": {n: float(v) for n, v in zip(reg.joint_names, c.joints, strict=True)},
            }
            for c in reg.configurations
        ],
        "dropped": list(reg.dropped),
        "warnings": list(reg.warnings),
        "seconds": {k: round(float(v), 2) for k, v in reg.seconds.items()},
    }


def save_pose_yaml(doc: dict[str, Any], path: Path) -> Path:
    """Write ``doc`` as YAML with a header comment stating the convention."""
    path.parent.mkdir(parents=True, exist_ok=True)
    text = f"# {CONVENTION}\n" + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def load_pose_yaml(path: str | Path) -> tuple[np.ndarray, str, str]:
    """``(T_cam_base [4, 4], camera_frame, base_frame)`` from a ``pose.yaml``."""
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
        T = np.asarray(doc["T_cam_base"], dtype=np.float64).reshape(4, 4)
        return T, str(doc["camera_frame"]), str(doc["base_frame"])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise RobosegError(f"{p}: not a roboseg pose.yaml ({type(exc).__name__}: {exc})") from exc


def overlay(rgb: np.ndarray, estimate: np.ndarray, segmentation: np.ndarray) -> np.ndarray:
    """BGR image: the estimate's silhouette tinted green, the segmentation's contour red."""
    out = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    blend = 0.55 * out[estimate].astype(np.float32) + 0.45 * TINT_BGR
    out[estimate] = blend.round().astype(np.uint8)
    contours, _ = cv2.findContours(
        segmentation.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    cv2.drawContours(out, contours, -1, SEG_BGR, thickness=1)
    return out


def write_overlays(reg: Registration, robot: RobotModel, folder: Path) -> list[Path]:
    """One PNG per configuration and view: ``<index>_<view>.png``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for v, view in enumerate(reg.views):
        silhouettes = estimate_silhouettes(reg, robot)[v]
        for c, conf in enumerate(reg.configurations):
            path = folder / f"{conf.index:05d}_{view.name}.png"
            cv2.imwrite(str(path), overlay(reg.images[v][c], silhouettes[c], reg.masks[v][c]))
            paths.append(path)
    return paths


def write_registered_recording(src: Path, dst: Path, reg: Registration) -> Path:
    """Copy ``src`` to ``dst`` with ``/tf_static`` replaced: the source's transforms that do not
    touch ``reg.base_frame`` plus ``T_camera_base`` = the estimate (parent = camera frame)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer
    from mcap_ros2._dynamic import serialize_dynamic

    from roboseg.recording import msgs
    from roboseg.recording.tf import matrix_to_quaternion

    with RecordingReader(src, on_error="skip") as r:
        edges = {k: T for k, T in r.tf_static().items() if reg.base_frame not in k}
    edges[(reg.camera_frame, reg.base_frame)] = reg.T_cam_base
    stamp = int(reg.configurations[0].stamp_ns) if reg.configurations else 0
    entries = []
    for (parent, child), T in edges.items():
        q = matrix_to_quaternion(np.asarray(T)[:3, :3]).tolist()
        x, y, z = (float(a) for a in np.asarray(T)[:3, 3])
        entries.append(
            {
                "header": msgs.header(stamp, parent),
                "child_frame_id": child,
                "transform": {
                    "translation": {"x": x, "y": y, "z": z},
                    "rotation": dict(zip("xyzw", q, strict=True)),
                },
            }
        )
    msgdef = msgs.MSGDEFS[msgs.TF_MESSAGE]
    encode = serialize_dynamic(msgs.TF_MESSAGE, msgdef)[msgs.TF_MESSAGE]
    tmp = dst.with_name(dst.name + ".part")
    dst.parent.mkdir(parents=True, exist_ok=True)
    with open(src, "rb") as fin, open(tmp, "wb") as fout:
        reader = make_reader(fin)
        writer = Writer(fout)
        writer.start(profile="ros2", library="roboseg")
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        tf_schema = writer.register_schema(msgs.TF_MESSAGE, "ros2msg", msgdef.encode())
        tf_channel = writer.register_channel(TF_STATIC, "cdr", tf_schema)
        writer.add_message(tf_channel, stamp, bytes(encode({"transforms": entries})), stamp)
        for schema, channel, message in reader.iter_messages():
            if channel.topic == TF_STATIC:
                continue
            if channel.id not in channel_ids:
                sid = 0
                if schema is not None:
                    if schema.id not in schema_ids:
                        schema_ids[schema.id] = writer.register_schema(
                            schema.name, schema.encoding, schema.data
                        )
                    sid = schema_ids[schema.id]
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, sid, dict(channel.metadata)
                )
            writer.add_message(
                channel_ids[channel.id],
                message.log_time,
                message.data,
                message.publish_time,
                message.sequence,
            )
        writer.finish()
    tmp.replace(dst)
    return dst


def config_from_cfg(cfg: DictConfig) -> RegisterConfig:
    """:class:`RegisterConfig` from the Hydra config (``cso``/``sdr``/``prior`` sections)."""
    try:
        cso_kw = OmegaConf.to_container(cfg.cso, resolve=True)
        sdr_kw = OmegaConf.to_container(cfg.sdr, resolve=True)
        assert isinstance(cso_kw, dict) and isinstance(sdr_kw, dict)
        if "about" in cso_kw:
            cso_kw["about"] = tuple(float(a) for a in cso_kw["about"])
        if "elevation_range" in cso_kw:
            cso_kw["elevation_range"] = tuple(float(a) for a in cso_kw["elevation_range"])
        sdr_cfg = SDRConfig(**sdr_kw)
        return RegisterConfig(
            configs=int(cfg.configs),
            phase=str(cfg.phase),  # type: ignore[arg-type]
            start_ns=None if cfg.start_ns is None else int(cfg.start_ns),
            stop_ns=None if cfg.stop_ns is None else int(cfg.stop_ns),
            robot=None if cfg.robot.name is None else str(cfg.robot.name),
            method=str(cfg.method),  # type: ignore[arg-type]
            width=int(cfg.width),
            coarse_width=None if cfg.coarse_width is None else int(cfg.coarse_width),
            screen_iterations=(
                None if cfg.get("screen_iterations") is None else int(cfg.screen_iterations)
            ),
            sdr_reduction=float(cfg.sdr_reduction),
            min_iou=float(cfg.min_iou),
            other_robots_margin=float(cfg.get("other_robots_margin", 0.05)),
            trim_masks=bool(cfg.get("trim_masks", False)),
            disparity_retry=str(cfg.get("disparity_retry", "failed")),  # type: ignore[arg-type]
            cso_configs=int(cfg.cso_configs),
            cso=CSOConfig(**cso_kw),
            sdr=sdr_cfg,
            prior=PriorConfig(
                int(cfg.prior.iterations), int(cfg.prior.refresh_every), sdr_cfg, int(cfg.width)
            ),
        )
    except (TypeError, ValueError) as exc:
        raise CameraError(f"invalid registration setting: {exc}") from exc


def segmentor_from_cfg(cfg: DictConfig) -> Segmentor:
    """The non-model segmentor ``cfg.segmentor`` names, from its section of the config."""
    from roboseg.registration.grabcut import GrabCutConfig
    from roboseg.registration.motion import MotionConfig

    kind = str(cfg.segmentor)
    if kind not in SEGMENTORS:
        raise SegmentationError(f"segmentor must be one of {', '.join(SEGMENTORS)}, got {kind!r}")
    section = {"motion": "motion", "prompt": "grabcut", "sam2": "sam2"}[kind]
    try:
        opts = OmegaConf.to_container(cfg[section], resolve=True)
        assert isinstance(opts, dict)
        if kind == "motion":
            return make_segmentor(kind, config=MotionConfig(**opts))
        prompt = None if cfg.get("prompt") is None else str(cfg.prompt)
        if kind == "prompt":
            return make_segmentor(kind, prompt=prompt, config=GrabCutConfig(**opts))
        return make_segmentor(
            kind,
            prompt=prompt,
            checkpoint=opts.get("checkpoint"),
            model_config=str(opts.get("config")),
            device=str(opts.get("device", "cpu")),
            max_frames=int(opts.get("max_frames", 200)),
        )
    except TypeError as exc:
        raise SegmentationError(f"{section}: invalid setting ({exc})") from exc


def self_training_from_cfg(cfg: DictConfig) -> tuple[Any, bool] | None:
    """``(SelfTrainingConfig, save_checkpoint)`` from the ``self_training`` section, or None when
    it is absent or ``rounds`` is 0 (then the training stack is not even imported)."""
    section = cfg.get("self_training")
    if section is None or section.get("rounds", 0) == 0:
        return None
    from roboseg.registration.self_training import SelfTrainingConfig, SelfTrainingError

    opts = OmegaConf.to_container(section, resolve=True)
    assert isinstance(opts, dict)
    save = bool(opts.pop("save_checkpoint", True))
    for key in ("image_size", "decoder_channels"):
        if isinstance(opts.get(key), list):
            opts[key] = tuple(opts[key])
    augment = opts.get("augment")
    if augment is not None and not isinstance(augment, dict):
        raise SelfTrainingError(
            f"self_training.augment must be null or an augmentation config, got {augment!r}"
        )
    try:
        return SelfTrainingConfig(**opts), save
    except TypeError as exc:
        raise SelfTrainingError(f"self_training: invalid setting ({exc})") from exc


@user_errors_exit
def run(cfg: DictConfig) -> Path:
    """Register as ``cfg`` says; write the outputs; return the pose.yaml path."""
    torch.set_num_threads(max(1, int(cfg.threads)))
    if cfg.recording is None:
        raise RecordingError("recording: required (recording=FILE.mcap)")
    recording = Path(str(cfg.recording))
    if not recording.is_file():
        raise RecordingError(f"recording: no such file {recording}")
    urdf = cfg.robot.urdf
    if urdf is not None and not Path(str(urdf)).is_file():
        raise RobosegError(f"robot.urdf: no such file {urdf}")
    reg_cfg = config_from_cfg(cfg)
    self_training = self_training_from_cfg(cfg)
    kind = str(cfg.get("segmentor") or "model")
    note = None
    if kind == "model":
        if cfg.model_file is None:
            raise ModelFileError(
                "model: required (model=FILE.onnx, e.g. outputs/default/model.onnx)"
            )
        from roboseg.segmentor import OnnxSegmentor

        scales = parse_scales(cfg.get("model_scales"), "model_scales")
        segmentor = OnnxSegmentor(str(cfg.model_file), threads=int(cfg.threads), scales=scales)
        robot = load_robot(None if urdf is None else str(urdf))
        reg = register(recording, robot, segmentor=segmentor, config=reg_cfg)
        model = str(Path(str(cfg.model_file)).resolve())
        described: dict[str, Any] = {"kind": "model"}
        if scales != [1.0]:
            described["scales"] = scales

        def first_masks(frame: Any) -> tuple[np.ndarray, np.ndarray]:
            probs = segmentor.predict(np.stack([frame.left, frame.right]))
            pair = probs > segmentor.meta.threshold  # as register() thresholds them
            return pair[0], pair[1]
    else:
        seg = segmentor_from_cfg(cfg)
        if reg_cfg.method == "sdr_prior":
            note = f"method=sdr_prior needs segmentor=model; segmentor={kind} used method=sdr"
            log.warning("%s", note)
            reg_cfg = replace(reg_cfg, method="sdr")
        if seg.trims:
            reg_cfg = replace(reg_cfg, trim_masks=True)
        robot = load_robot(None if urdf is None else str(urdf))
        seg.prepare(recording, robot, reg_cfg)
        reg = register(
            recording, robot, masks=seg, frames=seg.frames, links=seg.links, config=reg_cfg
        )
        if note:
            reg.warnings.insert(0, note)
        model, described = None, seg.describe()
        first_masks = seg
    out = Path(str(cfg.out))
    rounds = None
    if self_training is not None:
        from roboseg.registration.self_training import self_train

        st_cfg, save_model = self_training
        trained = self_train(recording, robot, reg, reg_cfg, st_cfg, described, first_masks)
        reg, rounds = trained.registration, trained.rounds
        if note and note not in reg.warnings:
            reg.warnings.insert(0, note)
        ckpt = trained.save_checkpoint(out / "self_trained.ckpt") if save_model else None
        if ckpt is not None:
            log.info("wrote %s (round %d's model)", ckpt, trained.kept)
    doc = pose_document(reg, str(recording.resolve()), model, described)
    if rounds is not None:
        doc["self_training"] = rounds
    pose_path = save_pose_yaml(doc, out / "pose.yaml")
    write_overlays(reg, robot, out / "overlays")
    if bool(cfg.write_recording):
        dst = write_registered_recording(recording, out / f"{recording.stem}_registered.mcap", reg)
        log.info("wrote %s", dst)
    for line in reg.dropped:
        log.warning("dropped: %s", line)
    if not reg.converged:
        raise CameraError(
            f"registration did not converge ({reg.result.reason}; "
            f"{'; '.join(reg.warnings) or 'no detail'}); inspect {pose_path}"
        )
    print(pose_path)
    return pose_path


def alias_model_argument(argv: list[str]) -> list[str]:
    """``model=PATH`` → ``model_file=PATH`` (``model`` is the training config group in conf/)."""
    return [f"model_file={a[6:]}" if a.startswith("model=") else a for a in argv]


@hydra.main(config_path=CONF_DIR, config_name="register", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point (accepts ``model=FILE.onnx``)."""
    sys.argv[1:] = alias_model_argument(sys.argv[1:])
    _hydra_main()


if __name__ == "__main__":
    main()
