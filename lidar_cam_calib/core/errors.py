"""One error family for every method (ROS-free).

Feature extraction, fitting and input conversion raise a subclass of
:class:`CalibError`; ``str(err)`` is the reason shown to the user (status,
service response, CLI). The node base catches :class:`CalibError` as an
expected refusal and anything else as a bug (logged with its traceback, the
node stays up).
"""
from __future__ import annotations


class CalibError(RuntimeError):
    """Base of every expected failure; the message is for the user."""


class InputError(CalibError, ValueError):
    """A message or file that cannot be used (wrong encoding, NaN cloud, ...)."""


class ConfigError(CalibError, ValueError):
    """A parameter value outside what is allowed; names the parameter."""


class NotReadyError(CalibError):
    """``fit()`` called before enough observations were collected."""


__all__ = ["CalibError", "ConfigError", "InputError", "NotReadyError"]
