"""Measurements and the results page of ``make reproduce`` (:mod:`roboseg.reproduce`).

Evaluation only: the functions here read the simulator's ground truth (``/tf_static`` robot
bases, ``robot_mask_gt`` topics, ``roboseg_truth`` metadata) to score what the pipeline
produced without it. Poses are ``T_cam_base`` 4×4 (robot base → left optical frame, metres);
errors are in millimetres.
"""

from __future__ import annotations

import json
import logging
import shutil
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from roboseg.errors import RobosegError
from roboseg.evaluation.metrics import binary_iou
from roboseg.recording import RecordingReader
from roboseg.robot import RobotModel
from roboseg.stages import machine_description, today

log = logging.getLogger("roboseg.reproduce")

SIM_METADATA = "roboseg_sim"
TRUTH_METADATA = "roboseg_truth"


# --- machine ---------------------------------------------------------------------------------


# --- annotation quality ----------------------------------------------------------------------


def annotation_iou(path: str | Path, camera: str = "camera") -> dict[str, Any]:
    """Per-frame IoU of the self-annotated left mask (``left/robot_mask``) against the
    simulator's ground truth (``left/robot_mask_gt``) in one annotated recording."""
    ious = []
    with RecordingReader(
        path, camera=camera, robots=[], mask_topics=["left/robot_mask", "left/robot_mask_gt"]
    ) as reader:
        for frame in reader.frames():
            ious.append(
                binary_iou(frame.masks["left/robot_mask"], frame.masks["left/robot_mask_gt"])
            )
    if not ious:
        raise RobosegError(f"{path}: no frame carries both left/robot_mask and robot_mask_gt")
    a = np.asarray(ious, dtype=np.float64)
    return {
        "frames": len(a),
        "iou_mean": float(np.nanmean(a)),
        "iou_std": float(np.nanstd(a)),
        "iou_min": float(np.nanmin(a)),
    }


# --- registration error ----------------------------------------------------------------------


def load_pose(path: str | Path) -> dict[str, Any]:
    """The ``pose.yaml`` of ``roboseg-register`` (safe loader) with ``T_cam_base`` as an array."""
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
        doc["T_cam_base"] = np.asarray(doc["T_cam_base"], dtype=np.float64).reshape(4, 4)
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise RobosegError(f"{p}: not a roboseg pose.yaml ({type(exc).__name__}: {exc})") from None
    return doc


def phase_of_frames(metadata: Mapping[str, Mapping[str, str]], stamps: np.ndarray) -> np.ndarray:
    """Bool ``[N]``: frame is draped (stamp at or after the simulator's drape stamp)."""
    value = metadata.get(SIM_METADATA, {}).get("drape_start_stamp_ns")
    if value is None or int(value) < 0:
        return np.ones(len(stamps), dtype=bool)
    return stamps >= int(value)


def frame_errors_mm(
    robot: RobotModel, q: np.ndarray, T_est: np.ndarray, T_true: np.ndarray
) -> np.ndarray:
    """``[N, F]`` distances (mm) between the origin of every frame of ``robot`` (root first,
    the tool centre last) at joints ``q`` ``[N, D]`` mapped into the camera by ``T_est`` and by
    ``T_true``."""
    T_bf = robot.frame_transforms(torch.as_tensor(q, dtype=robot.dtype))
    p = T_bf[..., :3, 3].double().numpy()
    d = p @ (T_est[:3, :3] - T_true[:3, :3]).T + (T_est[:3, 3] - T_true[:3, 3])
    return 1000.0 * np.linalg.norm(d, axis=-1)


