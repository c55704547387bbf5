"""argparse value types shared by the command-line modules.

A value of the wrong kind is an argparse usage error naming the option
(``argument --seed: expected an integer >= 0, got '-1'``): one line, exit 2.
"""

from __future__ import annotations

import argparse

__all__ = [
    "non_negative_int",
    "positive_int",
]


def _integer(text: str, minimum: int, what: str) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """Parse an integer >= 0 (seeds, pool sizes where 0 means "all CPUs").

    Parameters
    ----------
    text : str
        The command-line value.

    Returns
    -------
    int
        The value.

    Raises
    ------
    argparse.ArgumentTypeError
        When ``text`` is not an integer >= 0 (argparse turns it into a one-line usage error).
    """
    return _integer(text, 0, "an integer >= 0")


def positive_int(text: str) -> int:
    """Parse an integer >= 1 (counts).

    Parameters
    ----------
    text : str
        The command-line value.

    Returns
    -------
    int
        The value.

    Raises
    ------
    argparse.ArgumentTypeError
        When ``text`` is not an integer >= 1.
    """
    return _integer(text, 1, "an integer >= 1")
