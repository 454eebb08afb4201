"""Errors that dyq raises for a user's files rather than for its own bugs."""


class FileFormatError(ValueError):
    """A file that the user named is not one that dyq writes, or no longer is (truncated, edited by hand,
    of another kind). The message names the file; the command line reports it in one line."""
