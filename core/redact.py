"""One redaction for every place a camera source or other URL is written or shown.

Logs, ``session.toml``, reports and error messages pass their text through :func:`redact`: it hides
``user:password@`` in every URL inside the text and the values of query parameters whose names look
like secrets (``password``, ``pass``, ``pwd``, ``token``, ``key``, ``secret``, ``auth``, ``user``,
in any case and as part of a longer name such as ``api_key`` or ``username``).
"""

from __future__ import annotations

import logging
import re
import urllib.parse
from typing import Any

HIDDEN = "***"
_SECRET_NAME = re.compile(r"pass|pwd|token|key|secret|auth|user|sig|credential", re.I)
# a URL inside free text: a scheme, then anything up to whitespace, a quote or a closing bracket
_URL = re.compile(r"\b[a-zA-Z][a-zA-Z0-9+.-]*://[^\s'\"<>)\]]+")
_QUERY_PAIR = re.compile(r"([?&;])([^=&;#\s]+)=([^&;#\s]*)")


def redact_url(source: str) -> str:
    """``rtsp://user:pw@host/x?token=abc&ch=1`` -> ``rtsp://***@host/x?token=***&ch=1``.

    Works on the text of the URL (no parse-and-rebuild), so everything that is not a secret is kept
    exactly as written, even in URLs that ``urllib`` refuses.

    >>> redact_url("rtsp://admin:secret@192.0.2.7:554/stream1?token=abc&channel=1")
    'rtsp://***@192.0.2.7:554/stream1?token=***&channel=1'
    >>> redact_url("/dev/video0")
    '/dev/video0'
    """
    if "://" not in source:
        return source
    scheme, _, rest = source.partition("://")
    # userinfo: everything before the last '@' of the authority (the part before the first '/', '?', '#')
    ends = [i for i in (rest.find("/"), rest.find("?"), rest.find("#")) if i >= 0]
    authority_end = min(ends, default=len(rest))
    authority = rest[:authority_end]
    if "@" in authority:
        rest = f"{HIDDEN}@{authority.rpartition('@')[2]}{rest[authority_end:]}"
    rest = _QUERY_PAIR.sub(
        lambda m: f"{m[1]}{m[2]}={HIDDEN if _SECRET_NAME.search(urllib.parse.unquote(m[2])) else m[3]}", rest
    )
    return f"{scheme}://{rest}"


def redact(text: str) -> str:
    """Every URL inside ``text`` redacted (:func:`redact_url`); the rest unchanged.

    >>> redact("camera 'rtsp://u:p@cam1/live' stopped after 3 s")
    "camera 'rtsp://***@cam1/live' stopped after 3 s"
    """
    if "://" not in text:
        return text
    return _URL.sub(lambda m: redact_url(m[0]), text)


_factory_installed = False


def redact_log_records() -> None:
    """Redact the message of every log record made from now on, whichever logger or handler takes it."""
    global _factory_installed
    if _factory_installed:
        return
    make = logging.getLogRecordFactory()

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = make(*args, **kwargs)
        msg = record.getMessage()
        if "://" in msg:
            record.msg, record.args = redact(msg), None
        return record

    logging.setLogRecordFactory(factory)
    _factory_installed = True
