"""Errors that mean "the user gave us something wrong" (exit code 2) versus bugs (exit code 1).

Every user-facing error prints as one line naming where the problem is: the file, the column and the first bad row.
Rows are counted from 1 over data rows (the header is not a row), the way a person reads a spreadsheet.
"""

from __future__ import annotations


class UserError(Exception):
    """Base class of every error caused by input (files, options, configuration). The CLI exits 2 on these."""


class DataError(UserError, ValueError):
    """Bad data: NaN/inf, non-increasing time, missing or mislabelled columns, wrong units, empty input."""

    def __init__(self, message: str, *, file: str | None = None, column: str | None = None, row: int | None = None):
        self.message = message
        self.file = file
        self.column = column
        self.row = row
        super().__init__(self.__str__())

    def __str__(self) -> str:
        where = []
        if self.file:
            where.append(str(self.file))
        if self.column is not None:
            where.append(f"column '{self.column}'")
        if self.row is not None:
            where.append(f"row {self.row}")
        return (", ".join(where) + ": " if where else "") + self.message

    def with_file(self, file: str) -> DataError:
        """The same error, attributed to ``file`` when it did not name one yet."""
        if self.file:
            return self
        return DataError(self.message, file=file, column=self.column, row=self.row)


class ConfigError(UserError, ValueError):
    """A bad option, parameter file or scenario file (unknown key, impossible value)."""


class SocbenchWarning(UserWarning):
    """Something the user should know about their input or result, that does not stop the command (a reference SOC a
    few points outside [0, 1], a model driven outside its domain...). The CLI prints each as one line on stderr:
    ``socbench COMMAND: warning: message``. Raise with ``warnings.warn(message, SocbenchWarning, stacklevel=2)``."""


class ModelError(ValueError):
    """A model left its admissible region in strict mode (negative capacitance, unstable eigenvalue...)."""


#: an error quotes a bad cell up to this many characters (a block of zeroed bytes reads as one huge cell)
CELL_SHOWN = 40


def shown(value) -> str:
    """A bad cell as an error quotes it: ``empty or NaN`` for a missing value (a loader that parses numbers reads an
    empty cell and a NaN alike), else its ``repr`` (a numpy scalar as the plain number), cut to :data:`CELL_SHOWN`
    characters."""
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:
        value = value.item()
    if value is None or (isinstance(value, float) and value != value):
        return "empty or NaN"
    text = repr(value)
    return text if len(text) <= CELL_SHOWN else text[:CELL_SHOWN] + "…"


def first_line(exc: BaseException) -> str:
    """What a parser's exception says, as one line of an error: its message's first line, else its type's name."""
    text = str(exc)
    return text.splitlines()[0] if text.strip() else type(exc).__name__
