"""What build of the server is running: its version, and its source revision when known.

The version is the installed distribution's (pyproject.toml). The revision is the
git commit of the checkout the server runs from, read from the repository's files
(no `git` process: the server may run where git is not installed); an installed
package or an image built without the repository has none, and says `unknown`.
Both are read once per process: neither changes while it runs.
"""

from __future__ import annotations

import functools
import re
from importlib import metadata
from pathlib import Path

DISTRIBUTION = "glue-cell-server"
UNKNOWN = "unknown"
_COMMIT = re.compile(r"[0-9a-f]{40}([0-9a-f]{24})?")  # SHA-1 or SHA-256 object ids
# The checkout the package runs from: server/common/build.py is three levels below it.
CHECKOUT = Path(__file__).resolve().parents[2]


def package_version() -> str:
    """The installed distribution's version (pyproject.toml), or why it is unknown."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "(not installed: run from a checkout)"


@functools.cache
def source_revision(checkout: Path = CHECKOUT) -> str:
    """The commit checked out in `checkout` (a clone or a git worktree), or `unknown`."""
    try:
        git_dir = _git_dir(checkout)
        if git_dir is None:
            return UNKNOWN
        head = (git_dir / "HEAD").read_text(encoding="utf-8").strip()
        if _COMMIT.fullmatch(head):  # a detached HEAD names its commit
            return head
        if not head.startswith("ref:"):
            return UNKNOWN
        return _resolve(git_dir, head.removeprefix("ref:").strip()) or UNKNOWN
    except (OSError, UnicodeDecodeError):
        return UNKNOWN


def _git_dir(checkout: Path) -> Path | None:
    """The repository directory: `.git` itself, or where a worktree's `.git` file points."""
    dot_git = checkout / ".git"
    if dot_git.is_dir():
        return dot_git
    if dot_git.is_file():
        pointer = dot_git.read_text(encoding="utf-8").strip()
        if pointer.startswith("gitdir:"):
            return (checkout / pointer.removeprefix("gitdir:").strip()).resolve()
    return None


def _resolve(git_dir: Path, ref: str) -> str | None:
    """The commit `ref` names: a loose ref file, else the packed refs.

    A worktree keeps its own HEAD but shares the main repository's refs (`commondir`).
    """
    common = git_dir
    if (git_dir / "commondir").is_file():
        common = (git_dir / (git_dir / "commondir").read_text(encoding="utf-8").strip()).resolve()
    for base in (git_dir, common):
        loose = base / ref
        if loose.is_file():
            value = loose.read_text(encoding="utf-8").strip()
            return value if _COMMIT.fullmatch(value) else None
    packed = common / "packed-refs"
    if packed.is_file():
        for line in packed.read_text(encoding="utf-8").splitlines():
            commit, _, name = line.partition(" ")
            if name == ref and _COMMIT.fullmatch(commit):
                return commit
    return None
