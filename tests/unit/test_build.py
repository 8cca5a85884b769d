"""The running build's source revision, read from a checkout's git files: a clone's loose
and packed refs, a git worktree's pointer to its repository, a detached HEAD, none."""

from __future__ import annotations

from pathlib import Path

from server.common.build import UNKNOWN, source_revision

COMMIT = "1ad994582b39cc69afd4d06f6059b3d2c7e8e431"
OTHER = "0123456789abcdef0123456789abcdef01234567"


def clone(root: Path, head: str) -> Path:
    git = root / ".git"
    (git / "refs" / "heads").mkdir(parents=True)
    (git / "HEAD").write_text(head + "\n")
    return git


def test_a_branch_in_a_clone_reads_its_loose_ref(tmp_path: Path) -> None:
    git = clone(tmp_path, "ref: refs/heads/main")
    (git / "refs" / "heads" / "main").write_text(COMMIT + "\n")
    assert source_revision.__wrapped__(tmp_path) == COMMIT


def test_a_packed_ref_is_read_when_there_is_no_loose_one(tmp_path: Path) -> None:
    git = clone(tmp_path, "ref: refs/heads/main")
    (git / "packed-refs").write_text(
        f"# pack-refs with: peeled fully-peeled sorted\n{OTHER} refs/heads/other\n"
        f"{COMMIT} refs/heads/main\n"
    )
    assert source_revision.__wrapped__(tmp_path) == COMMIT


def test_a_detached_head_names_its_commit(tmp_path: Path) -> None:
    clone(tmp_path, COMMIT)
    assert source_revision.__wrapped__(tmp_path) == COMMIT


def test_a_worktree_reads_its_head_and_the_shared_refs(tmp_path: Path) -> None:
    main = clone(tmp_path / "main", "ref: refs/heads/main")
    (main / "refs" / "heads" / "feature").write_text(OTHER + "\n")
    private = main / "worktrees" / "feature"
    private.mkdir(parents=True)
    (private / "HEAD").write_text("ref: refs/heads/feature\n")
    (private / "commondir").write_text("../..\n")
    checkout = tmp_path / "feature"
    checkout.mkdir()
    (checkout / ".git").write_text(f"gitdir: {private}\n")
    assert source_revision.__wrapped__(checkout) == OTHER


def test_no_repository_or_an_unreadable_one_is_unknown(tmp_path: Path) -> None:
    assert source_revision.__wrapped__(tmp_path) == UNKNOWN
    clone(tmp_path, "ref: refs/heads/gone")  # a branch with no commit yet
    assert source_revision.__wrapped__(tmp_path) == UNKNOWN
