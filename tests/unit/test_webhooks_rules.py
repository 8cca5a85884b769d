"""The webhooks' rules with no network: which settings load, what is never shown, which
answers are retried and how long the waits are, and what a signature covers."""

from __future__ import annotations

import hashlib
import hmac
import json
from dataclasses import replace

import pytest
from pydantic import ValidationError

from server.core.worker.runs import RunEnded
from server.notify import notices, retry, signing
from server.notify.notices import Notice
from server.settings.load import SettingsRefused, load_settings
from server.settings.model import Settings

SECRET = "0123456789abcdef-secret"


def webhook(**fields) -> dict:
    return {"url": "https://plant.example/hook", "secret": SECRET, **fields}


@pytest.mark.parametrize(
    ("url", "problem"),
    [
        ("ftp://plant.example/hook", "http:// or https://"),
        ("https:///hook", "http:// or https://"),
        ("plant.example/hook", "http:// or https://"),
        ("https://user:pw@plant.example/hook", "user or password"),
        ("https://plant.example/hook#part", "fragment"),
        ("https://plant.example:99999/hook", "port"),
    ],
)
def test_a_webhook_url_that_cannot_work_is_refused_at_load(url: str, problem: str) -> None:
    with pytest.raises(ValidationError, match=problem):
        Settings(webhooks=[webhook(url=url)])


def test_a_webhook_needs_exactly_one_secret_long_enough(tmp_path) -> None:
    with pytest.raises(ValidationError, match="exactly one of secret and secret_file"):
        Settings(webhooks=[{"url": "https://plant.example/hook"}])
    with pytest.raises(ValidationError, match="at least 16"):
        Settings(webhooks=[webhook(secret="short")])
    with pytest.raises(ValidationError, match="cannot be read"):
        Settings(webhooks=[{"url": "https://p.example/", "secret_file": str(tmp_path / "none")}])
    key = tmp_path / "key"
    key.write_text(f"  {SECRET}\n", encoding="utf-8")
    both = webhook(secret_file=str(key))
    with pytest.raises(ValidationError, match="exactly one"):
        Settings(webhooks=[both])
    [target] = Settings(webhooks=[{"url": "https://p.example/", "secret_file": str(key)}]).webhooks
    assert target.secret_value == SECRET


def test_webhooks_are_named_by_position_and_names_must_differ() -> None:
    settings = Settings(webhooks=[webhook(), webhook(name="mes", events=["fault", "fault"])])
    assert [(t.name, t.events) for t in settings.webhooks] == [
        ("webhook-1", ["fault", "alert", "state", "run_completed", "part", "report"]),
        ("mes", ["fault"]),
    ]
    with pytest.raises(ValidationError, match="two webhooks are named 'a'"):
        Settings(webhooks=[webhook(name="a"), webhook(name="a")])


def test_the_settings_never_show_a_secret_or_the_url_s_path() -> None:
    url = "https://plant.example:8443/services/T01/B02/path-token?key=query-token"
    settings = Settings(webhooks=[webhook(url=url)])
    shown = json.dumps(settings.model_dump(mode="json"))
    assert SECRET not in shown and "path-token" not in shown and "query-token" not in shown
    assert settings.webhooks[0].model_dump(mode="json")["url"] == "https://plant.example:8443/..."
    # Validated again as PATCH /settings does: the secret and the URL survive.
    again = Settings.model_validate(settings.model_dump())
    assert again.webhooks[0].secret_value == SECRET and again.webhooks[0].url == url


def test_a_refused_webhooks_variable_is_not_repeated_in_the_message(monkeypatch) -> None:
    value = json.dumps([{"url": "gopher://plant.example/", "secret": SECRET}])
    monkeypatch.setenv("GLUE_APP_WEBHOOKS", value)
    with pytest.raises(SettingsRefused) as refused:
        load_settings()
    message = str(refused.value)
    assert "GLUE_APP_WEBHOOKS" in message and "http:// or https://" in message
    assert SECRET not in message and "gopher" not in message


@pytest.mark.parametrize(
    ("status", "verdict"),
    [
        (200, retry.Verdict.DELIVERED),
        (204, retry.Verdict.DELIVERED),
        (301, retry.Verdict.REFUSED),
        (400, retry.Verdict.REFUSED),
        (401, retry.Verdict.REFUSED),
        (404, retry.Verdict.REFUSED),
        (408, retry.Verdict.RETRY),
        (429, retry.Verdict.RETRY),
        (500, retry.Verdict.RETRY),
        (503, retry.Verdict.RETRY),
    ],
)
def test_only_answers_that_may_change_are_retried(status: int, verdict: retry.Verdict) -> None:
    assert retry.verdict(status) is verdict


