"""posecast: stream full-body VR poses (Vive trackers) to everyone in a shared session.

The code lives in the top-level folders protocol/, solver/, server/ and client/; they
install as posecast.protocol, posecast.solver, posecast.server and posecast.client
(package-dir mapping in pyproject.toml), so site-packages gets the one name ``posecast``.
In a checkout, this folder's links to them let tools that read the tree (mypy, pytest from
the repository root) resolve ``posecast.*`` without an install.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("posecast")
except PackageNotFoundError:  # a checkout that was never installed
    __version__ = "0+unknown"
