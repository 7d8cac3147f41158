"""The evaluation driver: models × test frames of an annotated dataset → IoU table, per-frame IoU,
qualitative figures.

Every model, ONNX file or Lightning checkpoint, goes through the same path:
:func:`roboseg.segmentor.preprocess` (anisotropic resize to the model's input size, normalisation,
prior channel) → logits → sigmoid → bilinear resize back to the image size → threshold. So the
numbers of a checkpoint and of its export are comparable. With ``scales`` every image is segmented
at those multiples of the model's input size and the probabilities averaged, as the registration
runtime's ``model_scales`` does.

4-channel models are evaluated twice: with a zero prior and with the in-context prior, the union of
the robots' silhouettes rendered at poses perturbed like in training
(:func:`roboseg.augment.prior.sample_pose_perturbation`, ``render_hard``) from the recording's
calibration (``/tf_static``), joints and left intrinsics; seeded per run.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from roboseg.errors import DatasetError, ModelFileError, RecordingError
from roboseg.evaluation.metrics import (
    ERROR_BANDS_PX,
    TableRow,
    binary_iou,
    error_bands,
    qualitative_figure,
)
from roboseg.recording.topics import ROBOT_MASK, ROBOT_MASK_GT
from roboseg.segmentor import SegmentorMeta, check_scales, multi_scale_probs

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "roboseg-annotations/1"
#: ``labels`` setting → mask kind read from ``/<camera>/left/<kind>/compressed``.
LABEL_KINDS = {"annotated": ROBOT_MASK, "gt": ROBOT_MASK_GT}
PRIORS = ("zero", "perturbed")
#: Frames of a recording that evaluation keeps: from ``draped_from_ns`` on, before it, or all.
PHASES = ("all", "draped", "undraped")


# --- dataset ---------------------------------------------------------------------------------


def load_manifest(root: str | Path) -> dict[str, Any]:
    """The ``manifest.json`` of an annotated dataset folder (format ``roboseg-annotations/1``)."""
    path = Path(root) / MANIFEST
    if not path.is_file():
        raise DatasetError(f"data.root {root}: no {MANIFEST} (run roboseg-annotate first)")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable manifest ({exc})") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise DatasetError(f"{path}: format is not {MANIFEST_FORMAT!r}")
    return manifest


def split_recordings(manifest: Mapping[str, Any], root: str | Path, split: str) -> list[Path]:
    """Files of the recordings of one split, in manifest order (a missing file is an error)."""
    files = [Path(root) / r["file"] for r in manifest.get("recordings", []) if r["split"] == split]
    if not files:
        raise DatasetError(f"data.root {root}: no recording in split {split!r}")
    for f in files:
        if not f.is_file():
            raise DatasetError(f"{f}: listed in {MANIFEST} but missing")
    return files


@dataclass
class EvalFrame:
    """One test frame: left RGB image ``[H,W,3]`` uint8, label mask ``[H,W]`` bool, and the
    perturbed-pose prior ``[H,W]`` float {0,1} (None unless a 4-channel model needs it)."""

    file: str
    stamp_ns: int
    image: np.ndarray
    target: np.ndarray
    prior: np.ndarray | None = None


@dataclass
class PriorRenderer:
    """Renders the in-context prior of a recording's frames (paper step 1, like training).

    ``translation_range`` in metres per camera axis, ``rotation_deg`` the exact rotation angle.
    """

    urdf: str | None = None
    translation_range: tuple[float, float] = (0.0, 0.05)
    rotation_deg: float = 5.0
    reduction: float = 0.0
    seed: int = 0
    _robot: Any = field(default=None, init=False, repr=False)
    _gen: torch.Generator | None = field(default=None, init=False, repr=False)

    def robot(self) -> Any:
        if self._robot is None:
            from roboseg.robot import load_robot

            self._robot = load_robot(self.urdf, reduction=self.reduction)
            self._gen = torch.Generator().manual_seed(int(self.seed))
        return self._robot

    def render(
        self,
        K: np.ndarray,  # noqa: N803
        size: tuple[int, int],
        poses: Mapping[str, np.ndarray],
        joints: Mapping[str, np.ndarray],
    ) -> np.ndarray:
        """Union ``[H,W]`` float32 of the robots' silhouettes, each at ``T_cam_base`` (4x4 m,
        left optical frame) perturbed by a fresh sample; ``size`` is ``(H, W)`` pixels."""
        from roboseg.augment.prior import InContextPrior

        robot = self.robot()
        names = sorted(poses)
        q = torch.as_tensor(np.stack([joints[r] for r in names]), dtype=torch.float32)
        T = torch.as_tensor(np.stack([poses[r] for r in names]), dtype=torch.float32)
        verts = robot.posed_vertices(q)
        prior = InContextPrior(self.translation_range, self.rotation_deg)
        sil = prior(
            verts,
            robot.faces,
            torch.as_tensor(K, dtype=torch.float32),
            T,
            size[0],
            size[1],
            self._gen,
        )
        return sil.amax(dim=0)[0].numpy().astype(np.float32)


def robot_poses(reader: Any, root_link: str, left_frame: str) -> dict[str, np.ndarray]:
    """``T_left_base`` (4x4, metres) of every robot of a recording from ``/tf_static``."""
    return {r: reader.lookup(left_frame, f"{r}/{root_link}") for r in reader.robots}


def iter_frames(
    files: Sequence[Path],
    *,
    labels: str = "annotated",
    camera: str = "camera",
    max_frames: int | None = None,
    prior: PriorRenderer | None = None,
    draped_from: Mapping[str, int | None] | None = None,
    phase: str = "all",
) -> Iterator[EvalFrame]:
    """Stream the left frames of ``files`` with their label masks (and priors if ``prior``).

    ``phase`` ``draped`` / ``undraped`` keeps the frames at or after / before the first draped
    stamp (ns) ``draped_from[file name]``; recordings without one (real data) keep every frame.
    """
    from roboseg.recording import RecordingReader

    if labels not in LABEL_KINDS:
        raise DatasetError(f"labels must be one of {sorted(LABEL_KINDS)}, got {labels!r}")
    mask_name = f"left/{LABEL_KINDS[labels]}"
    count = 0
    for path in files:
        joint_order = None
        if prior is not None:
            robot = prior.robot()
            with RecordingReader(path, camera=camera) as probe:
                joint_order = {r: robot.joint_names for r in probe.robots}
        try:
            reader = RecordingReader(
                path, camera=camera, mask_topics=[mask_name], joint_order=joint_order
            )
        except RecordingError as exc:
            if labels == "gt":
                raise DatasetError(f"labels=gt needs simulator masks: {exc}") from exc
            raise
        with reader:
            log.info("evaluating %s (%d left images)", path.name, len(reader))
            K, _, _, left_frame = reader.camera_info("left")
            poses = robot_poses(reader, prior.robot().root_link, left_frame) if prior else {}
            start = (draped_from or {}).get(path.name)
            for frame in reader.frames():
                if max_frames is not None and count >= max_frames:
                    return
                if phase != "all" and start is not None and (
                        (frame.stamp_ns >= start) != (phase == "draped")):
                    continue
                h, w = frame.left.shape[:2]
                rendered = prior.render(K, (h, w), poses, frame.joints) if prior else None
                yield EvalFrame(
                    path.name, frame.stamp_ns, frame.left, frame.masks[mask_name], rendered
                )
                count += 1


# --- models ----------------------------------------------------------------------------------


class EvalModel(Protocol):
    """What evaluation needs of a model: its metadata and logits of a preprocessed batch."""

    meta: SegmentorMeta

    def logits(self, x: np.ndarray) -> np.ndarray: ...


class CheckpointModel:
    """A Lightning checkpoint run in PyTorch (CPU) behind the :class:`EvalModel` interface."""

    def __init__(self, path: str | Path) -> None:
        from roboseg.training import SegmentationModule

        self.path = Path(path)
        module = SegmentationModule.load_from_checkpoint(self.path, map_location="cpu")
        self.net = module.net.eval()
        self.meta = SegmentorMeta(**module.export_metadata())

    def logits(self, x: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return self.net(torch.from_numpy(np.ascontiguousarray(x, np.float32))).numpy()


def load_model(
    path: str | Path,
    overrides: Mapping[str, object] | None = None,
    scales: Sequence[float] = (1.0,),
) -> EvalModel:
    """An ``.onnx`` file (metadata ``overrides`` allowed) or a ``.ckpt`` Lightning checkpoint.
    ``scales`` other than ``(1.0,)`` are checked against the ONNX graph (dynamic size needed)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"model {path}: no such file")
    if path.suffix == ".ckpt":
        check_scales(scales, str(path))
        return CheckpointModel(path)
    if path.suffix == ".onnx":
        from roboseg.segmentor import OnnxSegmentor

        return OnnxSegmentor(path, overrides=overrides or None, scales=scales)
    raise ModelFileError(f"model {path}: expected a .onnx or .ckpt file")


