"""How a run stops on bad input: one line on stderr (`error: ...`), exit status 1, no traceback."""

import sys


def fail(message: str):
    """Stop with one line on stderr and exit status 1, no traceback."""
    raise SystemExit("error: " + " ".join(message.split()))


def refusal(kind: type, message: str) -> Exception:
    """An exception of this kind (RuntimeError, ValueError, ...) that says all there is to say: raised deep in a run
    (a fork's per_seed function, a recorded update), a program catches it as any other; uncaught in a script run from
    the command line, it prints as fail() does, one line and exit status 1, without the traceback."""
    error = kind(" ".join(message.split()))
    error.one_line = True
    return error


def print_refusals_in_one_line(kind, error, traceback, python_hook=sys.excepthook):
    if getattr(error, "one_line", False):
        print(f"error: {error}", file=sys.stderr)
    else:
        python_hook(kind, error, traceback)


sys.excepthook = print_refusals_in_one_line
