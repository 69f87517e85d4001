"""What the command lines share: one `error:` line for a problem the user can fix."""

import sys


def report_error(error: Exception) -> int:
    """Prints `error` as one `error: ...` line on stderr and returns the exit status, 2.

    An operating-system error is named by its file and its reason (`runs/x: Permission
    denied`) rather than by its errno; every other error by its message.
    """
    if isinstance(error, OSError) and not isinstance(error, FileNotFoundError):
        where = f"{error.filename}: " if error.filename else ""
        print(f"error: {where}{error.strerror or error}", file=sys.stderr)
    else:
        print(f"error: {error}", file=sys.stderr)
    return 2
