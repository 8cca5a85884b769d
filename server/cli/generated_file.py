"""The command line of a file generated from the code (openapi.json, docs/settings.md).

`python -m <module>` prints the file as the code would write it; `--write` writes it.
tests/unit/test_generated_files.py fails when a committed one differs, so a change to
a route or a setting carries its regenerated file in the same commit.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path


def main(
    render: Callable[[], str], default_path: Path, description: str | None, argv: list[str] | None
) -> int:
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--write", action="store_true", help="write the file instead of printing")
    parser.add_argument("--path", type=Path, default=default_path)
    args = parser.parse_args(argv)
    if args.write:
        args.path.write_text(render(), encoding="utf-8")
        print(f"wrote {args.path}")
    else:
        sys.stdout.write(render())
    return 0
