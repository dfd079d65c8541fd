"""Vendored real data (issue 50 item 4): every folder under tests/fixtures/real has its licence and its
source note, and is listed in the one table of them (docs/real-data.md)."""

from __future__ import annotations

from shared.paths import REPO_ROOT

FIXTURES = REPO_ROOT / "tests" / "fixtures" / "real"
TABLE = REPO_ROOT / "docs" / "real-data.md"


def test_every_real_fixture_has_its_licence_source_and_row() -> None:
    folders = sorted(p for p in FIXTURES.iterdir() if p.is_dir())
    assert folders, "no real fixtures"
    table = TABLE.read_text()
    for folder in folders:
        assert any((folder / n).is_file() for n in ("LICENSE", "LICENSE.md")), f"{folder}: no licence"
        source = folder / "SOURCE.md"
        assert source.is_file(), f"{folder}: no SOURCE.md"
        assert "commit" in source.read_text(), f"{source}: says no commit"
        assert f"`tests/fixtures/real/{folder.name}/`" in table, f"{folder.name}: not in {TABLE.name}"
