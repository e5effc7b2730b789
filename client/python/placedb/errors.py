"""Errors: every failure the SDK reports is a :class:`Error` carrying a gRPC status code.

Server errors keep the server's code and message (INVALID_ARGUMENT messages name the offending
field as a path into the request, e.g. ``observation.features.keypoints[3].x: ...``). Input the
SDK refuses before sending (a wrong dtype or shape, a missing file) is reported the same way, as
:class:`InvalidArgument` with the field path the server would use, so callers handle one kind of
error whichever side found the problem.
"""

from __future__ import annotations

from typing import Dict, Optional, Type

import grpc


class Error(Exception):
    """A placedb call failed. ``code`` is the :class:`grpc.StatusCode`, ``message`` the detail."""

    code: grpc.StatusCode = grpc.StatusCode.UNKNOWN

    def __init__(self, message: str, code: Optional[grpc.StatusCode] = None) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code

    def __str__(self) -> str:
        return f"{self.code.name}: {self.message}"


class InvalidArgument(Error, ValueError):
    """A bad request: a bad name, setting or frame (the message names the field)."""

    code = grpc.StatusCode.INVALID_ARGUMENT


class NotFound(Error, LookupError):
    """The map or place does not exist."""

    code = grpc.StatusCode.NOT_FOUND


class AlreadyExists(Error):
    """The map name is taken."""

    code = grpc.StatusCode.ALREADY_EXISTS


class PermissionDenied(Error):
    """The token's principal lacks the right the call needs."""

    code = grpc.StatusCode.PERMISSION_DENIED


class Unauthenticated(Error):
    """No, a malformed or an unknown token (or client certificate)."""

    code = grpc.StatusCode.UNAUTHENTICATED


class ResourceExhausted(Error):
    """A server limit was hit (the message names it), or the disk is full."""

    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class FailedPrecondition(Error):
    """The map is not in a state that allows the call (e.g. recovering a healthy map)."""

    code = grpc.StatusCode.FAILED_PRECONDITION


class DataLoss(Error):
    """The map is damaged (see :meth:`placedb.Client.recover_map`), or a snapshot archive is
    truncated or corrupted (a download's size or SHA-256 does not match; an upload's)."""

    code = grpc.StatusCode.DATA_LOSS


class Unavailable(Error):
    """The server cannot be reached or is shutting down."""

    code = grpc.StatusCode.UNAVAILABLE


class Cancelled(Error):
    """The call was cancelled (e.g. the server closed an idle ingest stream)."""

    code = grpc.StatusCode.CANCELLED


class DeadlineExceeded(Error):
    """The call's timeout passed."""

    code = grpc.StatusCode.DEADLINE_EXCEEDED


class Internal(Error):
    """A server-side failure (or UNKNOWN / UNIMPLEMENTED / ABORTED / OUT_OF_RANGE)."""

    code = grpc.StatusCode.INTERNAL


_BY_CODE: Dict[grpc.StatusCode, Type[Error]] = {
    cls.code: cls
    for cls in (
        InvalidArgument,
        NotFound,
        AlreadyExists,
        PermissionDenied,
        Unauthenticated,
        ResourceExhausted,
        FailedPrecondition,
        DataLoss,
        Unavailable,
        Cancelled,
        DeadlineExceeded,
        Internal,
    )
}


def error_for(code: grpc.StatusCode, message: str) -> Error:
    """The :class:`Error` subclass instance for a gRPC status (codes without one: Internal)."""
    cls = _BY_CODE.get(code, Internal)
    return cls(message, code)


def error_from_status_number(number: int, message: str) -> Error:
    """As :func:`error_for`, from a numeric status (the proto's ``ErrorStatus.code``)."""
    for code in grpc.StatusCode:
        if code.value[0] == number:
            return error_for(code, message)
    return Internal(message, grpc.StatusCode.UNKNOWN)


def from_rpc_error(error: grpc.RpcError) -> Error:
    """Translates a failed call's :class:`grpc.RpcError` (code and details kept)."""
    code = error.code() if hasattr(error, "code") else grpc.StatusCode.UNKNOWN
    details = error.details() if hasattr(error, "details") else str(error)
    return error_for(code, details or "")
