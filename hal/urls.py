"""Device URLs split into their parts, with one-line errors for malformed ones."""

from __future__ import annotations

from urllib.parse import SplitResult, urlsplit

from hal.errors import HardwareConfigError


def split_url(url: str, kind: str) -> SplitResult:
    """`url` split by `urllib.parse.urlsplit`; `kind` ("camera", "machine") names it in errors.

    Raises:
        HardwareConfigError: a URL that cannot be split (an unclosed IPv6 bracket, say):
            "machine URL 'modbus-tcp://[::1': Invalid IPv6 URL".
    """
    try:
        return urlsplit(url)
    except ValueError as exc:
        raise HardwareConfigError(f"{kind} URL {url!r}: {exc}") from None
