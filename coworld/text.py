"""Wording shared by the messages: counts with the right plural."""

from __future__ import annotations


def count(n: int, noun: str, plural: str | None = None) -> str:
    """``1 episode``, ``2 episodes``, ``1,000 steps``: ``n`` with thousands separators and the noun in agreement."""
    return f"{n:,} {noun if n == 1 else plural or noun + 's'}"
