"""What every training entry point does with a bad input: one line naming it, no traceback."""
from __future__ import annotations

import functools
import sys
from typing import Any, Callable

from monostixels._checks import InputError, numeric_text_error

__all__ = ["one_line_errors"]


def one_line_errors(prog: str) -> Callable[[Callable[[Any], Any]], Callable[[Any], Any]]:
    """Decorate a Hydra task ``main(cfg)`` (below ``@hydra.main``) so that a bad input ends it as ``monostixels``
    ends one: ``<prog>: error: <message>`` on stderr, exit status 1.

    A bad input is an :class:`InputError` (a missing file, a value out of range), or text given for a
    number where the script converts an option itself (``train.steps=many``: the message names the
    option). Any other exception is a bug and keeps its traceback.
    """
    def wrap(main: Callable[[Any], Any]) -> Callable[[Any], Any]:
        @functools.wraps(main)
        def entry(cfg: Any) -> Any:
            try:
                return main(cfg)
            except ValueError as e:
                error = e if isinstance(e, InputError) else numeric_text_error(cfg, e)
                if error is None:
                    raise
                print(f"{prog}: error: {error}", file=sys.stderr)
                sys.exit(1)
        return entry
    return wrap
