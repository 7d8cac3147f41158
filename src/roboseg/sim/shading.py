"""Shading maths of the simulator: normals, per-pixel barycentrics, Blinn-Phong, noise, sensor.

Everything here is a small pure function on tensors. Geometry is in the camera's OpenCV optical
frame (x right, y down, z forward, metres); pixel ``(u, v)`` centres sit at integer coordinates.
Colours are linear RGB floats in [0, 1] until :func:`to_uint8` applies exposure, white balance and
the display gamma.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch


def face_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit normals ``[..., F, 3]`` of triangles ``faces [F,3]`` over ``verts [..., V, 3]``
    (counter-clockwise winding seen from outside gives an outward normal)."""
    a, b, c = (verts[..., faces[:, k], :] for k in range(3))
    n = torch.cross(b - a, c - a, dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals ``[..., V, 3]`` of a triangle mesh."""
    a, b, c = (verts[..., faces[:, k], :] for k in range(3))
    n_face = torch.cross(b - a, c - a, dim=-1)  # length = 2 × area
    out = torch.zeros_like(verts)
    for k in range(3):
        out.index_add_(-2, faces[:, k], n_face)
    return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def pixel_rays(K: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Ray directions ``[H, W, 3]`` through pixel centres, scaled so that z = 1 (so a point at
    depth d along the ray of pixel (u, v) is ``d · ray[v, u]``)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    v, u = torch.meshgrid(
        torch.arange(height, dtype=K.dtype), torch.arange(width, dtype=K.dtype), indexing="ij"
    )
    return torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)


def barycentric(
    rays: torch.Tensor, verts_cam: torch.Tensor, faces: torch.Tensor, face_id: torch.Tensor
) -> torch.Tensor:
    """Barycentric coordinates ``[N, 3]`` where rays ``[N, 3]`` (from the camera centre) meet the
    planes of triangles ``faces[face_id]`` (``face_id [N]``) of ``verts_cam [V, 3]``.

    Solves ``t·ray = a + β(b − a) + γ(c − a)`` (Cramer's rule, Möller–Trumbore); returns
    ``(1 − β − γ, β, γ)``. Coordinates are clamped to the triangle for rays grazing an edge.
    """
    tri = faces[face_id]
    a, b, c = verts_cam[tri[:, 0]], verts_cam[tri[:, 1]], verts_cam[tri[:, 2]]
    e1, e2 = b - a, c - a
    p = torch.cross(rays, e2, dim=-1)
    det = (e1 * p).sum(-1)
    det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    s = -a  # ray origin (0) minus a
    beta = (s * p).sum(-1) / det
    q = torch.cross(s, e1, dim=-1)
    gamma = (rays * q).sum(-1) / det
    bary = torch.stack([1.0 - beta - gamma, beta, gamma], dim=-1).clamp(0.0, 1.0)
    return bary / bary.sum(-1, keepdim=True).clamp_min(1e-12)


def interpolate(
    attr: torch.Tensor, faces: torch.Tensor, face_id: torch.Tensor, bary: torch.Tensor
) -> torch.Tensor:
    """Per-vertex attribute ``attr [V, C]`` interpolated at hits ``(face_id [N], bary [N, 3])``."""
    tri = faces[face_id]
    return (attr[tri] * bary[..., None]).sum(-2)


def blinn_phong(
    normal: torch.Tensor,
    view: torch.Tensor,
    light: torch.Tensor,
    albedo: torch.Tensor,
    *,
    ambient: float,
    diffuse: float,
    specular: float,
    shininess: float,
) -> torch.Tensor:
    """Linear RGB ``[N, 3]`` of a Lambert + Blinn-Phong surface.

    ``normal``, ``view`` (surface → camera) are unit ``[N, 3]``; ``light`` is the unit direction
    towards a directional light ``[3]``; normals facing away from the camera are flipped (the
    meshes are not always closed). Colour = albedo·(ambient + diffuse·max(n·l, 0)) +
    specular·max(n·h, 0)^shininess with h the half vector.
    """
    flip = (normal * view).sum(-1, keepdim=True) < 0
    n = torch.where(flip, -normal, normal)
    ndl = (n * light).sum(-1, keepdim=True).clamp_min(0.0)
    h = view + light
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    ndh = (n * h).sum(-1, keepdim=True).clamp_min(0.0)
    return albedo * (ambient + diffuse * ndl) + specular * ndh**shininess


def view_opacity(alpha: torch.Tensor, cos_view: torch.Tensor) -> torch.Tensor:
    """Opacity of a thin translucent sheet of normal-incidence opacity ``alpha`` seen at
    ``cos_view = |n·v|``: the path length grows as 1/cos, so ``1 − (1 − α)^(1/cos)``."""
    cos_view = cos_view.clamp(0.05, 1.0)
    return 1.0 - (1.0 - alpha).clamp(0.0, 1.0) ** (1.0 / cos_view)


def smooth_noise(
    height: int, width: int, cells: float, rng: np.random.Generator, octaves: int = 3
) -> np.ndarray:
    """Low-frequency value noise ``[H, W]`` float32 in about [−1, 1]: random grids of ``cells``
    cells across the longer side (doubling per octave, halving amplitude), bicubically upsampled."""
    out = np.zeros((height, width), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = max(2, int(round(cells * 2**o)))
        gh = max(2, int(round(n * height / max(height, width))) + 1)
        gw = max(2, int(round(n * width / max(height, width))) + 1)
        grid = rng.uniform(-1.0, 1.0, (gh, gw)).astype(np.float32)
        out += amp * cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.5
    return np.clip(out / total, -1.0, 1.0)


def plane_waves(
    points: torch.Tensor, directions: torch.Tensor, phases: torch.Tensor
) -> torch.Tensor:
    """Sum of sines ``Σ_k sin(d_k · p + φ_k) / K`` at points ``[..., 3]``: a smooth 3D noise field
    for drape wrinkles. ``directions [K, 3]`` are wave vectors (rad/m), ``phases [K]`` radians."""
    return torch.sin(points @ directions.T + phases).mean(-1)


def random_waves(
    k: int, wavelength: tuple[float, float], rng: np.random.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """``k`` random wave vectors (uniform directions, wavelengths in metres) and phases."""
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = rng.uniform(*wavelength, size=(k, 1))
    phases = rng.uniform(0.0, 2.0 * math.pi, size=k)
    return (
        torch.as_tensor(d * 2.0 * math.pi / lam, dtype=torch.float32),
        torch.as_tensor(phases, dtype=torch.float32),
    )


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Display gamma (sRGB transfer curve) of linear values in [0, 1]."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(
        linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1.0 / 2.4) - 0.055
    )


_LUT_SIZE = 4096
_SRGB_LUT = (srgb_encode(np.linspace(0.0, 1.0, _LUT_SIZE)) * 255.0).astype(np.float32)


def srgb_lut(linear: np.ndarray) -> np.ndarray:
    """:func:`srgb_encode` × 255 by table lookup (4096 linear steps) of values in [0, 1]."""
    return _SRGB_LUT[(linear * (_LUT_SIZE - 1) + 0.5).astype(np.int32)]


class NoiseBank:
    """Unit Gaussian sensor noise for every frame of a recording from one draw: each
    :meth:`sample` is a random ``[H, W, 3]`` window of a bank a quarter larger than the image."""

    def __init__(self, height: int, width: int, rng: np.random.Generator, margin: float = 0.25):
        self.height, self.width, self.rng = height, width, rng
        shape = (int(height * (1 + margin)) + 1, int(width * (1 + margin)) + 1, 3)
        self.bank = rng.standard_normal(shape, dtype=np.float32)

    def sample(self) -> np.ndarray:
        """A random window: :meth:`window` of :meth:`draw`."""
        return self.window(*self.draw())

    def draw(self) -> tuple[int, int]:
        """Random top-left corner ``(dy, dx)`` of a window (advances the generator)."""
        dy = int(self.rng.integers(0, self.bank.shape[0] - self.height + 1))
        dx = int(self.rng.integers(0, self.bank.shape[1] - self.width + 1))
        return dy, dx

    def window(self, dy: int, dx: int) -> np.ndarray:
        """The ``[H, W, 3]`` window of the bank at top-left corner ``(dy, dx)``."""
        return self.bank[dy : dy + self.height, dx : dx + self.width]


def to_uint8(
    linear_rgb: np.ndarray,
    exposure: float,
    white_balance: np.ndarray,
    noise_sigma: float = 0.0,
    noise: np.ndarray | None = None,
    blur_sigma: float = 0.0,
) -> np.ndarray:
    """Camera pipeline: linear RGB ``[H, W, 3]`` × exposure × per-channel white balance, optional
    Gaussian blur (pixels), sRGB gamma, additive sensor noise ``noise_sigma · noise`` (σ in
    8-bit levels, ``noise`` unit Gaussian ``[H, W, 3]``), rounded to uint8.

    float32 throughout; the per-channel gain and the final add-and-round run in OpenCV (one
    pass each), the gamma by table lookup (:func:`srgb_lut`)."""
    gain = exposure * np.asarray(white_balance, np.float32)  # float32 (weak Python scalar)
    img = cv2.multiply(np.asarray(linear_rgb, np.float32), (*(float(g) for g in gain), 0.0))
    if blur_sigma > 0.05:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    np.clip(img, 0.0, 1.0, out=img)
    img *= np.float32(_LUT_SIZE - 1)
    img += np.float32(0.5)
    img = _SRGB_LUT[img.astype(np.int32)]
    if noise_sigma > 0 and noise is not None:
        # img + σ·noise, rounded half to even and saturated to [0, 255]
        sigma = float(np.float32(noise_sigma))
        return cv2.addWeighted(img, 1.0, noise, sigma, 0.0, dtype=cv2.CV_8U)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
