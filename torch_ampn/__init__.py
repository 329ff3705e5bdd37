"""torch-ampn: algebraic-hierarchical message passing networks for PyTorch Geometric."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("torch-ampn")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
