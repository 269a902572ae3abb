"""Errors about what the user asked for, and the check of a number the user gave."""


class UserError(Exception):
    """A mistake in what the user asked for (a scene, a file, an option): the command
    line prints it as one line and exits with status 2, without a traceback."""


def int_flag(flag: str, text: str, least: int, most: int | None = None) -> int:
    """``text`` as an integer in ``least .. most`` (``most`` ``None``: no upper bound)."""
    expected = f"an integer >= {least}" if most is None else f"an integer in {least}..{most}"
    try:
        value = int(text)
    except ValueError:
        raise UserError(f"{flag} {text!r}: expected {expected}") from None
    if value < least or (most is not None and value > most):
        raise UserError(f"{flag} {text!r}: expected {expected}")
    return value
