"""``roboseg-track``: stereo AprilTag tracking and breathing model of one recording.

``roboseg-track recording=FILE.mcap out=OUT [roi.left=[tx,ty,w,h]] [T_cam_base=[16 numbers]]``
reads the stereo frames through :mod:`roboseg.recording`, triangulates every AprilTag (36h11) per
frame, maps the positions into the robot base frame and fits the breathing model over the last
``breathing.horizon`` seconds of each track. Writes ``OUT/tags.csv`` (one row per frame and tag,
with an explicit status), ``OUT/breathing.yaml`` (``omega0`` rad/s, per-axis amplitudes in mm)
and ``OUT/breathing.png`` (trajectories with the fitted model). Prints the output folder.
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import yaml
from omegaconf import DictConfig, OmegaConf

from roboseg.cli._main import user_errors_exit
from roboseg.config import CONF_DIR
from roboseg.errors import CameraError, RecordingError, RobosegError
from roboseg.recording import RecordingReader
from roboseg.tracking.breathing import BreathingFit, fit_breathing
from roboseg.tracking.tags import Roi, StereoTagTracker, TagStatus, TagTracks

log = logging.getLogger("roboseg.track")

AMPLITUDE_DEFINITION = (
    "half peak-to-peak of the fitted 3-harmonic model over one period, mm; the sign is the axis's "
    "in-phase correlation with AP (negative = moves opposite to AP during a breath)"
)


def _roi(value: Any, name: str) -> Roi | None:
    if value is None:
        return None
    try:
        tx, ty, w, h = (int(v) for v in value)
    except (TypeError, ValueError):
        raise CameraError(f"roi.{name} must be [tx, ty, width, height], got {value}") from None
    if w <= 0 or h <= 0:
        raise CameraError(f"roi.{name} needs a positive size, got {value}")
    return Roi(tx, ty, w, h)


def _axes(cfg: DictConfig) -> np.ndarray:
    rows = []
    for name in ("ML", "CC", "AP"):
        v = np.asarray(OmegaConf.select(cfg, f"axes.{name}"), dtype=np.float64).ravel()
        if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) < 1e-9:
            raise RobosegError(f"axes.{name} must be a non-zero 3-vector, got {v.tolist()}")
        rows.append(v / np.linalg.norm(v))
    return np.stack(rows)


def base_transform(reader: RecordingReader, cfg: DictConfig) -> tuple[np.ndarray, str]:
    """``T_cam_base`` (left optical frame ← robot base) from the config or ``/tf_static``."""
    if cfg.T_cam_base is not None:
        T = np.asarray(OmegaConf.to_container(cfg.T_cam_base), dtype=np.float64).ravel()
        if T.size != 16 or not np.isfinite(T).all():
            raise RobosegError(f"T_cam_base must be 16 finite numbers, got {T.size}")
        T = T.reshape(4, 4)
        if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise RobosegError("T_cam_base: rotation part is not orthonormal")
        return T, "T_cam_base (config)"
    left = reader.camera_infos("left").frame_id
    right = reader.camera_infos("right").frame_id
    base = cfg.base_frame
    if base is None:
        frames = {f for edge in reader.tf_static() for f in edge} - {left, right}
        if len(frames) != 1:
            raise RecordingError(
                f"{reader.path}: cannot choose the robot base frame among "
                f"{sorted(frames) or 'no /tf_static frames'}; set base_frame= or T_cam_base="
            )
        base = frames.pop()
    return reader.lookup(left, str(base)), str(base)


def fit_tag(
    stamps_ns: np.ndarray, anatomical: np.ndarray, t0_ns: int, cfg: DictConfig
) -> BreathingFit:
    """Fit the breathing model to one tag's ML/CC/AP track (metres) over the last horizon."""
    if len(stamps_ns) == 0:
        return BreathingFit(False, "never triangulated")
    t = (stamps_ns - t0_ns) * 1e-9
    sel = t >= t[-1] - float(cfg.breathing.horizon)
    return fit_breathing(
        t[sel],
        anatomical[sel],
        omega_min=float(cfg.breathing.omega_min),
        omega_max=float(cfg.breathing.omega_max),
        min_span=float(cfg.breathing.min_span),
    )


def write_tags_csv(path: Path, tracks: TagTracks, T_cam_base: np.ndarray, t0_ns: int) -> None:
    """One row per frame and known tag; positions (m) only when triangulated."""
    T_base_cam = np.linalg.inv(T_cam_base)
    ids = tracks.tag_ids
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "stamp_ns",
                "t_s",
                "tag_id",
                "status",
                "x_cam",
                "y_cam",
                "z_cam",
                "x_base",
                "y_base",
                "z_base",
                "reprojection_px",
            ]
        )
        for frame in tracks.frames:
            t_s = f"{(frame.stamp_ns - t0_ns) * 1e-9:.6f}"
            for i in ids:
                obs = frame.observations.get(i)
                if obs is None:
                    w.writerow([frame.stamp_ns, t_s, i, "not_found", *[""] * 7])
                    continue
                cam = base = ["", "", ""]
                if obs.status is TagStatus.TRIANGULATED and obs.position_cam is not None:
                    p = obs.position_cam
                    q = T_base_cam[:3, :3] @ p + T_base_cam[:3, 3]
                    cam = [f"{v:.6f}" for v in p]
                    base = [f"{v:.6f}" for v in q]
                err = "" if obs.reprojection_px is None else f"{obs.reprojection_px:.3f}"
                w.writerow([frame.stamp_ns, t_s, i, obs.status.value, *cam, *base, err])


