"""rgbd-gt: ground-truth RGB-D data from a terrestrial laser scan and photos."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("rgbd-gt")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
