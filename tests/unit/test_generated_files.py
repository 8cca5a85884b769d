"""Generated files stay in step with the code they come from."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from server.cli.openapi import generate
from server.cli.settings_doc import DEFAULT_PATH as SETTINGS_DOC
from server.cli.settings_doc import render as render_settings_doc
from server.core.machine.diagram import TARGET_FILES, diagram_block

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", TARGET_FILES)
def test_state_diagram_copy_matches_the_table(name: str) -> None:
    text = (ROOT / name).read_text(encoding="utf-8")
    assert diagram_block(name) in text, f"{name} is stale: run `make diagram`"


def test_openapi_json_matches_the_app() -> None:
    committed = json.loads((ROOT / "openapi.json").read_text(encoding="utf-8"))
    assert committed == json.loads(json.dumps(generate())), (
        "openapi.json is stale: run `make openapi`"
    )


def test_settings_doc_matches_the_settings_model() -> None:
    committed = (ROOT / SETTINGS_DOC).read_text(encoding="utf-8")
    assert committed == render_settings_doc(), (
        f"{SETTINGS_DOC} is stale: run `python -m server.cli.settings_doc --write`"
    )


def test_openapi_documents_every_command_and_its_refusals() -> None:
    paths = generate()["paths"]
    for command in (
        "start",
        "calibrate-robot",
        "calibrate-camera",
        "create-workpiece",
        "pause",
        "resume",
        "cancel",
        "estop",
        "reset",
    ):
        responses = paths[f"/{command}"]["post"]["responses"]
        assert {"202", "409", "503"} <= set(responses), command
    for command in ("start", "estop"):  # the commands that take a body
        assert "422" in paths[f"/{command}"]["post"]["responses"]