def plot_breathing(
    path: Path,
    series: dict[int, tuple[np.ndarray, np.ndarray]],
    fits: dict[int, BreathingFit],
) -> None:
    """PNG: ML/CC/AP trajectories (mm about the fitted a0) with the fitted model per tag."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for k, name in enumerate(("ML", "CC", "AP")):
        ax = axes[k]
        for tag_id, (t, z) in series.items():
            fit = fits[tag_id]
            offset = fit.coef[0, k] if fit.fitted and fit.coef is not None else np.mean(z[:, k])
            line = ax.plot(t, (z[:, k] - offset) * 1e3, ".", ms=3, label=f"tag {tag_id}")
            if fit.fitted:
                tt = np.linspace(fit.t_ref - fit.span, fit.t_ref, 400)
                model = (fit.predict(tt)[:, k] - offset) * 1e3
                ax.plot(tt, model, "-", color=line[0].get_color(), lw=1)
        ax.set_ylabel(f"{name} [mm]")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    if series:
        axes[0].legend(loc="upper right", fontsize=8)
    else:
        axes[0].set_title("no tag triangulated")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _mm(values: np.ndarray) -> dict[str, float]:
    return {n: round(float(v) * 1e3, 4) for n, v in zip(("ML", "CC", "AP"), values, strict=True)}


@user_errors_exit
def run(cfg: DictConfig) -> Path:
    """Track the recording ``cfg.recording``; write the outputs into ``cfg.out``."""
    if cfg.recording is None:
        raise RobosegError("recording=FILE.mcap is required")
    out = Path(str(cfg.out))
    if out.exists() and not out.is_dir():
        raise RobosegError(f"out: {out} exists and is not a folder")
    axes = _axes(cfg)
    with RecordingReader(str(cfg.recording), camera=str(cfg.camera), robots=[]) as reader:
        K_l, *_ = reader.camera_info("left")
        K_r, *_ = reader.camera_info("right")
        calib = reader.camera_calib()
        if calib.T_right_left is None:
            raise RecordingError(f"{reader.path}: no left/right stereo transform in /tf_static")
        T_cam_base, base_name = base_transform(reader, cfg)
        tracker = StereoTagTracker(
            K_l,
            K_r,
            calib.T_right_left,
            _roi(cfg.roi.left, "left"),
            _roi(cfg.roi.right, "right"),
            max_reprojection_px=float(cfg.tracking.max_reprojection_px),
            refinement=str(cfg.tracking.refinement),
        )
        tracks = TagTracks()
        for frame in reader.frames():
            tracks.add(tracker.process(frame.stamp_ns, frame.left, frame.right))
    if not tracks.frames:
        raise RecordingError(f"{cfg.recording}: no stereo frames")
    out.mkdir(parents=True, exist_ok=True)
    t0_ns = tracks.frames[0].stamp_ns
    write_tags_csv(out / "tags.csv", tracks, T_cam_base, t0_ns)

    visibility = tracks.visibility()
    series: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    fits: dict[int, BreathingFit] = {}
    per_tag: dict[int, dict[str, Any]] = {}
    for tag_id in tracks.tag_ids:
        stamps, p_base = tracks.trajectory(tag_id, T_cam_base)
        anatomical = p_base @ axes.T
        fit = fit_tag(stamps, anatomical, t0_ns, cfg)
        fits[tag_id] = fit
        if len(stamps):
            series[tag_id] = ((stamps - t0_ns) * 1e-9, anatomical)
        entry: dict[str, Any] = {
            "visibility": round(visibility[tag_id], 4),
            "samples": int(len(stamps)),
            "fitted": fit.fitted,
        }
        if fit.fitted:
            entry.update(
                omega0=round(fit.omega0, 6),
                amplitudes_mm=_mm(fit.signed_amplitudes(reference_axis=2)),
                rms_residual_mm=round(fit.rms_residual * 1e3, 4),
            )
        else:
            entry["reason"] = fit.reason
        per_tag[tag_id] = entry
        log.info("tag %d: visibility %.1f %%, %s", tag_id, 100 * visibility[tag_id], entry)

    ref = cfg.breathing.reference_tag
    fitted = [i for i in per_tag if fits[i].fitted]
    if ref is None and fitted:
        ref = max(fitted, key=lambda i: (visibility[i], -i))
    result: dict[str, Any] = {"recording": str(cfg.recording), "base_frame": base_name}
    if ref is not None and int(ref) in fits and fits[int(ref)].fitted:
        fit = fits[int(ref)]
        result.update(
            fitted=True,
            reference_tag=int(ref),
            omega0=round(fit.omega0, 6),
            period_s=round(fit.period, 4),
            breaths_per_min=round(60.0 / fit.period, 3),
            amplitudes_mm=_mm(fit.signed_amplitudes(reference_axis=2)),
        )
    else:
        why = "no tag triangulated" if not series else f"reference tag {ref} not fitted"
        result.update(fitted=False, reason=why)
        log.warning("%s: breathing model not fitted (%s)", cfg.recording, why)
    result["amplitude_definition"] = AMPLITUDE_DEFINITION
    result["horizon_s"] = float(cfg.breathing.horizon)
    result["tags"] = per_tag
    with open(out / "breathing.yaml", "w") as f:
        yaml.safe_dump(result, f, sort_keys=False)
    plot_breathing(out / "breathing.png", series, fits)
    print(out)
    return out


@hydra.main(config_path=CONF_DIR, config_name="track", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
