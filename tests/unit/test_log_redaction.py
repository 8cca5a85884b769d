"""The net under every log line: server/security/redaction.py and the filter that
server/bootstrap/logging_setup.py puts on the root handlers, on real logging records."""

from __future__ import annotations

import io
import logging
from collections.abc import Iterator

import pytest

from server.bootstrap.logging_setup import FORMAT, RedactingFilter, SpecFormatter, configure
from server.security.redaction import Redactor
from server.settings.model import Settings

TOKEN = "gc_0123abcd_Zm9vYmFyYmF6cXV4cXV1eGZvb2Jhcg-_x"
SECRET = TOKEN.split("_", 2)[2]
HOOK = "http://127.0.0.1:9000/hooks/path-secret?auth=query-secret"


@pytest.mark.parametrize(
    ("text", "gone", "kept"),
    [
        (f"call request (CellUser(name='a', token='{TOKEN}'))", SECRET, "name='a', token="),
        (f"a signed command from {TOKEN}", SECRET, "from gc_0123abcd_[redacted]"),
        (f"payload {{'token': '{TOKEN}', 'body': {{}}}}", SECRET, "'body'"),
        ('"GET /state?token=abc123def HTTP/1.1" 401', "abc123def", "GET /state?token="),
        ("/x?a=1&Access_Token=abc123def&b=2", "abc123def", "&b=2"),
        ("/ws?TICKET=abc123def", "abc123def", "/ws?TICKET="),
        ("/cb?password=abc123def;key=other-one", "abc123def", "/cb?password="),
        ("/cb?sig=abc123def", "abc123def", "/cb?sig="),
        ("/cb?secret=abc123def#frag", "abc123def", "#frag"),
        ("headers: {'Authorization': 'Bearer abc123def456ghi'}", "abc123def456ghi", "Bearer"),
        ("Authorization: Basic dXNlcjpwYXNzd29yZA==", "dXNlcjpwYXNzd29yZA", "Basic"),
        ("mqtt://cell:abc123def@broker:1883", "abc123def", "@broker:1883"),
        ('{"password": "abc\\"123def"}', '123def"', '"password"'),
        ("SecretStr(password='abc123def')", "abc123def", "password="),
        (f"POST {HOOK} 200", "path-secret", "POST http://127.0.0.1:9000/... 200"),
        (f"POST {HOOK} 200", "query-secret", "POST"),
        ("sent to /hooks/path-secret?auth=query-secret", "path-secret", "sent to /..."),
        ("auth=query-secret alone", "query-secret", "alone"),
    ],
)
def test_a_secret_is_removed_and_the_rest_kept(text: str, gone: str, kept: str) -> None:
    redacted = Redactor([HOOK])(text)
    assert gone not in redacted and kept in redacted


@pytest.mark.parametrize(
    "text",
    [
        "open /ws with a ticket from POST /ws-ticket, or send a bearer token",
        "GET /webhooks/deliveries HTTP/1.1",
        "/hooks/path-secrets-of-another-hook",
        "token 0123abcd revoked (plant)",
        "settings: shift_hours: 8 -> 12",
    ],
)
def test_prose_and_other_paths_are_left_alone(text: str) -> None:
    assert Redactor([HOOK])(text) == text


def test_redacting_twice_changes_nothing_more() -> None:
    redactor = Redactor([HOOK])
    text = f"GET /s?token={TOKEN}&ticket=t1 Bearer {TOKEN} {HOOK} mqtt://u:p@h password='x'"
    once = redactor(text)
    assert redactor(once) == once


def test_the_url_as_httpx_writes_it_is_redacted_too() -> None:
    """httpx percent-encodes what the configuration wrote plainly."""
    hook = "http://127.0.0.1:9000/hooks/a b?auth=c d"
    assert "hooks" not in Redactor([hook])("POST http://127.0.0.1:9000/hooks/a%20b?auth=c%20d")


@pytest.fixture
def written() -> Iterator[tuple[logging.Logger, io.StringIO]]:
    """A logger whose one handler has the cell's formatter and the redacting filter."""
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(SpecFormatter(FORMAT.replace("%(event_suffix)s", "")))
    handler.addFilter(RedactingFilter(Redactor([HOOK])))
    logger = logging.getLogger("tests.redaction")
    logger.propagate = False
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield logger, stream
    finally:
        logger.removeHandler(handler)
        logger.propagate = True


def test_a_records_arguments_exception_and_extras_are_redacted(written) -> None:
    logger, stream = written
    logger.info("user %r asked %s", {"token": TOKEN}, HOOK)
    try:
        raise ValueError(f"cannot post to {HOOK} with {TOKEN}")
    except ValueError:
        logger.exception("delivery failed", extra={"error": TOKEN, "context": {"t": TOKEN}})
    text = stream.getvalue()
    for secret in (SECRET, "path-secret", "query-secret"):
        assert secret not in text
    assert "Traceback" in text and "Error: gc_0123abcd_" in text and "Context: {'t': " in text


def test_uvicorns_lines_keep_the_path_and_drop_the_query(written) -> None:
    logger, stream = written
    access = logging.getLogger("uvicorn.access")
    access.handlers, access.propagate = logger.handlers, False
    access.setLevel(logging.INFO)
    try:
        access.info('%s - "%s %s HTTP/%s" %d', "127.0.0.1:5", "GET", "/ws?x=opaque-one", "1.1", 101)
    finally:
        access.handlers, access.propagate = [], True
        access.setLevel(logging.NOTSET)
    assert '127.0.0.1:5 - "GET /ws?... HTTP/1.1" 101' in stream.getvalue()


def test_the_cells_logging_redacts_and_quiets_httpx(tmp_path) -> None:
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    try:
        settings = Settings(
            data_path=tmp_path,
            webhooks=[{"url": HOOK, "secret": "k" * 16}],
            webhook_allowed_networks=["127.0.0.0/8"],  # the policy refuses loopback otherwise
        )
        path = configure(settings)
        logging.getLogger("httpx").info("HTTP Request: POST %s", HOOK)
        logging.getLogger("tests.redaction").warning("to %s as %s", HOOK, TOKEN)
        for handler in root.handlers:
            handler.flush()
        text = path.read_text()
        assert "HTTP Request" not in text  # httpx's per-request INFO line is off
        assert "to http://127.0.0.1:9000/... as gc_0123abcd_[redacted]" in text
    finally:
        for handler in root.handlers:
            handler.close()
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
        logging.getLogger("httpx").setLevel(logging.NOTSET)
        logging.getLogger("httpcore").setLevel(logging.NOTSET)
