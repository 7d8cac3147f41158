"""roboseg: see surgical robots under the sterile drape, and locate them from stereo RGB.

Importing the package is cheap: submodules are imported explicitly (``roboseg.robot``,
``roboseg.segmentor``…), so the light ONNX runtime never pulls in the training stack.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("roboseg")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0"
