"""Errors raised when a capture or derived dataset does not follow its schema."""

from __future__ import annotations

from pathlib import Path


class SchemaError(ValueError):
    """A file of a capture/dataset violates the schema.

    The message always names the file and the field, so a user can fix the input
    without reading a traceback: ``calibration.json: cam03.R: not a rotation (det=-1.00)``.
    """

    def __init__(self, file: str | Path, field: str, message: str) -> None:
        self.file = str(file)
        self.field = field
        self.message = message
        where = f"{self.file}: {field}" if field else self.file
        super().__init__(f"{where}: {message}")

    def __reduce__(self):
        # Rebuild from the three fields: the default (type, self.args) would call
        # SchemaError(message) and fail, so an error raised in a prep worker process
        # would reach the parent as BrokenProcessPool instead of this message.
        return type(self), (self.file, self.field, self.message)
