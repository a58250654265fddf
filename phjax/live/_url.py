"""The URL checks shared by live sources and outputs (``udp://``, ``opentrack://``, ``osc://``)."""

from __future__ import annotations

import urllib.parse

__all__ = ["url_options", "url_port"]


def url_port(parsed: urllib.parse.SplitResult, url: str, error: type[Exception]) -> int | None:
    """The port of a split ``url`` (``None`` when it names none); ``error`` with one line when it
    is not an integer in 1-65535."""
    try:
        port = parsed.port
    except ValueError:  # not an integer, or above 65535
        raise error(f"{url}: bad port (expected an integer in 1-65535)") from None
    if port == 0:
        raise error(f"{url}: port 0 out of range 1-65535")
    return port


def url_options(parsed: urllib.parse.SplitResult, url: str, allowed: tuple[str, ...],
                error: type[Exception]) -> dict[str, list[str]]:
    """The query options of a split ``url``; ``error`` with one line naming any not in
    ``allowed``."""
    query = urllib.parse.parse_qs(parsed.query, keep_blank_values=True)
    unknown = set(query) - set(allowed)
    if unknown:
        raise error(f"{url}: unknown option(s) {', '.join(sorted(unknown))}")
    return query


def url_extras(parsed: urllib.parse.SplitResult, url: str, error: type[Exception]) -> None:
    """``error`` with one line when a split ``url`` has a user, password or fragment (which
    the address ignores: a typing error, not an option)."""
    if parsed.username is not None or parsed.password is not None:
        raise error(f"{url}: unexpected user or password (use HOST[:PORT])")
    if parsed.fragment:
        raise error(f"{url}: unexpected fragment #{parsed.fragment}")
