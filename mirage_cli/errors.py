"""One exception base class: the CLI turns any MirageError into a one-line message, exit 2."""


class MirageError(Exception):
    """A failure the user can fix (bad input, missing file, ...). Message says what and how."""


class InputError(MirageError):
    """An input file or option is missing, unreadable or malformed."""


class OutputError(MirageError):
    """An output cannot be written."""


def cv_message(e: Exception) -> str:
    """The informative last line of an OpenCV (or other) exception, for one-line errors."""
    s = str(e).strip()
    return s.splitlines()[-1] if s else type(e).__name__