def registration_error(
    pose_yaml: str | Path, recording: str | Path, robot: RobotModel, phase: str
) -> dict[str, Any]:
    """Error of one estimate against the recording's ``/tf_static`` truth over every frame of
    ``phase`` (``undraped`` | ``draped`` | ``all``): per-frame distances of each link origin."""
    doc = load_pose(pose_yaml)
    name = str(doc.get("robot") or "robot_0")
    with RecordingReader(
        recording, robots=[name], joint_order={name: robot.joint_names}, on_error="skip"
    ) as reader:
        left = reader.camera_infos("left").frame_id
        T_true = reader.lookup(left, f"{name}/{robot.root_link}")
        frames = list(reader.frames(decode=False))
        draped = phase_of_frames(reader.metadata(), np.array([f.stamp_ns for f in frames]))
    keep = {"draped": draped, "undraped": ~draped}.get(phase, np.ones(len(frames), dtype=bool))
    q = np.stack([f.joints[name] for f, k in zip(frames, keep, strict=True) if k])
    err = frame_errors_mm(robot, q, doc["T_cam_base"], T_true)
    tool = err[:, -1]
    R = doc["T_cam_base"][:3, :3].T @ T_true[:3, :3]
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    q1, med, q3 = np.percentile(tool, [25, 50, 75])
    rounds = doc.get("self_training") or []
    kept = [r["round"] for r in rounds if r.get("kept")]
    # each self-training round's estimate scored alike (None: the round wrote no pose)
    by_round = [
        None if r.get("T_cam_base") is None else float(np.median(
            frame_errors_mm(robot, q, np.asarray(r["T_cam_base"], np.float64), T_true)[:, -1]))
        for r in rounds
    ]
    return {
        "robot": name,
        "method": doc.get("method"),
        "segmentor": (doc.get("segmentor") or {}).get("kind", "model"),
        # self-training: rounds run after the first registration, the round kept (0: the first)
        "self_training_rounds": max(0, len(rounds) - 1),
        "self_training_kept": kept[0] if kept else None,
        # what made the rounds' masks: grabcut | self_trained (a fine-tuned network)
        "self_training_masks": (rounds[1].get("masks") or {}).get("kind") if len(rounds) > 1
        else None,
        # tool-centre median (mm) of every round's estimate, round 0 first
        "tool_median_mm_by_round": by_round,
        "converged": bool(doc.get("converged", False)),
        "residual_iou": doc.get("residual_iou"),
        "frames": int(len(q)),
        "tool_median_mm": float(med),
        "tool_q1_mm": float(q1),
        "tool_q3_mm": float(q3),
        "tool_mm": [round(float(x), 3) for x in tool],
        "link_median_mm": [float(np.median(err[:, i])) for i in range(err.shape[1])],
        "link_names": list(robot.frame_names),
        "rotation_deg": angle,
        "translation_mm": float(1000 * np.linalg.norm(doc["T_cam_base"][:3, 3] - T_true[:3, 3])),
    }