def test_the_wait_doubles_up_to_its_ceiling_and_honours_retry_after_within_it() -> None:
    for attempt, base in [(1, 1.0), (2, 2.0), (3, 4.0), (4, 8.0)]:
        wait = retry.delay(attempt, 1.0, 10.0)
        assert base <= wait <= min(base * (1 + retry.JITTER), 10.0)
    assert retry.delay(30, 1.0, 10.0) == 10.0
    assert retry.delay(1, 1.0, 10.0, retry_after=7.0) == 7.0
    assert retry.delay(1, 1.0, 10.0, retry_after=3600.0) == 10.0
    assert retry.retry_after_seconds("5") == 5.0
    assert retry.retry_after_seconds("Wed, 21 Oct 2015 07:28:00 GMT") is None
    assert retry.retry_after_seconds("-1") is None


def test_the_signature_covers_the_timestamp_and_the_raw_body() -> None:
    body = Notice("fault", 1.5, "ERROR", {"code": "EMERGENCY_STOP"}).body("abc", "cell-1")
    assert json.loads(body) == {
        "id": "abc",
        "cell_id": "cell-1",
        "kind": "fault",
        "at": 1.5,
        "state": "ERROR",
        "code": "EMERGENCY_STOP",
    }
    headers = signing.headers(SECRET, 1700000000, body, "abc", "fault")
    mac = hmac.new(SECRET.encode(), b"1700000000." + body, hashlib.sha256).hexdigest()
    assert headers[signing.SIGNATURE_HEADER] == f"sha256={mac}"
    assert headers[signing.TIMESTAMP_HEADER] == "1700000000"
    assert signing.signature(SECRET, 1700000001, body) != headers[signing.SIGNATURE_HEADER]


def test_a_run_notice_carries_its_parts_verdict_and_reasons() -> None:
    reason = "segment 2: bead 1.1 mm wide (expected 2.0 mm ± 30 %)"
    inspection = {"verdict": "defective", "reasons": [reason], "precision_p95_mm": 0.8}
    ended = RunEnded("r1", "trajectory", "completed", 2.0, "EXECUTING_TRAJECTORY", {}, None, 1)
    inspected = replace(ended, result={"workpieces": ["demo"], "inspection": inspection})

    def body_of(run: RunEnded, delivery: str) -> dict:
        notice = notices.from_run(run, 10.0)
        assert notice is not None  # a completed run is told
        return json.loads(notice.body(delivery, "cell"))

    body = body_of(inspected, "d1")
    assert (body["verdict"], body["reasons"]) == ("defective", [reason])
    assert body["inspection"] == inspection
    assert (body["inspected"], body["label"]) == (True, "defective")
    plain = body_of(ended, "d2")
    off = ["not inspected (inspection_enabled is off)"]
    assert (plain["verdict"], plain["reasons"], plain["inspection"]) == ("not_inspected", off, None)
    # A verdict outside the contract is not passed on as one.
    odd = replace(ended, result={"inspection": {"verdict": "unsure", "reasons": ["?"]}})
    assert body_of(odd, "d3")["verdict"] == "not_inspected"


def test_a_part_notice_tells_a_stopped_part_defective_not_inspected() -> None:
    stopped = RunEnded(
        "r2",
        "trajectory",
        "failed",
        1.0,
        "EXECUTING_TRAJECTORY",
        None,
        "EMERGENCY_STOP",
        1,
        {"order_id": "ord-1"},
    )
    assert notices.from_run(stopped, 10.0) is None  # no run_completed: it did not complete
    notice = notices.from_part(stopped, 10.0)
    assert notice is not None and notice.kind == "part"
    body = json.loads(notice.body("d4", "cell"))
    assert (body["verdict"], body["inspected"], body["label"]) == (
        "defective",
        False,
        "defective (not inspected)",
    )
    assert body["reasons"] == ["run stopped: emergency stop (STOP)"]
    assert body["order_id"] == "ord-1"
    calibration = replace(stopped, operation="calibrate_robot")
    assert notices.from_part(calibration, 10.0) is None  # no part