def predict_probs(
    model: EvalModel,
    image: np.ndarray,
    prior: np.ndarray | None,
    scales: Sequence[float] = (1.0,),
) -> np.ndarray:
    """Robot probability ``[H,W]`` of one RGB image at the image's own size; with several
    ``scales`` (factors of the model's input size) the mean over them."""
    return multi_scale_probs(
        model.logits, model.meta, image[None], None if prior is None else prior[None], scales
    )[0]


def runs_of(meta: SegmentorMeta) -> tuple[str, ...]:
    """Prior settings a model is evaluated with: ``-`` for RGB models, zero and perturbed else."""
    return PRIORS if meta.in_channels == 4 else ("-",)


def aspect_differs(
    image_hw: tuple[int, int], source_hw: tuple[int, int], tol: float = 0.01
) -> bool:
    """True when two ``(H, W)`` sizes' aspect ratios W/H differ by more than ``tol`` (relative)."""
    a = image_hw[1] / image_hw[0]
    b = source_hw[1] / source_hw[0]
    return abs(a / b - 1.0) > tol


# --- the driver ------------------------------------------------------------------------------


@dataclass
class Run:
    """One row of the table: a model evaluated with one prior setting."""

    name: str
    model: EvalModel
    prior: str
    ious: list[float] = field(default_factory=list)
    figure: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]] = field(default_factory=list)
    # error pixels by distance to the true outline (metrics.error_bands), summed over frames
    misses: np.ndarray = field(default_factory=lambda: np.zeros(len(ERROR_BANDS_PX), np.int64))
    false_pos: np.ndarray = field(default_factory=lambda: np.zeros(len(ERROR_BANDS_PX), np.int64))
    true_pixels: int = 0


