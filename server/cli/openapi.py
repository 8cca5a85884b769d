"""Write or check openapi.json, generated from the app itself.

`python -m server.cli.openapi --write` regenerates the file at the repository
root; a test fails when the committed file drifts from the code.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from server.bootstrap.app import create_app
from server.cli import generated_file
from server.settings.model import Settings

DEFAULT_PATH = Path("openapi.json")


def generate() -> dict[str, Any]:
    """The OpenAPI document of the app with default settings."""
    return create_app(Settings()).openapi()


def render() -> str:
    return json.dumps(generate(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    return generated_file.main(render, DEFAULT_PATH, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
