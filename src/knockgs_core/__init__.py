"""KnockGS: physics-based calibration of simulatable 3D Gaussian assets."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("knockgs")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+src"

__all__ = ["__version__"]
