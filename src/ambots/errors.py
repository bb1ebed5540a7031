"""Typed errors.  Every error says *where* the problem is (file, line, field),
so a user can fix the input without reading a traceback."""


class AmbotsError(Exception):
    """Base class of every error this package raises on bad input."""


class ConfigError(AmbotsError):
    """A YAML profile or cell file is missing a field or has a bad value.

    Attributes: ``path`` (file), ``field`` (dotted name, e.g. ``arms[1].base.xyz``).
    """

    def __init__(self, path, field, message):
        self.path, self.field, self.message = path, field, message
        where = path if not field else "%s: %s" % (path, field)
        super().__init__("%s: %s" % (where, message))


class GCodeError(AmbotsError):
    """A G-code line could not be read.  Attributes: ``path``, ``line`` (1-based),
    ``text`` (the offending line), ``message``."""

    def __init__(self, path, line, text, message):
        self.path, self.line, self.text, self.message = path, line, text, message
        where = "%s:%s" % (path, line) if line else str(path)
        super().__init__("%s: %s: %r" % (where, message, text) if text else "%s: %s" % (where, message))


class ProtocolError(AmbotsError):
    """An A-series string is malformed.  Attributes: ``text``, ``message``."""

    def __init__(self, text, message):
        self.text, self.message = text, message
        super().__init__("%s: %r" % (message, text))


class MeshError(AmbotsError):
    """A model file cannot be used (unreadable, empty, not a closed volume...)."""


class KinematicsError(AmbotsError):
    """A kinematic model cannot be built (bad URDF, missing link...)."""


class UnreachableError(KinematicsError):
    """No joint configuration within limits reaches the requested nozzle pose."""


class ExportError(AmbotsError):
    """A planned job cannot be exported (``python -m ambots export``): a
    missing or inconsistent plan folder, an unknown format, an arm the
    format does not support, a plan that does not run to the end."""
