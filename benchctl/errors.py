"""The one exception type that means "the user asked for something wrong" (shown as one line, no traceback)."""


class BenchctlError(Exception):
    """A user-facing error: bad file, key, value or device state. The message names what is wrong."""


class BadValueError(BenchctlError, ValueError):
    """A value a user chose (method name, iteration count, seed) is not acceptable; also a ValueError for APIs."""