def figure_indices(figure_frames: Sequence[int] | int | None, n: int) -> set[int]:
    """Frame indices shown in the figures: explicit indices, or ``k`` evenly spaced (default 3)."""
    if n <= 0:
        return set()
    if figure_frames is None or isinstance(figure_frames, int):
        k = min(n, 3 if figure_frames is None else int(figure_frames))
        return {round(i * (n - 1) / max(1, k - 1)) for i in range(k)} if k > 1 else {0}
    return {int(i) for i in figure_frames if 0 <= int(i) < n}


def evaluate_models(
    models: Sequence[str | Path],
    root: str | Path,
    out: str | Path,
    *,
    split: str = "test",
    labels: str = "annotated",
    max_frames: int | None = None,
    figure_frames: Sequence[int] | int | None = None,
    overrides: Mapping[str, object] | None = None,
    prior: PriorRenderer | None = None,
    source_size: tuple[int, int] | None = None,
    progress: bool = True,
    phase: str = "all",
    scales: Sequence[float] = (1.0,),
) -> list[TableRow]:
    """Evaluate ``models`` on ``split`` of the annotated dataset ``root``; write ``out/``
    ``iou_table.md``, ``iou_table.csv``, ``per_frame_iou.csv``, ``error_bands.md`` (missed and
    false-positive pixels by distance to the true outline, as fractions of the true robot area)
    and ``qualitative_<row>.png``.

    ``source_size`` ``(H, W)``: image size the models were trained from (for the aspect check).
    ``phase``: ``all`` frames, or only the ``draped`` / ``undraped`` ones (see :func:`iter_frames`).
    ``scales``: factors of each model's input size, probabilities averaged (:func:`predict_probs`).
    """
    if phase not in PHASES:
        raise DatasetError(f"phase must be one of {PHASES}, got {phase!r}")
    manifest = load_manifest(root)
    files = split_recordings(manifest, root, split)
    loaded = [(Path(m), load_model(m, overrides, scales)) for m in models]
    if not loaded:
        raise DatasetError("models: empty list; give models=[A.onnx,B.ckpt]")
    runs: list[Run] = []
    for path, model in loaded:
        for p in runs_of(model.meta):
            runs.append(Run(path.name, model, p))
    needs_prior = any(r.prior == "perturbed" for r in runs)
    if needs_prior and prior is None:
        prior = PriorRenderer(urdf=manifest.get("robot_urdf"))
    frames_total = sum(
        int(r.get("frames_kept", 0)) for r in manifest["recordings"] if r["split"] == split
    )
    n_expected = frames_total if max_frames is None else min(frames_total, int(max_frames))
    shown = figure_indices(figure_frames, n_expected)
    per_frame: list[tuple[str, str, str, int, float]] = []
    warned: set[str] = set()
    frames = iter_frames(
        files,
        labels=labels,
        camera=str(manifest.get("camera", "camera")),
        max_frames=max_frames,
        prior=prior if needs_prior else None,
        draped_from={r["file"]: r.get("draped_from_ns") for r in manifest["recordings"]},
        phase=phase,
    )
    bar = _progress(frames, n_expected, progress)
    for i, frame in enumerate(bar):
        for run in runs:
            _note_resize(run, frame.image.shape[:2], source_size, warned)
            pr = frame.prior if run.prior == "perturbed" else None
            probs = predict_probs(run.model, frame.image, pr, scales)
            pred = probs > run.model.meta.threshold
            iou = binary_iou(pred, frame.target)
            run.ious.append(iou)
            misses, false_pos = error_bands(pred, frame.target)
            run.misses += misses
            run.false_pos += false_pos
            run.true_pixels += int(np.count_nonzero(frame.target))
            per_frame.append((run.name, run.prior, frame.file, frame.stamp_ns, iou))
            if i in shown:
                run.figure.append((frame.image, frame.target, pred, f"{frame.file} @{i}"))
    if not runs[0].ious:
        what = "" if phase == "all" else f" {phase}"
        raise DatasetError(
            f"data.root {root}: split {split!r} yielded no{what} frames with labels")
    rows = [_row(r) for r in runs]
    write_outputs(Path(out), rows, runs, per_frame)
    return rows


