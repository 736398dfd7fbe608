"""How a run stops on bad input: one line on stderr (`error: ...`), exit status 1, no traceback."""


def fail(message: str):
    """Stop with one line on stderr and exit status 1, no traceback."""
    raise SystemExit("error: " + " ".join(message.split()))