def localisation_plot(entries: Sequence[dict[str, Any]], path: Path) -> Path:
    """PNG: per-link median error (L0 … tool centre) per estimate, and tool-centre boxes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for e in entries:
        y = e["link_median_mm"]
        style = "--" if e["phase"] == "undraped" else "-"
        ax1.plot(range(len(y)), y, style, marker="o", ms=3, label=e["label"])
    if entries:
        names = entries[0]["link_names"]
        ax1.set_xticks(range(len(names)), [f"L{i}" for i in range(len(names) - 1)] + ["tool"])
        ax1.legend(fontsize=7)
    ax1.set_xlabel("kinematic chain (base → tool centre)")
    ax1.set_ylabel("median error [mm]")
    ax1.set_yscale("symlog", linthresh=1.0)
    ax1.grid(alpha=0.3)
    ax1.set_title("per link (dashed: undraped, solid: draped)")
    if entries:
        ax2.boxplot([e["tool_mm"] for e in entries], showfliers=False)
        ax2.set_xticks(range(1, len(entries) + 1), [e["label"] for e in entries], rotation=30,
                       ha="right", fontsize=7)
    ax2.set_ylabel("tool-centre error [mm]")
    ax2.set_yscale("symlog", linthresh=1.0)
    ax2.grid(alpha=0.3)
    ax2.set_title("tool centre, every frame of the phase")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def rounds_plot(entries: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """PNG: tool-centre median error (mm, log scale) of each self-training round's estimate,
    a line per undraped registration (``entries``: :func:`registration_error` results with a
    ``label``), the kept round circled; None when no entry ran a round."""
    shown = [e for e in entries if len(e.get("tool_median_mm_by_round") or []) > 1]
    if not shown:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for e in shown:
        ys = [np.nan if y is None else y for y in e["tool_median_mm_by_round"]]
        (line,) = ax.plot(range(len(ys)), ys, marker="o", ms=3, label=e["label"])
        k = e.get("self_training_kept")
        if k is not None and k < len(ys):
            ax.plot([k], [ys[k]], "o", ms=10, mfc="none", color=line.get_color())
    ax.axhline(TARGET_TOOL_MM, color="0.4", lw=0.8, ls=":")
    ax.set_yscale("log")
    ax.set_xlabel("self-training round (0: the first registration)")
    ax.set_ylabel("tool-centre median error [mm]")
    ax.set_title(f"undraped estimates by round (circled: kept; dotted: {TARGET_TOOL_MM:g} mm)")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --- breathing -------------------------------------------------------------------------------


def breathing_truth(recording: str | Path) -> dict[str, float]:
    """The simulator's breathing truth (``roboseg_truth`` metadata; tag 10 has gain 1)."""
    with RecordingReader(recording, robots=[]) as reader:
        meta = reader.metadata().get(TRUTH_METADATA, {})
    out = {}
    for key in ("omega0", "amplitude_ML_mm", "amplitude_CC_mm", "amplitude_AP_mm"):
        if key in meta:
            out[key] = float(meta[key])
    return out


# --- page ------------------------------------------------------------------------------------