def _progress(frames: Iterator[EvalFrame], total: int, enabled: bool) -> Iterator[EvalFrame]:
    if not enabled:
        return frames
    from tqdm import tqdm

    # a bar on a terminal; elsewhere (logs, CI) one line per recording from iter_frames
    return iter(tqdm(frames, total=total, desc="evaluating", unit="frame", disable=None))


def _note_resize(
    run: Run, hw: tuple[int, int], source: tuple[int, int] | None, warned: set[str]
) -> None:
    """Log once per model that images are squashed to its input size (and if aspects differ)."""
    meta = run.model.meta
    key = run.name
    if key in warned or hw == (meta.input_height, meta.input_width):
        return
    warned.add(key)
    log.info(
        "%s: images %dx%d resized to the model input %dx%d (anisotropic, like training)",
        key,
        hw[1],
        hw[0],
        meta.input_width,
        meta.input_height,
    )
    if source is not None and aspect_differs(hw, source):
        log.warning(
            "%s: test images are %dx%d but training images were %dx%d; the squash "
            "distorts them differently than in training",
            key,
            hw[1],
            hw[0],
            source[1],
            source[0],
        )


def _row(run: Run) -> TableRow:
    m = run.model.meta
    encoder = m.encoder.removeprefix("unet_")  # preset names: unet_<encoder>
    return TableRow(
        model=run.name,
        encoder=encoder,
        params_m=m.params_m,
        ious=run.ious,
        cmm=m.cmm,
        in_channels=m.in_channels,
        dataset=m.dataset or "?",
        prior=run.prior,
    )


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in text).strip("_")


def write_outputs(
    out: Path,
    rows: Sequence[TableRow],
    runs: Sequence[Run],
    per_frame: Sequence[tuple[str, str, str, int, float]],
) -> None:
    """The tables, the per-frame CSV and one qualitative figure per row, written under ``out``."""
    from roboseg.evaluation.metrics import error_bands_markdown, table_csv, table_markdown

    out.mkdir(parents=True, exist_ok=True)
    _write_text(out / "iou_table.md", table_markdown(rows))
    _write_text(out / "iou_table.csv", table_csv(rows))
    _write_text(out / "error_bands.md", error_bands_markdown([
        (r.name if r.prior == "-" else f"{r.name} ({r.prior} prior)", r.misses, r.false_pos,
         r.true_pixels) for r in runs]))
    lines = [("model", "prior", "file", "stamp", "iou")]
    lines += [
        (m, p, f, str(s), "nan" if math.isnan(v) else f"{v:.6f}") for m, p, f, s, v in per_frame
    ]
    tmp = out / ".per_frame_iou.csv.part"
    with open(tmp, "w", newline="") as fh:
        csv.writer(fh).writerows(lines)
    tmp.replace(out / "per_frame_iou.csv")
    for run in runs:
        if run.figure:
            images, targets, preds, titles = zip(*run.figure, strict=True)
            suffix = "" if run.prior == "-" else f"_{run.prior}"
            name = _slug(Path(run.name).stem + suffix)
            qualitative_figure(
                images, targets, preds, out / f"qualitative_{name}.png", row_titles=titles
            )


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.part")
    tmp.write_text(text)
    tmp.replace(path)
