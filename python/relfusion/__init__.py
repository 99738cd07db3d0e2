"""The Python client of relfusiond (DeepRelativeFusion as a service): stream frames and get
poses back as they come, upload TUM-layout sequences, fetch trajectories as numpy and meshes as
trimesh, keep and reuse maps. ``Client`` is synchronous, ``AsyncClient`` the same for asyncio.
Errors are :class:`RelfusionError` subclasses carrying the service's status, code and message.
"""

from .aio import AsyncClient
from .client import Client
from .errors import (
    BadRequest,
    Conflict,
    Forbidden,
    Gone,
    NotFound,
    RelfusionError,
    TooLarge,
    TooManyRequests,
    Unauthorized,
    Unavailable,
)
from .images import png_bytes
from .types import Camera, Pose, Results, parse_tum

__all__ = [
    "AsyncClient",
    "BadRequest",
    "Camera",
    "Client",
    "Conflict",
    "Forbidden",
    "Gone",
    "NotFound",
    "Pose",
    "RelfusionError",
    "Results",
    "TooLarge",
    "TooManyRequests",
    "Unauthorized",
    "Unavailable",
    "parse_tum",
    "png_bytes",
]
__version__ = "0.1.0"
