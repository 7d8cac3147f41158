"""The light runtime segmentor: an exported roboseg ONNX model behind numpy in, numpy out.

Needs only numpy, OpenCV and onnxruntime (no torch, Lightning, smp, kornia or Hydra), so the
registration runtime can run in the operating room without the training stack.

The model file describes itself in its ONNX ``metadata_props`` (written by ``roboseg-export``):
input size, channels, normalisation and threshold. Images of any size are resized (anisotropically,
as in training) to the model's input size and the probabilities are resized back.

Multi-scale inference (``scales``): the probabilities are averaged over inputs of the model's
size times each scale (a fully convolutional model takes any size). A robot much farther from
the camera than in the training recordings looks smaller than the model learned it; larger
inputs show it at the size it was trained on.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from roboseg.errors import ModelFileError

log = logging.getLogger(__name__)

#: Metadata keys every roboseg ONNX file carries (values are strings; lists as JSON).
METADATA_KEYS = (
    "roboseg_version",
    "encoder",
    "in_channels",
    "input_height",
    "input_width",
    "mean",
    "std",
    "threshold",
    "trained_on",
)


@dataclass(frozen=True)
class SegmentorMeta:
    """What a model needs to be used correctly, read from its ONNX metadata."""

    encoder: str
    in_channels: int
    input_height: int
    input_width: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    threshold: float
    trained_on: str = ""
    roboseg_version: str = ""
    # Descriptive only (Table S4 columns): parameters in millions, cut-mix-merge, dataset subset.
    params_m: float = 0.0
    cmm: bool | None = None
    dataset: str = ""
    # test-time augmentation inside the graph ("flip": logits of image and mirror averaged)
    tta: str = ""

    @classmethod
    def from_props(cls, props: Mapping[str, str], source: str = "model") -> SegmentorMeta:
        """Parse ``metadata_props``; raise :class:`ModelFileError` naming the missing keys."""
        missing = [k for k in METADATA_KEYS if k not in props and k != "roboseg_version"]
        if missing:
            raise ModelFileError(
                f"{source}: not a roboseg ONNX model (metadata lacks {', '.join(missing)}); "
                "pass the missing values as overrides if you know them"
            )
        try:
            mean = tuple(float(x) for x in json.loads(props["mean"]))
            std = tuple(float(x) for x in json.loads(props["std"]))
            meta = cls(
                encoder=str(props["encoder"]),
                in_channels=int(props["in_channels"]),
                input_height=int(props["input_height"]),
                input_width=int(props["input_width"]),
                mean=mean,  # type: ignore[arg-type]
                std=std,  # type: ignore[arg-type]
                threshold=float(props["threshold"]),
                trained_on=str(props.get("trained_on", "")),
                roboseg_version=str(props.get("roboseg_version", "")),
                params_m=float(props.get("params_m", 0.0)),
                cmm=None if props.get("cmm", "") == "" else props["cmm"] == "1",
                dataset=str(props.get("dataset", "")),
                tta=str(props.get("tta", "")),
            )
        except (ValueError, TypeError, json.JSONDecodeError) as exc:
            raise ModelFileError(f"{source}: malformed roboseg metadata ({exc})") from exc
        if meta.in_channels not in (3, 4) or len(meta.mean) != 3 or len(meta.std) != 3:
            raise ModelFileError(
                f"{source}: metadata says in_channels={meta.in_channels}, mean={meta.mean}, "
                f"std={meta.std}; expected 3 or 4 channels and 3 RGB statistics"
            )
        return meta

    def to_props(self) -> dict[str, str]:
        """The metadata as ONNX ``metadata_props`` strings."""
        return {
            "roboseg_version": self.roboseg_version,
            "encoder": self.encoder,
            "in_channels": str(self.in_channels),
            "input_height": str(self.input_height),
            "input_width": str(self.input_width),
            "mean": json.dumps(list(self.mean)),
            "std": json.dumps(list(self.std)),
            "threshold": repr(self.threshold),
            "trained_on": self.trained_on,
            "params_m": f"{self.params_m:.3f}",
            "cmm": "" if self.cmm is None else str(int(self.cmm)),
            "dataset": self.dataset,
            "tta": self.tta,
        }


def preprocess(
    images: np.ndarray, meta: SegmentorMeta, prior: np.ndarray | None = None
) -> np.ndarray:
    """RGB uint8 ``[N,H,W,3]`` (+ optional prior ``[N,H,W]`` in [0,1]) → model input ``[N,C,h,w]``.

    Images are resized to the model's input size (anisotropic, like training), scaled to [0, 1]
    and normalised with the model's mean/std. A 4-channel model gets the prior as its 4th channel
    (zeros when ``prior`` is None: "no localisation estimate yet").
    """
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"images must be uint8 [N,H,W,3] RGB, got {images.dtype} {images.shape}")
    size = (meta.input_width, meta.input_height)
    mean = np.asarray(meta.mean, np.float32)
    std = np.asarray(meta.std, np.float32)
    out = np.empty((len(images), meta.in_channels, meta.input_height, meta.input_width), np.float32)
    for i, img in enumerate(images):
        x = cv2.resize(img, size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        out[i, :3] = ((x - mean) / std).transpose(2, 0, 1)
        if meta.in_channels == 4:
            if prior is None:
                out[i, 3] = 0.0
            else:
                p = np.asarray(prior[i], np.float32)
                out[i, 3] = cv2.resize(p, size, interpolation=cv2.INTER_NEAREST)
    return out


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # overflow-free logistic


def scaled_sizes(meta: SegmentorMeta, scales: Sequence[float]) -> list[tuple[int, int]]:
    """Input sizes ``(h, w)`` px, one per scale: the model's own size at 1, else its size times
    the scale rounded to the nearest even number of pixels."""
    h, w = meta.input_height, meta.input_width
    return [
        (h, w) if s == 1.0 else (max(2, 2 * round(h * s / 2)), max(2, 2 * round(w * s / 2)))
        for s in scales
    ]


def check_scales(scales: Sequence[float], source: str) -> tuple[float, ...]:
    """``scales`` as a tuple of floats; :class:`ModelFileError` naming ``source`` unless every
    factor is finite and > 0 and there is at least one."""
    try:
        out = tuple(float(x) for x in scales)
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"{source}: scales must be numbers, got {scales!r}") from exc
    if not out or not all(np.isfinite(x) and x > 0 for x in out):
        raise ModelFileError(
            f"{source}: scales must be one or more positive factors, got {list(scales)}"
        )
    return out


def multi_scale_probs(
    logits: Callable[[np.ndarray], np.ndarray],
    meta: SegmentorMeta,
    images: np.ndarray,
    prior: np.ndarray | None = None,
    scales: Sequence[float] = (1.0,),
    batch_size: int = 8,
) -> np.ndarray:
    """Robot probabilities ``[N,H,W]`` float32 of RGB uint8 ``images`` ``[N,H,W,3]`` at their own
    size: each batch preprocessed at the model's input size times each scale
    (:func:`scaled_sizes`), run through ``logits`` (``[N,C,h,w]`` → ``[N,1,h,w]``), and the
    probabilities resized back and averaged over the scales."""
    n, h, w = images.shape[:3]
    out = np.zeros((n, h, w), np.float32)
    sizes = scaled_sizes(meta, scales)
    for size in sizes:
        sized = replace(meta, input_height=size[0], input_width=size[1])
        for s in range(0, n, batch_size):
            sl = slice(s, min(n, s + batch_size))
            x = preprocess(images[sl], sized, None if prior is None else prior[sl])
            probs = _sigmoid(logits(x)[:, 0])
            for i, p in enumerate(probs):
                out[s + i] += cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR)
    if len(sizes) > 1:
        out /= len(sizes)
    return out


class OnnxSegmentor:
    """Robot segmentation with an exported roboseg ONNX model (onnxruntime, CPU by default).

    Args:
        path: the ``.onnx`` file.
        overrides: metadata values to use instead of (or, for a foreign model, in place of) the
            file's; keys as in :data:`METADATA_KEYS`.
        providers: onnxruntime execution providers; default CUDA when available, else CPU.
        threads: intra-op threads (None: onnxruntime's default).
        scales: factors of the model's input size (each > 0) at which every image is segmented;
            the probabilities are averaged. ``(1.0,)``: the input size alone.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        overrides: Mapping[str, object] | None = None,
        providers: Sequence[str] | None = None,
        threads: int | None = None,
        scales: Sequence[float] = (1.0,),
    ) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.is_file():
            raise ModelFileError(f"{self.path}: no such ONNX file")
        self.scales = check_scales(scales, str(self.path))
        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = threads
        available = ort.get_available_providers()
        if providers is None:
            providers = [
                p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available
            ]
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=list(providers))
        except Exception as exc:  # onnxruntime raises its own exception types
            raise ModelFileError(f"{self.path}: onnxruntime cannot load it ({exc})") from exc
        props = dict(self.session.get_modelmeta().custom_metadata_map)
        props.update(
            {k: v if isinstance(v, str) else json.dumps(v) for k, v in (overrides or {}).items()}
        )
        self.meta = SegmentorMeta.from_props(props, source=str(self.path))
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        channels = inp.shape[1]
        if isinstance(channels, int) and channels != self.meta.in_channels:
            raise ModelFileError(
                f"{self.path}: metadata says {self.meta.in_channels} input channels but the graph "
                f"takes {channels}"
            )
        fixed = [d for d in inp.shape[2:] if isinstance(d, int)]
        if fixed and self.sizes() != [(self.meta.input_height, self.meta.input_width)]:
            raise ModelFileError(
                f"{self.path}: the graph's input size is fixed ({inp.shape[2:]}); "
                f"scales={list(self.scales)} needs a model exported with dynamic height and width"
            )

    def sizes(self) -> list[tuple[int, int]]:
        """Input sizes ``(h, w)`` px, one per scale (:func:`scaled_sizes`)."""
        return scaled_sizes(self.meta, self.scales)

    @property
    def in_channels(self) -> int:
        return self.meta.in_channels

    def logits(self, x: np.ndarray) -> np.ndarray:
        """Raw model output ``[N,1,h,w]`` for an already preprocessed batch ``[N,C,h,w]``."""
        return self.session.run(None, {self.input_name: np.ascontiguousarray(x, np.float32)})[0]

    def predict(
        self,
        images: np.ndarray | Sequence[np.ndarray],
        prior: np.ndarray | Sequence[np.ndarray] | None = None,
        *,
        batch_size: int = 8,
    ) -> np.ndarray:
        """Robot probabilities ``[N,H,W]`` float32 at each image's own size.

        Args:
            images: RGB uint8 ``[N,H,W,3]`` (or a sequence of ``[H,W,3]`` of equal size).
            prior: in-context prior ``[N,H,W]`` in [0,1] (silhouette rendered at the current pose
                estimate), used by 4-channel models; None means a zero prior.
            batch_size: images per onnxruntime call.

        With several ``scales`` the probabilities are the mean over the input sizes.
        """
        images = np.asarray(images)
        if images.ndim == 3:
            images = images[None]
            prior = None if prior is None else np.asarray(prior)[None]
        if prior is not None:
            prior = np.asarray(prior, np.float32)
            if prior.shape != images.shape[:3]:
                raise ValueError(
                    f"prior shape {prior.shape} does not match images {images.shape[:3]}"
                )
            if self.meta.in_channels == 3:
                log.debug("%s is a 3-channel model: the prior is ignored", self.path.name)
        return multi_scale_probs(self.logits, self.meta, images, prior, self.scales, batch_size)

    def predict_mask(self, images: np.ndarray, prior: np.ndarray | None = None) -> np.ndarray:
        """Binary robot masks ``[N,H,W]`` (probability above the model's threshold)."""
        return self.predict(images, prior) > self.meta.threshold
