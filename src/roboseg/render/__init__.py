"""Rendering of robot meshes: hard z-buffer rasterisation (:mod:`.raster`); the differentiable
silhouettes live in :mod:`.soft`."""

from roboseg.render.raster import Raster, rasterize, render_hard

__all__ = ["Raster", "rasterize", "render_hard"]
