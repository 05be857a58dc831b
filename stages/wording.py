"""Wording shared by the stages' notes and errors."""

from __future__ import annotations


def counted(count: int, noun: str, plural: str | None = None) -> str:
    """`count` and `noun`, the noun plural unless the count is 1: "1 point", "3 points", "0 points".

    Args:
        count: how many. noun: the singular. plural: the plural when it is not noun + "s".
    """
    return f"{count} {noun if count == 1 else (plural or noun + 's')}"