def fmt(value: Any, digits: int = 2) -> str:
    """A number with ``digits`` decimals, ``-`` for missing or non-finite."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "-"
    return f"{v:.{digits}f}" if np.isfinite(v) else "-"


def md_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def lab_rows(lab: Sequence[Any]) -> list[list[Any]]:
    """One row per split of the (many, short) lab recordings: names, count, robots, seeds."""
    rows = []
    for split in dict.fromkeys(r.split for r in lab):
        recs = [r for r in lab if r.split == split]
        names = recs[0].stem if len(recs) == 1 else f"{recs[0].stem} … {recs[-1].stem}"
        seeds = str(recs[0].seed) if len(recs) == 1 else f"{recs[0].seed} … {recs[-1].seed}"
        robots = "/".join(str(v) for v in dict.fromkeys(r.robots for r in recs))
        rows.append([f"{names} ({len(recs)})", "lab (bootstrap)", split, robots, seeds])
    return rows


def copy_figure(src: Path, figures: Path, name: str) -> str | None:
    """Copy ``src`` into ``figures/name``; return the name, or None when ``src`` is missing."""
    if not src.is_file():
        return None
    figures.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src, figures / name)
    return name


def read_json(path: Path) -> Any:
    """JSON of ``path`` or None when it does not exist."""
    return json.loads(path.read_text()) if path.is_file() else None


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a ``.part`` file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text)
    tmp.replace(path)


def _stage_log_header(logs: Path, name: str) -> tuple[str, str]:
    """``(command, "date on machine")`` from the first two lines of a stage log."""
    path = logs / f"{name}.log"
    if not path.is_file():
        return "-", "-"
    lines = path.read_text(errors="replace").splitlines()[:2]
    command = lines[0][2:] if lines and lines[0].startswith("$ ") else "-"
    where = lines[1][2:] if len(lines) > 1 and lines[1].startswith("# ") else "-"
    return command, where


def portable(text: str, root: Path, python: str = sys.executable) -> str:
    """``text`` with this interpreter written ``python`` and paths under ``root`` made relative
    to it, so that the page's commands run from any checkout's root."""
    text = text.replace(python, "python")
    return text.replace(f"{Path(root).resolve()}/", "")


def _stdout(logs: Path, name: str, max_lines: int = 150) -> str:
    path = logs / f"{name}.stdout"
    if not path.is_file():
        return ""
    lines = path.read_text(errors="replace").splitlines()
    if len(lines) > max_lines:
        lines = lines[:max_lines] + [f"... ({len(lines) - max_lines} more lines in {path.name})"]
    return "\n".join(lines)


def _val_iou(logs: Path, name: str) -> str:
    """The ``val/iou=`` line a training run prints last."""
    return _printed(logs, name, "val/iou")


def _printed(logs: Path, name: str, key: str) -> str:
    """The value of the last ``key=`` line training run ``name`` printed (``-``: none)."""
    for line in reversed(_stdout(logs, f"train_{name}", 10_000).splitlines()):
        if line.startswith(f"{key}="):
            return line.split("=", 1)[1]
    return "-"


def _status(stages: Any, name: str) -> str:
    seconds, code = stages.status(name)
    if seconds is None:
        return "not run"
    return "ok" if code == 0 else f"exit status {code}"


def _masks_of(reg: dict[str, Any]) -> str:
    """Where an undraped registration's masks came from: ``motion + self-training 1, kept 1``
    (rounds of a fine-tuned network) or ``model + GrabCut 3, kept 2``."""
    text = str(reg.get("segmentor") or "model")
    if reg.get("self_training_rounds"):
        how = "GrabCut" if reg.get("self_training_masks") == "grabcut" else "self-training"
        text += f" + {how} {reg['self_training_rounds']}, kept {reg['self_training_kept']}"
    return text


def _by_round(reg: dict[str, Any]) -> str:
    """Tool-centre median (mm) of each self-training round's estimate, round 0 first, the kept
    round in bold: ``169.6 → 52.8 → **10.2**``; ``–`` without rounds."""
    errs = reg.get("tool_median_mm_by_round") or []
    if len(errs) < 2:
        return "–"
    kept = reg.get("self_training_kept")
    cells = [fmt(e, 1) if k != kept else f"**{fmt(e, 1)}**" for k, e in enumerate(errs)]
    return " → ".join(cells)


#: Columns of :func:`_estimate_cells`.
ESTIMATE_COLUMNS = ["undraped masks", "converged", "tool error [mm]", "base error [mm]",
                    "rotation [°]", "tool error by round [mm]"]


def _estimate_cells(reg: dict[str, Any]) -> list[str]:
    """One undraped estimate's :data:`ESTIMATE_COLUMNS` (``reg``: :func:`registration_error`,
    or ``{"error": ...}`` when no pose was written)."""
    if "error" in reg:
        return ["–", reg["error"], "–", "–", "–", "–"]
    return [
        _masks_of(reg), "yes" if reg["converged"] else "**no**",
        f"{fmt(reg['tool_median_mm'], 1)} ({fmt(reg['tool_q1_mm'], 1)}–"
        f"{fmt(reg['tool_q3_mm'], 1)})",
        fmt(reg["link_median_mm"][0], 1), fmt(reg["rotation_deg"], 2), _by_round(reg),
    ]


#: The tool-centre error (median over the phase's frames, mm) the study aims within.
TARGET_TOOL_MM = 10.0


def _within(rows: Sequence[Mapping[str, Any]]) -> str:
    """``, k within 10 mm``: converged estimates whose median tool-centre error is within
    :data:`TARGET_TOOL_MM` (empty when no row has an error)."""
    tool = [r for r in rows if r.get("tool_median_mm") is not None]
    if not tool:
        return ""
    k = sum(bool(r.get("converged")) and r["tool_median_mm"] <= TARGET_TOOL_MM for r in tool)
    return f", {k} within {TARGET_TOOL_MM:g} mm"


def at_a_glance(
    stage_status: Sequence[tuple[str, float | None, int | None]],
    bootstrap_val_iou: str,
    annotation: Any,
    localisation: Any,
    wall_seconds: float | None = None,
) -> list[str]:
    """Bullet lines summing up a run: time and failures, the bootstrap segmenter, the
    undraped registrations and self-annotation, the draped registrations.

    ``stage_status`` holds ``(name, seconds, exit status)`` per stage (``None``: not run);
    ``annotation`` / ``localisation`` are the metrics files' contents (or ``None``);
    ``wall_seconds`` the wall-clock time the stages took (side-by-side stages counted once).
    """
    ran = [(n, t, c) for n, t, c in stage_status if t is not None]
    failed = [n for n, _, c in ran if c]
    missing = [n for n, t, _ in stage_status if t is None]
    total_min = sum(float(t) for _, t, _ in ran) / 60
    lines = [
        f"- stages: {len(ran) - len(failed)} of {len(stage_status)} ok, {len(failed)} failed"
        + (f" ({', '.join(failed)})" if failed else "")
        + (f", {len(missing)} not run" if missing else "")
        + (f"; {wall_seconds / 60:.1f} min wall clock" if wall_seconds is not None else "")
        + f"; {total_min:.1f} min of stage time in all",
        f"- bootstrap segmenter (undraped lab frames): validation IoU {bootstrap_val_iou}",
    ]
    if annotation is not None:
        regs = [r for row in annotation["rows"] for r in row["registration"]]
        ious = [row["annotation"]["iou_mean"] for row in annotation["rows"]
                if row["annotation"].get("iou_mean") is not None]
        ok = sum(bool(r.get("converged")) for r in regs)
        head = f"- undraped registrations converged: {ok} of {len(regs)}{_within(regs)}"
        lines.append(
            f"{head}; self-annotated masks vs simulator: mean IoU {np.mean(ious):.3f} over "
            f"{len(ious)} recordings" if ious else head
        )
    if localisation is not None:
        rows = localisation["rows"]
        ok = sum(bool(r.get("converged")) for r in rows)
        tool = [r["tool_median_mm"] for r in rows if r.get("tool_median_mm") is not None]
        lines.append(
            f"- draped test registrations converged: {ok} of {len(rows)}{_within(rows)}"
            + (f"; median tool-centre error {min(tool):.1f}–{max(tool):.1f} mm" if tool else "")
        )
    return lines


def write_page(cfg: Any, layout: Any, plan: Sequence[Any], stages: Any) -> Path:
    """Write the results page ``layout.page`` and its figures into ``layout.figures``."""
    out: Path = layout.out
    logs: Path = stages.logs
    figures: Path = layout.figures
    rel = figures.name
    parts: list[str] = []
    add = parts.append
    from roboseg.reproduce import operating_room_size

    or_w, or_h = operating_room_size(cfg)
    add("# Results: the paper's pipeline on simulated data\n")
    add(
        "**Every number on this page comes from simulated recordings** written by roboseg's own "
        "simulator (a rendered robot under a simulated drape, with simulated cameras, "
        "occluders and lighting), not from an operating room. They show what the chain "
        "record → self-annotate → train → export → evaluate → register → track gives end to "
        "end, where it fails, and how its parts compare with each other; they are not the "
        "paper's clinical results and should not be compared with them as such.\n"
    )
    add(
        f"Produced by `make reproduce` (`python -m roboseg.reproduce`, recipe `{cfg.recipe}`, "
        f"{cfg.frames} frames per recording, the lab's at {cfg.width}×{cfg.height}, the operating "
        f"room's at {or_w}×{or_h}, seed {cfg.seed}); "
        f"page written {today()} on {machine_description()}.\n"
    )
    add("## At a glance\n")
    from roboseg.reproduce import (
        draped_scales,
        draped_settings,
        lab_in_training,
        model_init,
        undraped_segmentor,
    )

    segmentor = undraped_segmentor(cfg)
    glance = at_a_glance(
        [(step.name, *stages.status(step.name)) for step in plan],
        _val_iou(logs, "bootstrap") if segmentor == "model"
        else f"none (undraped.segmentor={segmentor})",
        read_json(out / "metrics" / "annotation.json"),
        read_json(out / "metrics" / "localisation.json"),
        stages.wall_seconds([step.name for step in plan]),
    )
    add("\n".join(glance) + "\n")

    # study
    add("## Study\n")
    site = cfg.operating_room.get("site")
    add(
        "Shaped like the paper's (Table S3): several single-robot training recordings with "
        "different camera placements, one validation recording and a two-robot test recording"
        + (f", all sessions of one operating room (simulator site {site}: room, drape kind and "
           "the camera's side of the table shared; placement, people, light and motion per "
           "session)" if site is not None else ", each in a room of its own")
        + ". Each recording starts undraped; the robots are then draped in place and the motion "
        "is replayed and continued under the drape.\n"
    )
    if segmentor == "model":
        add(
            "**Bootstrap (stands in for SAM 2).** The paper segments the undraped robot with the "
            "foundation model SAM 2 to localise it before draping. roboseg ships no SAM 2, so a "
            "calibrated lab rig stands in: the `lab_*` recordings are annotated from their own "
            "`/tf_static` calibration, a small segmenter is trained on their undraped frames and "
            "exported, and that model segments the undraped phase of every operating-room "
            "recording. Nothing downstream reads the operating-room ground truth except the "
            "evaluation on this page.\n"
        )
    else:
        add(
            "**Undraped masks without a model.** The paper segments the undraped robot with the "
            f"foundation model SAM 2; here `segmentor={segmentor}` makes the masks of every "
            "operating-room recording's undraped phase from that recording alone (no lab rig, "
            "no trained model). Nothing downstream reads the operating-room ground truth "
            "except the evaluation on this page.\n"
        )
    rows = lab_rows(layout.lab) if segmentor == "model" else []
    rows += [[r.stem, "operating room", r.split, r.robots, r.seed] for r in layout.study]
    add(md_table(["recording", "role", "split", "robots", "seed (camera placement)"], rows))

    # annotation quality
    add("\n## Self-annotation quality\n")
    ann = read_json(out / "metrics" / "annotation.json")
    if ann is None:
        add("_not measured (stage annotation_quality did not run)_\n")
    else:
        add(
            "The undraped phase of each operating-room recording is registered with the camera "
            f"swarm + SDR on the masks of `undraped.segmentor={segmentor}` (column *undraped "
            "masks*; *+ self-training N, kept k*: N rounds of fine-tuning a segmenter on the "
            "recording's own frames labelled by the estimate, then registering again; *+ GrabCut "
            "N, kept k*: N rounds of cutting each frame by GrabCut from the estimate's "
            "silhouette, then registering again; round k's estimate kept, 0 being "
            "the first registration); the "
            f"{cfg.annotate.phase} phase is then annotated with that estimate "
            "(`roboseg-annotate calibration=…`). Columns: the estimate's error against the "
            "simulator's `/tf_static` over every undraped frame (tool centre: median and "
            "quartiles; robot base L0; rotation; *by round*: the tool-centre median of every "
            "round's estimate, the kept one in bold), and the IoU of the self-annotated masks "
            "against the simulator's ground-truth masks (`robot_mask_gt`) per frame.\n"
        )
        rows = []
        for row in ann["rows"]:
            a = row["annotation"]
            for reg in row["registration"]:
                rows.append([
                    row["recording"], row["split"], reg["robot"], *_estimate_cells(reg),
                    a["frames"], f"{fmt(a['iou_mean'], 3)} ± {fmt(a['iou_std'], 3)}",
                    fmt(a["iou_min"], 3),
                ])
        add(md_table(["recording", "split", "robot", *ESTIMATE_COLUMNS, "annotated frames",
                      "IoU vs simulator", "min IoU"], rows))
        rounds = [{**reg, "label": f"{row['recording']} {reg['robot']}"}
                  for row in ann["rows"] for reg in row["registration"]]
        if rounds_plot(rounds, figures / "self_training_rounds.png"):
            add(f"\n![tool-centre error by self-training round]({rel}/self_training_rounds.png)\n")

    walk = read_json(out / "metrics" / "walkers.json")
    if walk is not None:
        add("\n### People walking through the view\n")
        add(
            f"The recordings {', '.join(f'`{r.stem}`' for r in layout.walkers)} again, with "
            f"{cfg.walkers.people} people walking across the view during the undraped phase "
            "(`roboseg-simulate walkers=N`: the same room, camera placement and robot motion), "
            "their undraped phase registered as above; errors against the simulator's "
            "`/tf_static` over every undraped frame.\n"
        )
        rows = [[r["recording"], r["people_walking"], r["robot"], *_estimate_cells(r)]
                for r in walk["rows"]]
        add(md_table(["recording", "people walking", "robot", *ESTIMATE_COLUMNS], rows))

    # segmentation
    add("\n## Segmentation (Table S4 columns)\n")
    table = out / "eval" / "iou_table.md"
    labels = "the simulator's ground-truth masks" if cfg.evaluate.labels == "gt" else (
        "the self-annotated masks")
    add(
        f"IoU (mean ± std over frames) on the {cfg.annotate.phase} frames of the two-robot test "
        f"recording against {labels}. Models of the `{cfg.recipe}` recipe, all trained on the "
        "self-annotated operating-room recordings"
        + (" and the lab bootstrap's training recordings (`lab.in_training`)"
           if lab_in_training(cfg) else "")
        + ", starting from "
        + ("the lab bootstrap's weights" if model_init(cfg, warn=False) == "bootstrap"
           else "random weights")
        + "; `val IoU` is the best checkpoint's IoU on the validation recording (self-annotated "
        "labels).\n"
    )
    add(table.read_text() if table.is_file() else "_not evaluated_\n")
    scales = draped_scales(cfg)
    scaled = out / "eval_scales" / "iou_table.md"
    if scales != [1.0] and scaled.is_file():
        add(
            "\nThe same models and frames, each image segmented at "
            f"{', '.join(f'{x:g}' for x in scales)} times the model's input size and "
            "the probabilities averaged, as the draped test registrations below segment them "
            "(`register.draped_scales`):\n\n" + scaled.read_text()
        )
    # steps: as trained / trainer.max_steps (fewer: fitted to or cut by trainer.max_time)
    add("\n" + md_table(
        ["model", "experiment", "overrides", "steps", "val IoU"],
        [[m.name, m.experiment, " ".join(f"`{o}`" for o in m.overrides) or "-",
          _printed(logs, m.name, "steps"), _val_iou(logs, m.name)] for m in layout.models],
    ))
    for png in sorted((out / "eval").glob("qualitative_*.png")):
        name = copy_figure(png, figures, png.name)
        if name:
            add(f"\n![{png.stem}]({rel}/{name})\n")
    add("\nQualitative rows: image | ground truth | prediction | difference.\n")

    # localisation
    add("\n## Localisation of the draped test recording\n")
    loc = read_json(out / "metrics" / "localisation.json")
    chosen = cfg.localise[str(cfg.recipe)]
    added = " ".join(f"`{o}`" for o in draped_settings(cfg)) or "none"
    add(
        f"SDR with the 3-channel model `{chosen.sdr}`, SDR with in-context prior with the "
        f"4-channel model `{chosen.sdr_prior}`, {cfg.register.configs} stereo configurations "
        "from the draped phase, each robot on its own: the masks contain both robots, so each "
        "fit is refined on the pixels near its own estimate, and refitted without the other "
        "robot's pixels when the other robot's joints explain it better "
        f"(`other_robots_margin`). Settings added to these registrations: {added}"
        + (" (`model_scales`: each image segmented at these multiples of the model's input "
           "size, probabilities averaged; the test robots stand farther from the camera than "
           "in the training sessions and look smaller)" if scales != [1.0] else "")
        + ". Errors against the simulator's `/tf_static` at every link origin over every draped "
        "frame. For scale, the paper's two-robot clinical recording "
        "(camera wall-mounted 2.6 m from the robots' bases, error as the deviation from the "
        "undraped localisation) ended at medians of 9.6 / 3.9 mm at the base (L0) and "
        "23.4 / 16.6 mm at the end effector with SDR / SDR with prior; its 1.3-4.8 mm at the "
        "tool centre are the single-robot benchmark with a bedside camera.\n"
    )
    entries = []
    if ann is not None:
        for row in ann["rows"]:
            for reg in row["registration"]:
                entries.append({**reg, "phase": "undraped",
                                "label": f"undraped {row['recording']} {reg['robot']}"})
    rows = []
    for reg in (loc or {}).get("rows", []):
        if "error" in reg:
            rows.append([reg["method"], reg["robot"], reg["error"], "-", "-", "-", "-"])
            continue
        entries.append({**reg, "phase": "draped", "label": f"draped {reg['method']} "
                                                            f"{reg['robot']}"})
        iou = reg.get("residual_iou") or {}
        rows.append([
            reg["method"], reg["robot"], "yes" if reg["converged"] else "**no**",
            " / ".join(fmt(v, 3) for v in iou.values()) or "-",
            f"{fmt(reg['tool_median_mm'], 1)} ({fmt(reg['tool_q1_mm'], 1)}–"
            f"{fmt(reg['tool_q3_mm'], 1)})",
            fmt(reg["link_median_mm"][0], 1), fmt(reg["rotation_deg"], 2),
        ])
    add(md_table(["method", "robot", "converged", "residual IoU (left / right)",
                  "tool error [mm]", "base error [mm]", "rotation [°]"], rows) if rows else
        "_not registered_\n")
    if entries:
        localisation_plot(entries, figures / "localisation.png")
        add(f"\n![localisation errors]({rel}/localisation.png)\n")

    # breathing
    add("\n## Breathing motion (tracking demo)\n")
    track = out / "track"
    if copy_figure(track / "breathing.png", figures, "breathing.png"):
        add(
            "A simulated patient with AprilTags breathes under a stereo camera (1920×1080); "
            "`roboseg-track` triangulates the tags and fits the three-harmonic breathing model "
            "over the last 15 s.\n"
        )
        add(f"\n![breathing]({rel}/breathing.png)\n")
        fit = yaml.safe_load((track / "breathing.yaml").read_text()) if (
            track / "breathing.yaml").is_file() else {}
        truth = breathing_truth(layout.breathing) if layout.breathing.is_file() else {}
        tag = (fit.get("tags") or {}).get(10) or {}
        amps = tag.get("amplitudes_mm") or {}
        rows = [["ω0 [rad/s]", fmt(tag.get("omega0"), 4), fmt(truth.get("omega0"), 4)]]
        rows += [[f"{a} amplitude [mm]", fmt(amps.get(a), 3),
                  fmt(truth.get(f"amplitude_{a}_mm"), 3)] for a in ("ML", "CC", "AP")]
        add("\n" + md_table(["tag 10", "fitted", "simulated truth"], rows))
    else:
        add("_no breathing plot (stage track did not finish)_\n")

    # benches
    add("\n## Benchmarks\n")
    add(
        "Each benchmark as it printed its figures, with the command (run from the project "
        "root) and the machine. Wall-clock figures depend on the machine's load at the time.\n"
    )
    for step in plan:
        if not step.name.startswith("bench_"):
            continue
        command, where = _stage_log_header(logs, step.name)
        add(f"\n### {step.name.removeprefix('bench_')}\n")
        command = portable(command, Path.cwd())
        add(f"- command: `{command}`\n- ran: {where}\n- status: {_status(stages, step.name)}\n")
        text = portable(_stdout(logs, step.name), Path.cwd())
        add("\n```text\n" + (text or "(no output)") + "\n```\n")

    # run
    add("\n## Run\n")
    rows = []
    total = 0.0
    for step in plan:
        seconds, _ = stages.status(step.name)
        total += seconds or 0.0
        rows.append([step.name, fmt(seconds, 0), _status(stages, step.name)])
    add(f"Stage times (seconds, each from the run that did it); all stages together "
        f"{total / 60:.1f} min. Logs: `{portable(str(out / 'logs'), Path.cwd())}`.\n\n")
    add(md_table(["stage", "seconds", "status"], rows))
    write_text_atomic(layout.page, "\n".join(parts))
    return layout.page
