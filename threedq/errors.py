"""Errors a user can fix, and the one line the ``threedq`` command prints for them.

An :class:`InputError` (such as :class:`~threedq.scene.SceneValidationError`) is a bad input whose message is one line
naming the file (or option) and the field, e.g. ``data/x/train/scene_000003.npz: field 'depth': 12 non-finite
value(s) (NaN or inf)``. :func:`error_line` turns any error the command reports into that one line.
"""

from __future__ import annotations

import re

__all__ = ["InputError", "error_line", "flatten_message", "user_error_in_chain"]


class InputError(ValueError):
    """A bad input the user can fix; the message is one line naming the file (or option) and the field."""


# Lines of jsonargparse's nested messages that say nothing about the fault itself.
_NOISE = re.compile(r"^(Does not validate against any of the Union subtypes|Subtypes: |Errors:$|Given value type: |"
                    r"Given value: |- Expected a <class 'NoneType'>)")


def flatten_message(message: str) -> str:
    """``message`` on one line: blank and boilerplate lines of nested parser messages dropped, whitespace collapsed."""
    lines = [line.strip() for line in str(message).splitlines()]
    kept = [line for line in lines if line and not _NOISE.match(line)]
    return re.sub(r"\s+", " ", " ".join(kept)).strip()


def user_error_in_chain(e: BaseException) -> BaseException | None:
    """The first :class:`InputError` or ``OSError`` among ``e`` and its explicit causes, or None."""
    seen: set[int] = set()
    x: BaseException | None = e
    while x is not None and id(x) not in seen:
        seen.add(id(x))
        if isinstance(x, (InputError, OSError)):
            return x
        x = x.__cause__
    return None


# torch's DataLoader re-raises an error of a worker process with the worker's whole traceback in its message
_WORKER = re.compile(r"^Caught \w+ in DataLoader worker process \d+\.")


def error_line(e: BaseException) -> str:
    """The one line that reports ``e`` (without the ``threedq: error:`` prefix)."""
    inner = user_error_in_chain(e)
    if isinstance(inner, OSError):
        reason = inner.strerror or flatten_message(str(inner)) or type(inner).__name__
        reason = reason[:1].lower() + reason[1:]
        if inner.filename is None:
            return flatten_message(str(inner)) if inner.strerror is None else reason
        target = f"{inner.filename}" + (f" -> {inner.filename2}" if inner.filename2 is not None else "")
        return f"{target}: {reason}"
    if inner is not None:
        e = inner
    text = str(e)
    if _WORKER.match(text):  # the worker's own error is the traceback's last line: "module.Type: message"
        last = next((ln for ln in reversed(text.splitlines()) if ln.strip()), text)
        return re.sub(r"^[\w.]+: ", "", last.strip(), count=1)
    return flatten_message(text) or type(e).__name__
