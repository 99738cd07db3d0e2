"""Errors of the service, as Python exceptions carrying its error code."""

from __future__ import annotations

from typing import Any, Dict, Optional, Type


class RelfusionError(Exception):
    """The service refused a request (or could not be reached).

    ``status`` is the HTTP status (0 when there was no answer), ``code`` the service's error code
    (``"not_found"``, ``"quota_exceeded"``, ...), ``message`` its explanation.
    """

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(f"{status} {code}: {message}" if status else f"{code}: {message}")
        self.status = status
        self.code = code
        self.message = message


class BadRequest(RelfusionError):
    """400: the request itself is wrong (camera, config, image, timestamp)."""


class Unauthorized(RelfusionError):
    """401: no token, or one the service does not know."""


class Forbidden(RelfusionError):
    """403: the token is known but may not do this."""


class NotFound(RelfusionError):
    """404: no such session or map for this token, or the result does not exist yet."""


class Conflict(RelfusionError):
    """409: the session is not in a state for this (still running, stream ended)."""


class Gone(RelfusionError):
    """410: the session expired."""


class TooLarge(RelfusionError):
    """413: the body is over a limit of the service."""


class TooManyRequests(RelfusionError):
    """429: a quota of the token is used up; retry later or free something."""


class Unavailable(RelfusionError):
    """503: the service is at capacity or shutting down; retry later."""


_BY_STATUS: Dict[int, Type[RelfusionError]] = {
    400: BadRequest,
    401: Unauthorized,
    403: Forbidden,
    404: NotFound,
    409: Conflict,
    410: Gone,
    413: TooLarge,
    429: TooManyRequests,
    503: Unavailable,
}


def error_from_response(status: int, body: bytes) -> RelfusionError:
    """The exception for an error answer: the service's `{"error": {"code", "message"}}`."""
    code, message = "http_error", body[:500].decode("utf-8", "replace")
    try:
        import json

        parsed: Any = json.loads(body)
        detail: Optional[Dict[str, Any]] = parsed.get("error") if isinstance(parsed, dict) else None
        if isinstance(detail, dict):
            code = str(detail.get("code", code))
            message = str(detail.get("message", message))
    except ValueError:
        pass
    return _BY_STATUS.get(status, RelfusionError)(status, code, message)
