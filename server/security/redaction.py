"""Secrets out of text that is about to be written down: the net under every log line.

Secrets are kept out of log lines at their source (a token's holder masks it in its
repr, uvicorn's access log keeps the path and drops the query, httpx's per-request
lines are off). This is the net for whatever a library or a future line still lets
through: a pure function on the final text, so it is the same for the cell's own
records, uvicorn, asyncua, httpx and aiomqtt, and can be tested on its own.

What it removes, wherever it appears in the text:

- an API token, `gc_<id>_<secret>`: the id stays (it names the token, as the audit
  trail does), the secret goes;
- a query parameter whose name says it is secret (token, access_token, ticket,
  password, secret, key, sig and the like, any case), and the same names written as
  `name='value'` or `"name": "value"` (a repr, a JSON document);
- the credentials of an `Authorization: Bearer ...` or `Basic ...` header;
- a user and password in a URL (`scheme://user:password@host`);
- the path and query of every configured webhook URL, which receivers use to carry
  their own token (server/settings/webhooks.py says why): the URL is written as
  `scheme://host:port/...`, as everywhere else.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterable
from urllib.parse import urlsplit

REDACTED = "[redacted]"


def shown_url(url: str) -> str:
    """`url` as it may be shown: scheme, host and port; a path or query as `/...`."""
    parts = urlsplit(url)
    rest = "/..." if parts.path.strip("/") or parts.query else ""
    return f"{parts.scheme}://{parts.netloc}{rest}"


_SECRET_NAMES = (
    r"(?:access_token|refresh_token|id_token|token|ticket|password|passwd|secret"
    r"|api_key|apikey|key|sig|signature)"
)
# gc_<8 hex>_<secret>: the store's own pattern is anchored; this one finds it inside text,
# also a truncated or overlong secret (whatever follows the id is the secret).
_TOKEN = re.compile(r"\b(gc_[0-9a-fA-F]{8}_)[A-Za-z0-9_\-]+")
# ?token=... &Ticket=... in a URL or a query string (also URL-encoded names are plain here).
_QUERY_PARAM = re.compile(
    rf"(?i)([?&;]{_SECRET_NAMES}=)(?!\[redacted\])[^&;#\s\"'<>)\]]*",
)
# token='...', password="...", "secret": "...": a repr or a JSON document.
_ASSIGNED = re.compile(
    r"(?i)(\b(?:access_token|token|ticket|password|passwd|secret|api_key|sig|signature)"
    r"[\"']?\s*[:=]\s*)([\"'])((?:\\.|(?!\2).)*)\2",
)
# A credential after its scheme; at least 12 characters, so "a bearer token" stays prose.
_AUTHORIZATION = re.compile(r"(?i)\b(bearer|basic)(\s+)[A-Za-z0-9._~+/=\-]{12,}")
_USERINFO = re.compile(r"(?i)\b([a-z][a-z0-9+.\-]*://)[^/\s@:\"'<>]*:[^/\s@\"'<>]*@")


class Redactor:
    """Removes secrets from text; `secret_urls` are URLs whose path and query are secret."""

    def __init__(self, secret_urls: Iterable[str] = ()) -> None:
        replacements: dict[str, str] = {}
        for url in secret_urls:
            for variant in _spellings(url):
                parts = urlsplit(variant)
                tail = parts.path + (f"?{parts.query}" if parts.query else "")
                if not tail.strip("/?"):
                    continue  # nothing secret in a bare host
                replacements[variant] = shown_url(variant)
                replacements[tail] = "/..."
                if parts.query:
                    replacements[parts.query] = "..."
                if parts.path.strip("/"):
                    replacements[parts.path] = "/..."
        self._urls = dict(sorted(replacements.items(), key=lambda item: -len(item[0])))
        self._url_pattern = (
            # Whole words only: a webhook at /hook must not mangle a line about /hooks.
            re.compile("|".join(rf"(?<![\w%-]){re.escape(text)}(?![\w%-])" for text in self._urls))
            if self._urls
            else None
        )

    def __call__(self, text: str) -> str:
        if self._url_pattern is not None:
            text = self._url_pattern.sub(lambda m: self._urls[m.group(0)], text)
        text = _USERINFO.sub(rf"\1{REDACTED}@", text)
        text = _QUERY_PARAM.sub(rf"\1{REDACTED}", text)
        text = _ASSIGNED.sub(rf"\1\2{REDACTED}\2", text)
        text = _AUTHORIZATION.sub(rf"\1\2{REDACTED}", text)
        return _TOKEN.sub(rf"\1{REDACTED}", text)

    def __repr__(self) -> str:
        return f"Redactor({len(self._urls)} secret URL spellings)"


def _spellings(url: str) -> set[str]:
    """The URL as configured and as httpx writes it (its request line, percent-encoded)."""
    import httpx  # here: only a configured secret URL needs it, and the settings import this

    spellings = {url}
    with contextlib.suppress(httpx.InvalidURL):  # an URL httpx cannot parse, it never requests
        spellings.add(str(httpx.URL(url)))
    return spellings


def path_only(target: str) -> str:
    """A request target without its query: `/ws?ticket=...` -> `/ws?...` (uvicorn's lines)."""
    path, mark, _ = target.partition("?")
    return f"{path}?..." if mark else path
