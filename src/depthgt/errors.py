"""Exception types shared by the library.

Two levels of failure are distinguished so that nothing is silently lost:

* :class:`FrameError`: one frame cannot be used (missing or corrupt file, non-finite
  pose, empty depth). The frame-set batch that reads it records it with ``reason`` and
  skips the frame sets holding it, and goes on.
* :class:`SourceError`: the scene as a whole cannot be read (unknown kind or scene,
  truncated ``.sens`` header, missing intrinsics). The run stops with this message.
* :class:`ConfigError`: the configuration is invalid; the message names the key.
"""


class DepthGTError(Exception):
    """Base class of all depthgt errors."""


class SourceError(DepthGTError):
    """A scene or source cannot be opened; the message names the file or scene."""


class FrameError(DepthGTError):
    """One frame is unusable; ``reason`` is a short machine-friendly tag."""

    def __init__(self, message: str, reason: str = "unreadable"):
        super().__init__(message)
        self.reason = reason


class ConfigError(DepthGTError):
    """Invalid configuration; the message names the offending key."""
