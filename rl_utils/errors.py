"""How a run stops on bad input: one line on stderr (`error: ...`), exit status 1, no traceback."""

import os
import sys
import traceback as tracebacks


def fail(message: str):
    """Stop with one line on stderr and exit status 1, no traceback."""
    raise SystemExit("error: " + " ".join(message.split()))


def refusal(kind: type, message: str) -> Exception:
    """An exception of this kind (RuntimeError, ValueError, ...) that says all there is to say: raised deep in a run
    (a fork's per_seed function, a recorded update), a program catches it as any other; uncaught in a script run from
    the command line, it prints as fail() does, one line and exit status 1, with the line of the script's own code it
    came from in place of the traceback (RL_UTILS_TRACEBACK=1 prints the traceback too)."""
    error = kind(" ".join(message.split()))
    error.one_line = True
    return error


def where(error: BaseException) -> str:
    """The last line of code outside rl_utils, torch and the standard library that the error (or the one it was
    raised from) passed through: where a fork's code met the refusal."""
    library, found = (os.path.dirname(os.path.abspath(__file__)), os.path.dirname(os.path.abspath(os.__file__))), ""
    for cause in (error, error.__cause__):  # the cause's last: the deeper of the two
        for frame in tracebacks.extract_tb(cause.__traceback__) if cause is not None else []:
            path = os.path.abspath(frame.filename)
            if not path.startswith(library) and f"{os.sep}site-packages{os.sep}" not in path:
                found = f"{os.path.basename(path)}:{frame.lineno}"
    return found


def print_refusals_in_one_line(kind, error, traceback, python_hook=sys.excepthook):
    if getattr(error, "one_line", False) and not os.environ.get("RL_UTILS_TRACEBACK"):
        line = where(error)
        print(f"error: {error}" + (f" (at {line})" if line else ""), file=sys.stderr)
    else:
        python_hook(kind, error, traceback)


sys.excepthook = print_refusals_in_one_line
